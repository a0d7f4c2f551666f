"""What a real airframe adds to the twin: each effect's sign and size against a hand calculation."""

from __future__ import annotations

import json
from dataclasses import replace

import mujoco
import numpy as np
import pytest

from fcemu.sim_bridge.airframe import EFFECT_KEYS, effect_fields, load_airframe
from fcemu.sim_bridge.env import RateControlEnv
from fcemu.sim_bridge.plant import AirframeEffects, DelayLine, MotorModel, body_torque
from fcemu.sim_bridge.twin import Twin, TwinState, hover_state
from fcemu.sim_bridge.vec_env import BatchedRateEnv
from tests.sim_bridge.test_vec_env import _assert_matches_single_envs

IRIS = load_airframe("iris")
REALISTIC = load_airframe("iris_realistic")
DT = 0.001


def rig_inertia(twin: Twin) -> np.ndarray:
    """The rig's 3×3 inertia about the ball joint (body FLU axes), from MuJoCo's mass matrix."""
    m = np.zeros((3, 3))
    for i in range(3):  # M·e_i, column by column
        e, col = np.zeros((3, 1)), np.zeros((3, 1))
        e[i] = 1.0
        mujoco.mj_mulM(twin.model, twin.data, col, e)
        m[:, i] = col[:, 0]
    return m


def hold(twin: Twin, omega: np.ndarray) -> np.ndarray:
    """The PWM that holds rotor speeds `omega` exactly."""
    return np.asarray(twin.airframe.motor.pwm_for_rotor_speed(omega), dtype=float)


def test_nominal_has_every_effect_off_and_the_realistic_one_every_effect_on_with_a_source():
    assert not (IRIS.body_torques or IRIS.battery_sags or IRIS.gyro_effects or IRIS.esc_delay_ticks)
    assert REALISTIC.body_torques and REALISTIC.battery_sags and REALISTIC.gyro_effects
    assert set(effect_fields()) == set(EFFECT_KEYS.values())
    for af in (IRIS, REALISTIC):
        sources = dict(af.effect_sources)
        assert set(sources) == set(effect_fields())
        assert all(len(s) > 10 for s in sources.values())
    for name in effect_fields():
        # full 3S in both; the telemetry on time in both (a late bus is a fault or a training range)
        # nor a centre of mass off the rotors' centre: a trim is a real quad's own, read from its log
        if name not in ("battery_voltage_full", "battery_drawn_at_start", "esc_telemetry_delay_ticks",
                        "centre_of_mass_offset"):
            assert getattr(REALISTIC, name) != getattr(IRIS, name), name
    # the realistic airframe is the nominal one plus effects
    assert REALISTIC.mass == IRIS.mass and REALISTIC.motor == IRIS.motor


def test_unknown_effect_and_fractional_ticks_are_refused(tmp_path):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({"base": "iris", "name": "bad", "effects": {"wind": {"value": 1}}}))
    with pytest.raises(ValueError, match="unknown effect 'wind'"):
        load_airframe(path)
    half_tick = {"esc_delay_ticks": {"value": 1.5}}
    path.write_text(json.dumps({"base": "iris", "name": "bad", "effects": half_tick}))
    with pytest.raises(ValueError, match="whole number of ticks"):
        load_airframe(path)
    every_frame_lost = {"esc_telemetry_loss_fraction": {"value": 1.0}}
    path.write_text(json.dumps({"base": "iris", "name": "bad", "effects": every_frame_lost}))
    with pytest.raises(ValueError, match="below 1"):
        load_airframe(path)


def test_each_effect_field_can_be_drawn():
    drawn = replace(IRIS, rate_damping=(0.1, 0.1, 0.1), esc_delay_ticks=2, battery_resistance=0.05)
    assert drawn.rate_damping == (0.1, 0.1, 0.1) and drawn.esc_delay_ticks == 2
    scaled = REALISTIC.scaled(mass=1.1, kf=0.9)
    assert scaled.rotor_inertia == REALISTIC.rotor_inertia
    assert scaled.motor.kf == pytest.approx(0.9 * IRIS.motor.kf)


