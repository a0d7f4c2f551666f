import numpy as np
import pytest

from fcemu.firmware.observation import observe_step
from fcemu.sim_bridge.env import RateControlEnv
from fcemu.sim_bridge.randomization import parse_randomization
from fcemu.sim_bridge.twin import SensorNoise
from fcemu.sim_bridge.vec_env import NOISE_BLOCK, BatchedRateEnv

pytestmark = pytest.mark.no_wall_clock

INFO_KEYS = ("setpoint", "rate", "gyro", "pwm", "paper_reward", "action_rate")
CONFIGS = {
    "episodic": dict(episode_s=0.05),
    "continuous-m3": dict(task="continuous", memory=3, episode_s=0.3),
    "throttle-penalty": dict(action_mapping="throttle", throttle=(0.3, 0.8), action_rate_penalty=0.2,
                             episode_s=0.05),
    # episodes longer than a noise block, so the per-copy noise streams are refilled mid-episode
    "noise": dict(noise=SensorNoise(gyro_std=0.1, gyro_bias=(0.01, 0.02, -0.03), accel_std=0.3,
                                    rotor_speed_std=4.0), episode_s=0.3),
    "randomize": dict(randomize={"mass": 0.2, "inertia": 0.3, "kf": 0.2, "km": 0.3}, episode_s=0.05),
    # the penalty's gate counts each copy's held setpoint across pulses and auto-resets
    "gated-penalty": dict(task="continuous", action_rate_penalty=0.5, action_rate_after_s=0.02,
                          episode_s=0.3),
    # the integrator state lives in ObservationHistory: restarted per copy on auto-reset
    "integral-m2": dict(memory=2, obs_fields=("rate_error", "rotor_speed", "rate_error_integral"),
                        action_mapping="throttle", episode_s=0.05),
    "rms-m2": dict(memory=2, obs_fields=("rate_error", "rotor_speed", "rate_error_rms"), rms_leak=0.9,
                   action_mapping="throttle", episode_s=0.05),
    # each copy's previous output, from the rotors at its (auto-)reset
    "motor-output-m2": dict(memory=2, obs_fields=("rate_error", "rotor_speed", "motor_output"),
                            action_mapping="throttle", episode_s=0.05, action_rate_penalty=0.5),
    # half the episodes start in flight: rotors at the throttle's speed, the ESC line holding its command
    "inflight-half": dict(action_mapping="throttle", inflight_share=0.5, episode_s=0.05),
    "inflight-realistic": dict(airframe="iris_realistic", action_mapping="throttle", inflight_share=0.5,
                               episode_s=0.05),
    "inflight-randomised": dict(randomize="iris_esc2", action_mapping="throttle", inflight_share=0.5,
                                episode_s=0.05),
    # ESC telemetry late and lossy, the gyro late, per copy; episodes past a block of loss draws; some nominal
    "telemetry": dict(randomize=parse_randomization({"airframe": "iris", "parameters": {
        "esc_telemetry_delay_ticks": {"nominal": 0, "range": [0, 5], "unit": "ticks", "source": "test"},
        "esc_telemetry_loss": {"nominal": 0, "range": [0, 0.4], "unit": "share", "source": "test"},
        "gyro_delay_ticks": {"nominal": 0, "range": [0, 3], "unit": "ticks", "source": "test"}}}),
        randomize_share=0.7, action_mapping="throttle", inflight_share=0.5, episode_s=0.3),
    # the in-flight authority estimate: its state per copy, started over on each copy's auto-reset
    "authority-m2": dict(memory=2, obs_fields=("rate_error", "rotor_speed", "authority"),
                         action_mapping="throttle", inflight_share=0.5, episode_s=0.05),
    # each copy's loop delay as its firmware is configured with it, drawn per episode; some nominal
    "loop-delay": dict(randomize=parse_randomization({"airframe": "iris", "parameters": {
        "esc_delay_ticks": {"nominal": 0, "range": [0, 2], "unit": "ticks", "source": "test"},
        "gyro_delay_ticks": {"nominal": 0, "range": [0, 3], "unit": "ticks", "source": "test"}}}),
        randomize_share=0.7, memory=2, obs_fields=("rate_error", "rotor_speed", "loop_delay"),
        action_mapping="throttle", episode_s=0.05),
}


