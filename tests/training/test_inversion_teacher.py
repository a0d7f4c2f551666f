from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import fcemu.evaluation.runner as runner
from fcemu.evaluation.metrics import AXES, compute_metrics
from fcemu.firmware.action import action_to_pwm
from fcemu.firmware.observation import (
    MOTOR_OUTPUT,
    RATE,
    RATE_ERROR,
    ROTOR_SPEED,
    ObservationSpec,
    observe_step,
)
from fcemu.sim_bridge.airframe import load_airframe
from fcemu.sim_bridge.plant import body_torque
from fcemu.sim_bridge.tasks import OMEGA_MAX
from fcemu.training.inversion_teacher import (
    SATURATED_YAW_SPEED,
    InversionController,
    InversionModel,
    InversionTeacher,
    axis_speeds,
    max_scale,
)


def test_max_scale_is_the_largest_share_some_collective_keeps_inside_every_motors_reach():
    rng = np.random.default_rng(3)
    lo, hi = -rng.uniform(0, 1, (200, 4)), rng.uniform(0, 1, (200, 4))
    delta = rng.normal(0, 2, (200, 4))
    s = max_scale(lo, hi, delta)

    def fits(scale: np.ndarray) -> np.ndarray:  # is there a c with lo ≤ s·δ + c ≤ hi on every motor?
        moved = scale[:, None] * delta
        return (lo - moved).max(-1) <= (hi - moved).min(-1) + 1e-9

    assert np.all((s >= 0.0) & (s <= 1.0)) and np.all(fits(s))
    short = s < 1.0
    assert short.any() and not np.any(fits(np.minimum(s + 1e-3, 1.0))[short])


def test_the_teacher_acts_on_its_observation_as_on_the_signals_and_keeps_the_collective_at_the_throttle():
    teacher = InversionTeacher("iris")
    rng = np.random.default_rng(1)
    hover = teacher.throttle * teacher.model.w_max
    setpoint, gyro = rng.uniform(-3, 3, (64, 3)), rng.uniform(-3, 3, (64, 3))
    rotor = hover + rng.uniform(-20, 20, (64, 4))
    action = teacher.act(observe_step(teacher.spec, setpoint, gyro, rotor))
    assert teacher.spec.fields == ("rate_error", "rotor_speed", "rate") and action.shape == (64, 4)
    assert np.all(np.abs(action) <= 1.0)
    # Small errors near hover: a mix the action mapping gives (inside the range, within its half
    # range of the mean, the collective at the throttle), so the action gives back the teacher's PWM.
    setpoint, gyro, rotor = setpoint * 0.002, gyro * 0.002, hover + rng.uniform(-0.5, 0.5, (64, 4))
    pwm = teacher.pwm(setpoint - gyro, gyro, rotor, teacher.throttle)
    action = teacher.act(observe_step(teacher.spec, setpoint, gyro, rotor))
    u = (pwm - 1000.0) / 1000.0
    fits = ((u > 0.0) & (u < 1.0)).all(-1) & (np.abs(u - u.mean(-1, keepdims=True)) <= 0.5).all(-1)
    fits &= np.abs(u.mean(-1) - teacher.throttle) < 1e-3
    assert fits.sum() >= 32
    given = action_to_pwm("throttle", action, teacher.throttle)
    np.testing.assert_allclose(given[fits], pwm[fits], atol=0.05)
    quiet = teacher.pwm(np.zeros((1, 3)), np.zeros((1, 3)), np.full((1, 4), hover), teacher.throttle)
    np.testing.assert_allclose(quiet, 1000.0 + 1000.0 * teacher.throttle, atol=1e-6)


def test_the_teacher_reads_each_signal_from_the_columns_its_spec_declares_for_it():
    teacher = InversionTeacher("iris")
    assert teacher.spec.columns == {RATE_ERROR: slice(0, 3), ROTOR_SPEED: slice(3, 7), RATE: slice(7, 10)}
    rng = np.random.default_rng(6)
    hover = teacher.throttle * teacher.model.w_max
    setpoint, gyro = rng.uniform(-3, 3, (16, 3)), rng.uniform(-3, 3, (16, 3))
    rotor = hover + rng.uniform(-20, 20, (16, 4))
    action = teacher.act(observe_step(teacher.spec, setpoint, gyro, rotor))
    teacher.spec = ObservationSpec(memory=1, fields=(MOTOR_OUTPUT, RATE, ROTOR_SPEED, RATE_ERROR),
                                   max_rotor_speed=teacher.model.w_max)
    np.testing.assert_array_equal(teacher.act(observe_step(teacher.spec, setpoint, gyro, rotor)), action)