# ── aerodynamic damping ───────────────────────────────────────────────────────────────
@pytest.mark.parametrize("axis", [0, 1, 2])
def test_free_spin_decays_with_time_constant_inertia_over_damping(axis):
    damping = (0.062, 0.024, 0.016)
    twin = Twin(replace(IRIS, rate_damping=damping))
    rates = np.zeros(3)
    rates[axis] = 5.0
    twin.reset(state=TwinState(body_rates=tuple(rates)))
    tau = rig_inertia(twin)[axis, axis] / damping[axis]
    steps = 200
    for _ in range(steps):
        twin.step(np.full(4, 1000.0))
    measured = twin.truth().body_rates[axis]
    np.testing.assert_allclose(measured, 5.0 * np.exp(-steps * DT / tau), rtol=5e-3)
    undamped = Twin(IRIS)
    undamped.reset(state=TwinState(body_rates=tuple(rates)))
    for _ in range(steps):
        undamped.step(np.full(4, 1000.0))
    np.testing.assert_allclose(undamped.truth().body_rates[axis], 5.0, rtol=1e-3)  # today: no decay


def test_damping_opposes_the_rate():
    torque = body_torque(np.array([2.0, -3.0, 4.0]), np.zeros(4), np.zeros(4), np.array([0.1, 0.2, 0.3]), 0.0,
                         IRIS.spin.astype(float), DT)
    np.testing.assert_allclose(torque, [-0.2, 0.6, -1.2], rtol=1e-15)


# ── a centre of mass off the rotors' centre: the thrust turns the body ────────────────
def test_thrust_off_the_centre_of_mass_rolls_and_pitches_by_the_offset_times_the_thrust():
    thrust = np.array([1.0, 2.0, 3.0, 4.0])
    torque = body_torque(np.zeros(3), np.zeros(4), np.zeros(4), np.zeros(3), 0.0, IRIS.spin.astype(float), DT,
                         np.array([0.01, -0.02, 0.0]), thrust)
    np.testing.assert_allclose(torque, [-0.02 * 10.0, -0.01 * 10.0, 0.0], rtol=1e-15)


def test_a_centre_of_mass_to_the_right_rolls_the_hovering_twin_right():
    offset = (0.0, 0.01, 0.0)  # 1 cm right of the rotors' centre
    twin = Twin(replace(IRIS, centre_of_mass_offset=offset))
    twin.reset(state=hover_state(IRIS, IRIS.hover_throttle()))
    hover = np.full(4, IRIS.hover_pwm())
    for _ in range(50):
        twin.step(hover)
    weight = IRIS.mass * 9.81
    expected = 0.01 * weight * 0.05 / rig_inertia(twin)[0, 0]  # torque over inertia, for 50 ms
    np.testing.assert_allclose(twin.truth().body_rates[0], expected, rtol=0.05)
    assert replace(IRIS, centre_of_mass_offset=offset).body_torques


# ── rotor inertia: spin-up reaction and gyroscopic moment ─────────────────────────────
def test_spin_up_reaction_has_the_drag_torque_sign_and_size():
    spin = IRIS.spin.astype(float)
    omega = np.array([10.0, 0.0, 0.0, 0.0])  # rotor 1 is clockwise (spin −1)
    torque = body_torque(np.zeros(3), omega, np.zeros(4), np.zeros(3), 7.5e-5, spin, DT)
    np.testing.assert_allclose(torque, [0.0, 0.0, -7.5e-5 * 10.0 / DT], rtol=1e-15)
    assert np.sign(torque[2]) == np.sign(IRIS.yaw_sign[0])  # the way its drag twists the body


def test_spinning_up_the_clockwise_rotors_yaws_the_body_by_angular_momentum():
    j = 7.5e-5
    plain, spinning = Twin(IRIS), Twin(replace(IRIS, rotor_inertia=j))
    pwm = np.array([1800.0, 1000.0, 1000.0, 1800.0])  # the clockwise pair
    for _ in range(30):
        plain.step(pwm)
        spinning.step(pwm)
    gained = spinning.truth().body_rates[2] - plain.truth().body_rates[2]
    momentum = j * float(np.dot(IRIS.spin, spinning.rotor_speed))  # Σ s_i ω_i J: −ω for clockwise
    expected = momentum / rig_inertia(spinning)[2, 2]
    assert gained < 0.0  # clockwise rotors speeding up twist the body counter-clockwise: negative yaw FRD
    np.testing.assert_allclose(gained, expected, rtol=2e-2)


