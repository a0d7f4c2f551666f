import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from fcemu.firmware.action import DEFAULT_ACTION_MAPPING, action_to_pwm
from fcemu.firmware.observation import observe_step
from fcemu.sim_bridge.env import RateControlEnv
from fcemu.sim_bridge.tasks import OMEGA_MAX, episodic_commands
from fcemu.sim_bridge.twin import SensorNoise


def _rollout(env: RateControlEnv, seed: int, steps: int, actions: np.ndarray) -> dict[str, np.ndarray]:
    obs, _ = env.reset(seed=seed)
    out: dict[str, list] = {"obs": [obs], "reward": [], "rate": [], "setpoint": []}
    for k in range(steps):
        obs, r, term, trunc, info = env.step(actions[k % len(actions)])
        out["obs"].append(obs)
        out["reward"].append(r)
        out["rate"].append(info["rate"])
        out["setpoint"].append(info["setpoint"])
        if term or trunc:
            obs, _ = env.reset()
            out["obs"].append(obs)
    return {k: np.array(v) for k, v in out.items()}


@pytest.mark.parametrize("task", ["episodic", "continuous"])
@pytest.mark.parametrize("memory", [1, 3])
def test_check_env(task, memory):
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*infinity.*")  # the paper's observations are unbounded
        check_env(RateControlEnv(task=task, memory=memory, episode_s=0.2), skip_render_check=True)


def test_registered_ids():
    for env_id, task in (("fcemu/RateEpisodic-v0", "episodic"), ("fcemu/RateContinuous-v0", "continuous")):
        env = gym.make(env_id, memory=2)
        assert env.unwrapped.config.task == task
        assert env.observation_space.shape == (14,)
        assert env.action_space.shape == (4,) and env.action_space.dtype == np.float32
        env.reset(seed=0)
        env.step(env.action_space.sample())


def test_the_env_maps_actions_as_training_does_by_default():
    assert RateControlEnv().config.action_mapping == DEFAULT_ACTION_MAPPING == "throttle"


def test_reward_formula_on_a_known_state():
    env = RateControlEnv(action_mapping="gymfc")  # the paper's mapping: an action is a motor's PWM
    obs, info = env.reset(seed=4)
    sp = info["setpoint"]
    # at rest the gyro reads zero, so the observed error is the command itself
    np.testing.assert_allclose(obs[:3], sp / 5.24, rtol=1e-6)
    np.testing.assert_allclose(obs[3:], 0.0)
    _, reward, _, _, info = env.step(np.array([0.2, -0.1, 0.4, 0.0], dtype=np.float32))
    err = sum(abs(float(s) - float(r)) for s, r in zip(info["setpoint"], info["rate"], strict=True))
    assert reward == pytest.approx(-min(err / (3 * 5.24), 1.0), abs=1e-15)
    assert reward == info["paper_reward"]
    np.testing.assert_array_equal(info["pwm"], [1600.0, 1450.0, 1700.0, 1500.0])


def test_observation_is_observe_step_of_the_frame():
    env = RateControlEnv(memory=3)
    env.reset(seed=1)
    rng = np.random.default_rng(0)
    steps = []
    for _ in range(3):
        obs, _, _, _, info = env.step(rng.uniform(-1, 1, 4).astype(np.float32))
        steps.append(observe_step(env.obs_spec, info["setpoint"], info["gyro"], env.twin.rotor_speed))
    np.testing.assert_array_equal(obs, np.concatenate(steps[::-1]))  # newest first
    assert obs.dtype == np.float32


def test_seeding_reproduces_and_seeds_differ():
    actions = np.random.default_rng(0).uniform(-1, 1, (37, 4)).astype(np.float32)
    kw = dict(episode_s=0.1)
    a = _rollout(RateControlEnv(**kw), 5, 250, actions)
    b = _rollout(RateControlEnv(**kw), 5, 250, actions)
    c = _rollout(RateControlEnv(**kw), 6, 250, actions)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert not np.array_equal(a["setpoint"], c["setpoint"])


def test_episodic_setpoints_match_the_evaluation_commands():
    env = RateControlEnv(episode_s=0.002)
    sps = [env.reset(seed=11 if i == 0 else None)[1]["setpoint"] for i in range(5)]
    np.testing.assert_array_equal(np.array(sps), episodic_commands(11, 5))


@pytest.mark.parametrize(("task", "episode_s", "n"), [("episodic", None, 1000), ("continuous", 0.5, 500)])
def test_episode_length_truncates_never_terminates(task, episode_s, n):
    env = RateControlEnv(task=task, episode_s=episode_s)
    env.reset(seed=0)
    a = np.zeros(4, dtype=np.float32)
    for k in range(1, n + 1):
        _, _, term, trunc, _ = env.step(a)
        assert not term
        assert trunc == (k == n)