def _assert_matches_single_envs(batch: BatchedRateEnv, singles: list[RateControlEnv], seed: int,
                                steps: int) -> int:
    """Step a batch and single envs seeded seed + i with the same actions; return the episode ends seen."""
    obs, _ = batch.reset(seed=seed)
    np.testing.assert_array_equal(obs, [e.reset(seed=seed + i)[0] for i, e in enumerate(singles)])
    rng = np.random.default_rng(99)
    ends = 0
    for k in range(steps):
        actions = rng.uniform(-1.2, 1.2, (len(singles), 4)).astype(np.float32)
        obs, reward, terminated, truncated, info = batch.step(actions)
        assert not terminated.any()
        for i, env in enumerate(singles):
            o, r, _, trunc, inf = env.step(actions[i])
            assert trunc == truncated[i], (k, i)
            for key in INFO_KEYS:
                np.testing.assert_array_equal(info[key][i], inf[key], err_msg=f"{key} step {k} env {i}")
            assert reward[i] == r, (k, i)
            if trunc:
                ends += 1
                assert info["_final_obs"][i]
                np.testing.assert_array_equal(info["final_obs"][i], o)
                o, _ = env.reset()
            np.testing.assert_array_equal(obs[i], o, err_msg=f"obs step {k} env {i}")
            if batch.on_time_observation is not None:
                np.testing.assert_array_equal(batch.on_time_observation[i], env.on_time_observation)
    return ends


def test_the_on_time_observation_is_what_the_sensors_sampled_before_their_delays_and_the_bus():
    env = RateControlEnv(on_time_view=True, **CONFIGS["telemetry"])
    nothing_late = RateControlEnv(on_time_view=True, **CONFIGS["inflight-half"])
    assert nothing_late.on_time_observation is None
    assert RateControlEnv(**CONFIGS["telemetry"]).on_time_observation is None  # not asked for
    late = 0
    for seed in range(12):
        obs, _ = env.reset(seed=seed)
        for _ in range(40):
            obs, _, _, _, info = env.step(np.full(4, 0.3, dtype=np.float32))
        sampled = observe_step(env.obs_spec, info["setpoint"], *env.twin.sampled)
        np.testing.assert_array_equal(env.on_time_observation, sampled)
        seen = observe_step(env.obs_spec, info["setpoint"], info["gyro"], env.twin.sampled[1])
        np.testing.assert_array_equal(obs[:3], seen[:3])  # the rate error of the gyro the firmware read
        late += not np.array_equal(sampled, obs)
    assert late >= 3


def test_the_truth_view_is_the_true_rates_and_rotor_speeds_without_noise_vibration_or_delay():
    env = BatchedRateEnv(3, on_time_view=True, truth_view=True, airframe="iris_realistic",
                         action_mapping="throttle", episode_s=0.05)
    env.reset(seed=2)
    for _ in range(30):
        obs, _, _, _, info = env.step(np.full((3, 4), 0.3, dtype=np.float32))
    truth = observe_step(env.obs_spec, info["setpoint"], info["rate"], env._omega)
    np.testing.assert_array_equal(env.on_time_observation, truth)
    assert not np.allclose(obs[:, :3], truth[:, :3], atol=1e-4)  # the firmware's gyro is noisy and late
    plain = BatchedRateEnv(3, truth_view=True, airframe="iris")  # a view only where one is asked for
    assert plain.on_time_observation is None


@pytest.mark.parametrize("name", CONFIGS)
def test_batch_is_bit_identical_to_single_envs_across_auto_resets(name):
    kw = CONFIGS[name]
    n = 3
    steps = 700 if kw["episode_s"] > 0.1 else 160
    ends = _assert_matches_single_envs(BatchedRateEnv(n, on_time_view=True, **kw),
                                       [RateControlEnv(on_time_view=True, **kw) for _ in range(n)],
                                       seed=10, steps=steps)
    assert ends >= 2 * n  # several auto-resets per copy
    if "noise" in kw:
        assert steps < 3 * NOISE_BLOCK and kw["episode_s"] * 1000 > NOISE_BLOCK


def test_seed_contract_is_seed_plus_index():
    batch = BatchedRateEnv(2)
    _, info = batch.reset(seed=7)
    same = RateControlEnv().reset(seed=8)[1]["setpoint"]
    np.testing.assert_array_equal(info["setpoint"][1], same)
    assert not np.array_equal(info["setpoint"][1], RateControlEnv().reset(seed=7)[1]["setpoint"])
    _, info = batch.reset(seed=[8, None])  # a list seeds each copy; None keeps its stream going
    np.testing.assert_array_equal(info["setpoint"][0], same)


def test_threaded_physics_gives_the_same_results():
    a, b = BatchedRateEnv(8, nthread=0), BatchedRateEnv(8, nthread=2)
    oa, _ = a.reset(seed=3)
    ob, _ = b.reset(seed=3)
    rng = np.random.default_rng(0)
    for _ in range(120):
        act = rng.uniform(-1, 1, (8, 4)).astype(np.float32)
        oa, ra, *_ = a.step(act)
        ob, rb, *_ = b.step(act)
    np.testing.assert_array_equal(oa, ob)
    np.testing.assert_array_equal(ra, rb)
    b.close()