def test_gyroscopic_moment_rolls_right_when_pitching_up_over_counter_clockwise_rotors():
    j, w, q = 7.5e-5, 800.0, 2.0
    spin = IRIS.spin.astype(float)
    omega = np.where(spin > 0, w, 0.0)  # only the counter-clockwise pair spins: h along −z FRD (up)
    torque = body_torque(np.array([0.0, q, 0.0]), omega, omega, np.zeros(3), j, spin, DT)
    np.testing.assert_allclose(torque, [2 * j * w * q, 0.0, 0.0], rtol=1e-15)  # −Ω × h
    # in the twin: the same airframe with and without rotor inertia, pitching at q over the spinning pair
    state = TwinState(body_rates=(0.0, q, 0.0), rotor_speed=tuple(omega))
    rolls = []
    for af in (IRIS, replace(IRIS, rotor_inertia=j)):
        twin = Twin(af)
        twin.reset(state=state)
        for _ in range(20):
            twin.step(hold(twin, omega))
        rolls.append(twin.truth().body_rates[0])
    expected = 2 * j * w * q * 0.02 / rig_inertia(twin)[0, 0]
    assert rolls[1] - rolls[0] > 0.0
    np.testing.assert_allclose(rolls[1] - rolls[0], expected, rtol=3e-2)


# ── latency ───────────────────────────────────────────────────────────────────────────
@pytest.mark.parametrize("k", [1, 3])
def test_a_pwm_step_reaches_the_rotors_and_the_gyro_exactly_k_ticks_later(k):
    pwm = np.array([1700.0, 1300.0, 1700.0, 1300.0])  # rolls the rig
    runs = {}
    for name, af in {"plain": IRIS, "esc": replace(IRIS, esc_delay_ticks=k),
                     "gyro": replace(IRIS, gyro_delay_ticks=k)}.items():
        twin = Twin(af)
        frames = [twin.reset()] + [twin.step(pwm) for _ in range(40)]
        runs[name] = (np.array([f.rotor_speed for f in frames]), np.array([f.gyro for f in frames]))
    omega, gyro = runs["plain"]
    esc_omega, esc_gyro = runs["esc"]
    assert not esc_omega[: k + 1].any() and esc_omega[k + 1].all()
    np.testing.assert_array_equal(esc_omega[k:], omega[: len(omega) - k])
    np.testing.assert_allclose(esc_gyro[k:], gyro[: len(gyro) - k], rtol=1e-9, atol=1e-15)
    gyro_omega, delayed = runs["gyro"]
    np.testing.assert_array_equal(gyro_omega, omega)  # the rotors do not wait for the gyro
    np.testing.assert_array_equal(delayed[k:], gyro[: len(gyro) - k])
    np.testing.assert_array_equal(delayed[:k], np.zeros((k, 3)))  # the reading at rest, held


def test_late_esc_telemetry_arrives_k_ticks_later_with_its_true_sample_time():
    pwm = np.array([1700.0, 1300.0, 1700.0, 1300.0])
    plain, late = Twin(IRIS), Twin(replace(IRIS, esc_telemetry_delay_ticks=3))
    frames = [(plain.reset(), late.reset())] + [(plain.step(pwm), late.step(pwm)) for _ in range(20)]
    omega = np.array([p.rotor_speed for p, _ in frames])
    seen = np.array([q.rotor_speed for _, q in frames])
    np.testing.assert_array_equal(seen[3:], omega[:-3])
    # only the ESC bus is late
    np.testing.assert_array_equal([q.gyro for _, q in frames], [p.gyro for p, _ in frames])
    assert all((q.rotor_speed_age_us() == 3000).all() for _, q in frames)
    assert plain.rotor_speed.tolist() == late.rotor_speed.tolist()  # the rotors themselves are on time