@pytest.mark.parametrize("airframe", ["iris", "racer5"])
def test_the_teacher_flies_the_commands_with_less_error_than_the_airframes_tuned_pid(airframe, monkeypatch):
    original = runner.load_controller
    monkeypatch.setattr(runner, "load_controller", lambda spec, *a, **k: InversionController(
        InversionTeacher(airframe)) if spec == "inversion" else original(spec, *a, **k))
    cfg = runner.EvalConfig(episodes=6, seed=11, airframe=airframe)
    teacher, pid = (compute_metrics(runner.run_controller(spec, cfg, progress=False))
                    for spec in ("inversion", "pid"))
    error = {name: sum(m.stat("error", a).mean for a in AXES)
             for name, m in (("teacher", teacher), ("pid", pid))}
    assert error["teacher"] < 0.97 * error["pid"], error
    assert all(teacher.stat("success_pct", a).mean == 100.0 for a in AXES)


def test_roll_and_pitch_are_as_fast_as_their_authority_allows_and_a_yaw_that_rides_its_range_slower():
    square = InversionModel.of(load_airframe("x500"))  # its yaw moves 0.12 rad/s in a motor lag
    assert axis_speeds(square) == pytest.approx([1.0, 1.0, SATURATED_YAW_SPEED])
    assert axis_speeds(InversionModel.of(load_airframe("crazyflie"))) == pytest.approx([1.0, 1.0, 1.0])
    racer = InversionModel.of(load_airframe("racer5"))  # motors 0.085 m out in x, 0.0675 m in y
    assert axis_speeds(racer)[:2] == pytest.approx([1.0, np.sqrt(0.085 / 0.0675)], rel=1e-3)
    teacher = InversionTeacher("racer5", 0.5)
    assert teacher.time_constant == pytest.approx(0.5 * teacher.model.lag_s / axis_speeds(racer))


def test_a_law_faster_than_its_motors_steers_under_the_braking_curve_and_overshoots_less():
    cfg = runner.EvalConfig(episodes=4, seed=2018, airframe="crazyflie")  # motors lagging 72 ms

    def fly(teacher: InversionTeacher):
        return compute_metrics(runner.run_controller("inversion", cfg, progress=False,
                                                     controller=InversionController(teacher, mapped=True)))

    braked, linear = InversionTeacher("crazyflie", 0.1), InversionTeacher("crazyflie", 0.1)
    linear.braking_jerk = np.full(3, np.inf)  # the second-order law alone
    b, lin = fly(braked), fly(linear)
    assert all(b.stat("peak_pct", a).mean < lin.stat("peak_pct", a).mean for a in AXES)
    assert sum(b.stat("error", a).mean for a in AXES) < sum(lin.stat("error", a).mean for a in AXES)
    assert b.stat("smoothness", "roll").mean < lin.stat("smoothness", "roll").mean
    # Where the law is no faster than its motors the curve lies past every command's step.
    slow = InversionTeacher("racer5", 0.5)
    assert np.all(8.0 * slow.damping**2 * slow.braking_jerk[:2] * slow.time_constant[:2] ** 2 > OMEGA_MAX)


def test_a_time_constant_that_is_not_positive_is_refused():
    with pytest.raises(ValueError, match="lag multiple"):
        InversionTeacher("iris", 0.0)


def test_the_teacher_knows_the_body_torques_the_twin_adds_damping_and_the_rotors_momentum():
    airframe = load_airframe("iris_realistic")
    model = InversionModel.of(airframe)
    rng = np.random.default_rng(4)
    rates, rotor = rng.uniform(-6, 6, (32, 3)), rng.uniform(300, 1000, (32, 4))
    torque = body_torque(rates, rotor, rotor, np.asarray(airframe.rate_damping), airframe.rotor_inertia,
                         np.asarray(airframe.spin, dtype=float), 0.001)  # no spin-up: the rotors hold
    gyroscopic = -np.cross(rates, model.inertia * rates)
    np.testing.assert_allclose(model.body_acceleration(rates, rotor), (torque + gyroscopic) / model.inertia,
                               rtol=1e-12, atol=1e-9)
    assert (model.gyro_delay_ticks, model.esc_delay_ticks) == (2, 1)
    assert InversionTeacher(airframe).ahead_ticks == 4  # its own tick, the gyro's two, the ESC's one
    assert InversionTeacher(airframe, reads_truth=True).ahead_ticks == 2
    nominal = InversionModel.of(load_airframe("iris"))
    assert not nominal.damping.any() and not nominal.rotor_inertia and not nominal.gyro_delay_ticks