def test_randomisation_is_per_copy_and_changes_dynamics():
    batch = BatchedRateEnv(4, randomize={"mass": 0.3, "inertia": 0.3}, episode_s=0.1)
    batch.reset(seed=0)
    factors = batch.episode_factors
    assert len({f["mass"] for f in factors}) == 4
    act = np.tile(np.array([0.3, 0.5, -0.2, 0.1], dtype=np.float32), (4, 1))
    for _ in range(80):
        info = batch.step(act)[4]
    rates = info["rate"]
    assert len({round(float(r), 6) for r in rates[:, 0]}) == 4


def test_bench_functions_measure_and_the_batch_is_faster():
    from fcemu.benchmarks.env import env_steps_per_s, vec_env_steps_per_s

    single = env_steps_per_s(seconds=0.3)
    batched = vec_env_steps_per_s(64, seconds=0.3)
    assert single > 1000
    assert batched > 2 * single


def test_an_episode_in_flight_starts_with_every_rotor_at_the_throttles_speed():
    from fcemu.sim_bridge.twin import hover_state

    env = RateControlEnv(action_mapping="throttle", throttle=0.6, inflight_share=0.5)
    starts = []
    for seed in range(12):
        env.reset(seed=seed)
        starts.append(env._episode.in_flight)
        speed = env._twin.rotor_speed
        expected = hover_state(env.config.base_airframe, 0.6).rotor_speed if starts[-1] else (0.0,) * 4
        np.testing.assert_allclose(speed, expected)
    assert 0 < sum(starts) < len(starts)
    with pytest.raises(ValueError, match="inflight_share"):
        RateControlEnv(inflight_share=1.5)


def test_the_loop_delay_field_is_each_copys_drawn_esc_and_gyro_delay():
    kw = CONFIGS["loop-delay"]
    env = BatchedRateEnv(8, **kw)
    seen = set()
    obs, _ = env.reset(seed=3)
    for _ in range(600):
        drawn = [f.get("esc_delay_ticks", 0) + f.get("gyro_delay_ticks", 0) for f in env.episode_factors]
        np.testing.assert_array_equal(obs[:, 7], np.float32(0.2) * np.array(drawn, dtype=np.float32))
        np.testing.assert_array_equal(obs[:, 15], obs[:, 7])  # the same in every step of the memory
        seen.update(drawn)
        obs, *_ = env.step(np.zeros((8, 4), np.float32))
    assert seen == {0, 1, 2, 3, 4, 5}


def test_a_copy_of_a_pool_of_quads_is_the_single_env_of_the_quad_it_drew():
    from fcemu.sim_bridge.airframe_draw import airframe_pool

    pool = airframe_pool("draw:3:5")  # different sizes, each with its own sensor effects
    kw = dict(action_mapping="throttle", inflight_share=0.5, memory=2, episode_s=0.2)
    batch = BatchedRateEnv(6, airframe_pool=pool, **kw)
    batch.reset(seed=10)
    flown = batch.episode_airframes
    assert len({a.name for a in flown}) > 1
    singles = [RateControlEnv(airframe=a, **kw) for a in flown]
    assert _assert_matches_single_envs(batch, singles, 10, 199) == 0  # the first episode: one quad each
    spec = batch.obs_spec
    assert spec.per_airframe_rotor_speed and singles[0].obs_spec.rotor_speed_scale != spec.rotor_speed_scale


def test_each_episode_of_a_pool_draws_its_quad_and_observes_shares_of_its_top_speed():
    env = BatchedRateEnv(4, airframe_pool="draw:5:2", action_mapping="throttle", inflight_share=1.0,
                         episode_s=0.01)
    obs, _ = env.reset(seed=0)
    seen = set()
    for _ in range(100):
        flown = env.episode_airframes
        seen.update(a.name for a in flown)
        hover = np.array([a.hover_throttle() for a in flown])
        # in flight at each quad's own hover: its rotors at that share of its own top speed
        np.testing.assert_allclose(obs[:, 3:7], np.repeat(hover[:, None], 4, 1), rtol=1e-5)
        for _ in range(10):
            obs, *_ = env.step(np.zeros((4, 4), np.float32))
    assert seen == {f"drawn_2_{i}" for i in range(5)}


def test_a_pool_is_refused_with_ranges_or_by_a_single_env():
    with pytest.raises(ValueError, match="not both"):
        BatchedRateEnv(2, airframe_pool="draw:2:1", randomize="iris")
    with pytest.raises(ValueError, match="batched environment"):
        RateControlEnv(airframe_pool="draw:2:1")