def test_a_lost_esc_frame_holds_the_last_sample_with_its_old_time():
    pwm = np.array([1700.0, 1300.0, 1700.0, 1300.0])
    plain, lossy = Twin(IRIS), Twin(replace(IRIS, esc_telemetry_loss=0.3))
    frames = [(plain.reset(), lossy.reset(telemetry_seed=5))] + [(plain.step(pwm), lossy.step(pwm))
                                                                   for _ in range(400)]
    omega = np.array([p.rotor_speed for p, _ in frames])
    seen = np.array([q.rotor_speed for _, q in frames])
    age = np.array([q.rotor_speed_age_us() for _, q in frames]) // 1000
    assert 0.25 < (age > 0).mean() < 0.35  # a frame is lost with probability 0.3
    for k in range(1, len(frames)):  # each reading is the true speed of `age` ticks before
        np.testing.assert_array_equal(seen[k], omega[k - age[k], range(4)])
    again = Twin(replace(IRIS, esc_telemetry_loss=0.3))
    again.reset(telemetry_seed=5)
    np.testing.assert_array_equal([again.step(pwm).rotor_speed for _ in range(400)], seen[1:])


def test_delay_line_rows_have_their_own_delays():
    line = DelayLine(np.array([0, 2]), (2, 1), capacity=4)
    line.fill(np.zeros((2, 1)))
    out = [line.push(np.full((2, 1), float(t)))[:, 0] for t in range(1, 6)]
    np.testing.assert_array_equal(out, [[1, 0], [2, 0], [3, 1], [4, 2], [5, 3]])
    with pytest.raises(ValueError):
        line.set_delay(np.array([0]), 5)


# ── gyro noise and vibration ──────────────────────────────────────────────────────────
def test_gyro_spectrum_peaks_at_the_rotor_frequency_with_amplitude_in_omega_squared():
    a = np.array([1e-7, 1e-7, 0.5e-7])
    twin = Twin(replace(IRIS, gyro_vibration=tuple(a), gyro_noise_std=0.01))
    peaks = []
    for hz in (90.0, 130.0):
        w = 2 * np.pi * hz
        omega = np.full(4, w)  # level thrust, no net torque: the body stays still
        twin.reset(seed=3, state=TwinState(rotor_speed=tuple(omega)))
        gyro = np.array([twin.step(hold(twin, omega)).gyro for _ in range(1000)])
        spectrum = np.abs(np.fft.rfft(gyro, axis=0)) * 2 / len(gyro)
        freqs = np.fft.rfftfreq(len(gyro), DT)
        assert freqs[np.argmax(spectrum[1:, 0]) + 1] == hz
        peak = spectrum[np.searchsorted(freqs, hz)]
        np.testing.assert_allclose(peak, 4 * a * w**2, rtol=0.05)  # four rotors in phase
        residual = gyro - gyro.mean(axis=0) - 4 * a * w**2 * np.sin(w * DT * np.arange(1, 1001))[:, None]
        np.testing.assert_allclose(residual.std(axis=0), 0.01, rtol=0.1)  # the white part
        peaks.append(peak[0])
    np.testing.assert_allclose(peaks[1] / peaks[0], (130.0 / 90.0) ** 2, rtol=0.05)


def test_realistic_gyro_leaves_the_reward_judging_the_true_rate():
    clean = replace(REALISTIC, gyro_noise_std=0.0, gyro_vibration=(0.0, 0.0, 0.0), gyro_delay_ticks=0)
    envs = [RateControlEnv(airframe=af, episode_s=0.05) for af in (REALISTIC, clean)]
    for env in envs:
        env.reset(seed=0)
    action = np.array([0.5, -0.5, 0.5, -0.5], dtype=np.float32)
    for _ in range(30):
        info, truth = (env.step(action)[4] for env in envs)
        np.testing.assert_array_equal(info["rate"], truth["rate"])
        np.testing.assert_array_equal(truth["gyro"], truth["rate"])
    assert np.abs(info["gyro"] - info["rate"]).max() > 1e-3