def test_setpoints_bounded_episodic_constant_continuous_pulsed():
    env = RateControlEnv()
    for seed in range(20):
        env.reset(seed=seed)
        sp = env.episode.setpoints
        assert np.abs(sp).max() <= OMEGA_MAX and (sp == sp[0]).all()
    env = RateControlEnv(task="continuous", episode_s=10.0, omega_max=3.0)
    env.reset(seed=0)
    sp = env.episode.setpoints
    assert sp.shape == (10_001, 3) and np.abs(sp).max() <= 3.0
    assert not sp[0].any() and len(np.unique(sp[:, 0])) > 5  # starts at rest, then pulses


def _response(env: RateControlEnv, seed: int) -> np.ndarray:
    env.reset(seed=seed)
    a = np.array([0.3, 0.5, -0.2, 0.1], dtype=np.float32)
    return np.array([env.step(a)[4]["rate"] for _ in range(150)])


def test_randomisation_changes_dynamics_and_is_seeded():
    rand = {"mass": 0.3, "inertia": 0.3, "kf": 0.2, "km": 0.3}
    env = RateControlEnv(randomize=rand)
    nominal = _response(RateControlEnv(), 3)
    first = _response(env, 3)
    factors = dict(env.episode.factors)
    assert set(factors) == set(rand)
    assert all(abs(factors[k] - 1.0) <= rand[k] for k in rand)
    assert not np.allclose(first, nominal, rtol=1e-3)
    again = _response(RateControlEnv(randomize=rand), 3)
    np.testing.assert_array_equal(first, again)
    np.testing.assert_allclose(env.twin.airframe.base_mass, 1.5 * factors["mass"])
    env.reset()
    assert env.episode.factors != factors  # redrawn per episode


def test_throttle_mapping_draws_throttle_per_episode():
    env = RateControlEnv(action_mapping="throttle", throttle=(0.4, 0.6))
    a = np.array([0.5, -0.5, 0.2, -0.2], dtype=np.float32)
    seen = set()
    for seed in range(5):
        env.reset(seed=seed)
        t = env.episode.throttle
        assert 0.4 <= t <= 0.6
        seen.add(t)
        info = env.step(a)[4]
        np.testing.assert_array_equal(info["pwm"], action_to_pwm("throttle", a, t))
    assert len(seen) == 5
    hover = RateControlEnv(action_mapping="throttle")
    hover.reset(seed=0)
    assert hover.episode.throttle == pytest.approx((hover.twin.airframe.hover_pwm() - 1000) / 1000)


def test_noise_reaches_observation_not_reward():
    env = RateControlEnv(noise=SensorNoise(gyro_std=0.05, rotor_speed_std=5.0))
    env.reset(seed=0)
    _, reward, _, _, info = env.step(np.zeros(4, dtype=np.float32))
    assert not np.allclose(info["gyro"], info["rate"])
    assert reward == pytest.approx(float(-np.abs(info["setpoint"] - info["rate"]).sum() / (3 * 5.24)))
    a = _rollout(RateControlEnv(noise=SensorNoise(gyro_std=0.05)), 2, 50, np.zeros((1, 4), np.float32))
    b = _rollout(RateControlEnv(noise=SensorNoise(gyro_std=0.05)), 2, 50, np.zeros((1, 4), np.float32))
    np.testing.assert_array_equal(a["obs"], b["obs"])


def test_action_rate_penalty_is_reported_separately():
    env = RateControlEnv(action_rate_penalty=0.5)
    env.reset(seed=0)
    _, r0, _, _, info0 = env.step(np.zeros(4, dtype=np.float32))
    assert info0["action_rate"] == 0.0 and r0 == info0["paper_reward"]
    _, r1, _, _, info1 = env.step(np.array([1.0, 1.0, -1.0, 0.0], dtype=np.float32))
    assert info1["action_rate"] == pytest.approx((0.5 + 0.5 + 0.5 + 0.0) / 4)
    assert r1 == pytest.approx(info1["paper_reward"] - 0.5 * info1["action_rate"])


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="task"):
        RateControlEnv(task="hover")
    with pytest.raises(ValueError, match="randomise"):
        RateControlEnv(randomize={"drag": 0.1})
    with pytest.raises(ValueError, match="memory"):
        RateControlEnv(memory=0)
    with pytest.raises(RuntimeError, match="reset"):
        RateControlEnv().step(np.zeros(4, dtype=np.float32))