def test_knowing_the_damping_and_the_delays_flies_a_damped_late_airframe_closer(monkeypatch, tmp_path):
    import dataclasses
    import json

    spec = json.loads((Path(__file__).parents[2] / "sim_bridge/airframes/iris_realistic.json").read_text())
    spec["name"] = "iris_damped_late"
    spec["effects"] = {k: v for k, v in spec["effects"].items()
                       if k in ("rate_damping_N_m_s_rad", "esc_delay_ticks", "gyro_delay_ticks")}
    spec["effects"]["rate_damping_N_m_s_rad"]["value"] = [0.15, 0.15, 0.1]
    path = tmp_path / "damped.json"
    path.write_text(json.dumps(spec))
    knowing = InversionTeacher(str(path))
    blind = InversionTeacher(str(path))
    blind.model = dataclasses.replace(blind.model, damping=np.zeros(3), rotor_inertia=0.0)
    blind.ahead_ticks = 1
    original = runner.load_controller
    teachers = {"knowing": knowing, "blind": blind}
    monkeypatch.setattr(runner, "load_controller", lambda spec, *a, **k: InversionController(
        teachers[spec]) if spec in teachers else original("pid:iris"))
    cfg = runner.EvalConfig(episodes=2, seed=11, airframe=str(path))
    error = {name: sum(compute_metrics(runner.run_controller(name, cfg, progress=False)).stat("error", a).mean
                       for a in AXES) for name in teachers}
    assert error["knowing"] < 0.9 * error["blind"], error


def test_the_yaw_the_rotors_lend_is_counted_and_yaw_rises_sooner() -> None:
    """Rotors spinning up push the body round and take it back as they return; counted in the yaw
    error the law closes on the rate that remains, so yaw rises sooner with less Error."""
    airframe = replace(load_airframe("iris"), rotor_inertia=9e-6)  # a drawn Iris's rotors
    teacher = InversionTeacher(airframe, 0.5)
    m, error, rates = teacher.model, np.array([[0.0, 0.0, 2.0]]), np.zeros((1, 3))
    w_hold = np.full((1, 4), teacher.throttle * m.w_max)
    at_hold = teacher.lent_yaw(error, rates, w_hold, teacher.throttle)  # the rotors at the holding speeds
    assert np.abs(at_hold).max() < 1e-9
    spun = w_hold + 50.0 * m.spin  # the rotors' differential turned toward +yaw
    lent = teacher.lent_yaw(error, rates, spun, teacher.throttle)
    assert lent[0, :2] == pytest.approx([0.0, 0.0])
    assert lent[0, 2] == pytest.approx(m.rotor_inertia / m.inertia[2] * 200.0, rel=1e-9)
    assert not InversionTeacher("iris").lent_yaw(error, rates, spun, teacher.throttle).any()  # no J_r

    class Unaware(InversionTeacher):
        def lent_yaw(self, error, rates, w, throttle, law=None):
            return np.zeros_like(error)

    cfg = runner.EvalConfig(episodes=6, seed=2019, airframe="iris")

    def fly(t: InversionTeacher):
        return compute_metrics(runner.run_controller("inversion", cfg, progress=False, airframe=airframe,
                                                     controller=InversionController(t, mapped=True)))

    aware, unaware = fly(teacher), fly(Unaware(airframe, 0.5))
    assert aware.stat("rise_ms", "yaw").mean < unaware.stat("rise_ms", "yaw").mean - 10.0
    assert aware.stat("error", "yaw").mean < 0.97 * unaware.stat("error", "yaw").mean


def test_a_share_of_yaw_is_served_first_while_roll_and_pitch_gather_speed_and_not_while_they_brake():
    """Served after roll and pitch, yaw waits while they take every motor's reach; with a share
    served first it moves from the first tick, but not where roll or pitch brakes (its overshoot)."""
    first, after = InversionTeacher("iris", 0.5, yaw_first=0.3), InversionTeacher("iris", 0.5)
    m = first.model
    hover = np.full((1, 4), first.throttle * m.w_max)
    thrust = m.kf * hover**2
    lo = m.kf * (hover * (1 - m.a_down)) ** 2 - thrust  # each rotor's reach by the next tick
    hi = m.kf * (hover + m.a_up * (m.w_max - hover)) ** 2 - thrust
    needed = np.array([[400.0, 0.0, 40.0]])  # a large roll and yaw step: roll alone takes the reach
    collective = np.zeros(1)

    def yaw_of(teacher: InversionTeacher, from_thrust: np.ndarray) -> float:
        return float((teacher._by_change(needed, lo, hi, collective, from_thrust) @ m.B.T)[0, 2])

    gathering = np.array([[50.0, 0.0, 0.0]])  # roll's acceleration along its need
    assert abs(yaw_of(after, gathering)) < 1e-6 * needed[0, 2]
    assert yaw_of(first, gathering) > 0.25 * max_scale(lo, hi, needed[:, 2:3] * first._alloc[:, 2])[0] * 40.0
    braking = -gathering  # roll's need against its acceleration
    assert yaw_of(first, braking) == pytest.approx(yaw_of(after, braking), abs=1e-9)
    with pytest.raises(ValueError, match="share of yaw"):
        InversionTeacher("iris", yaw_first=1.5)