# ── battery sag ───────────────────────────────────────────────────────────────────────
def test_max_thrust_falls_with_load_and_discharge_over_a_long_full_throttle_run():
    af = REALISTIC
    motors = MotorModel.from_spec(af.motor, DT)
    fx = AirframeEffects(replace(af, esc_delay_ticks=0), DT)
    fx.reset(np.full(4, af.motor.pwm_min))
    omega = np.zeros(4)
    thrust_at = {}
    for k in range(1, 60_001):
        omega, thrust = motors.step(omega, np.full(4, af.motor.pwm_max), speed_scale=fx.speed_scale())
        fx.advance(omega, thrust)
        if k in (1000, 60_000):
            thrust_at[k] = thrust[0]
    full = motors.max_thrust
    # at 1 s: the load alone, V = V_full − R·I with I = c·4·T^1.5 (fixed point, solved by hand)
    t = full
    for _ in range(50):
        volts = af.battery_voltage_full - af.battery_resistance * af.battery_current_per_thrust * 4 * t**1.5
        t = full * (volts / af.battery_voltage_full) ** 2
    np.testing.assert_allclose(thrust_at[1000], t, rtol=2e-3)
    assert thrust_at[1000] < 0.9 * full
    # over a minute the drawn charge lowers it further: k·Q, Q = ∫I dt ≈ the mean of I at 1 s and 60 s × 60 s
    current = {k: af.battery_current_per_thrust * 4 * t**1.5 for k, t in thrust_at.items()}
    np.testing.assert_allclose(fx.charge[0], (current[1000] + current[60_000]) / 2 * 60.0, rtol=5e-3)
    volts = (af.battery_voltage_full - af.battery_sag_per_charge * fx.charge[0]
             - af.battery_resistance * current[60_000])
    np.testing.assert_allclose(thrust_at[60_000], full * (volts / af.battery_voltage_full) ** 2, rtol=1e-3)
    assert thrust_at[60_000] < thrust_at[1000] * 0.98


def test_no_load_no_sag_and_a_part_drawn_battery_starts_lower():
    fx = AirframeEffects(REALISTIC, DT)
    fx.reset(np.full(4, 1000.0))
    assert fx.speed_scale()[0] == 1.0 == fx.speed_scale_one()
    assert not AirframeEffects(IRIS, DT).sags
    half = AirframeEffects(replace(REALISTIC, battery_drawn_at_start=9000.0), DT)
    half.reset(np.full(4, 1000.0))
    expected = 1.0 - REALISTIC.battery_sag_per_charge * 9000.0 / REALISTIC.battery_voltage_full
    np.testing.assert_allclose(half.speed_scale()[0], expected, rtol=1e-12)
    assert half.speed_scale_one() == half.speed_scale()[0]


# ── every effect on: the batch is the single environment ──────────────────────────────
def test_batch_is_bit_identical_to_single_envs_with_every_effect_on():
    kw = dict(airframe="iris_realistic", action_mapping="throttle", episode_s=0.05)
    n = 3
    ends = _assert_matches_single_envs(BatchedRateEnv(n, **kw), [RateControlEnv(**kw) for _ in range(n)],
                                       seed=4, steps=160)
    assert ends >= 2 * n


def test_realistic_airframe_changes_what_the_env_flies():
    a, b = RateControlEnv(episode_s=0.05), RateControlEnv(airframe="iris_realistic", episode_s=0.05)
    a.reset(seed=1)
    b.reset(seed=1)
    action = np.array([0.8, -0.2, 0.8, -0.2], dtype=np.float32)
    for _ in range(40):
        ia, ib = a.step(action)[4], b.step(action)[4]
    assert np.abs(ia["rate"] - ib["rate"]).max() > 0.05


def test_eval_flies_the_airframe_it_is_given():
    from fcemu.evaluation.runner import EvalConfig, run_controller

    nominal, realistic = (run_controller("pid", EvalConfig(episodes=2, seed=1, airframe=af), progress=False)
                          for af in ("iris", "iris_realistic"))
    np.testing.assert_array_equal(nominal.setpoint, realistic.setpoint)
    assert np.abs(nominal.rate - realistic.rate).max() > 0.05
    assert EvalConfig(airframe="iris_realistic").hover_throttle == EvalConfig().hover_throttle  # same body
