"""The digital twin: axis signs in FRD, hover, motor lag, sensors, determinism, input checks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fcemu.firmware.sensors import SensorFrame
from fcemu.sim_bridge.twin import SensorNoise, Twin, TwinState

pytestmark = pytest.mark.timeout(60)

G = 9.81
NOISE = SensorNoise(gyro_std=0.1, gyro_bias=(0.01, -0.02, 0.03), accel_std=0.5, accel_bias=(0.1, 0.0, -0.1),
                    rotor_speed_std=5.0)


@pytest.fixture(scope="module")
def rig() -> Twin:
    return Twin(rig="rig")


def spinning_at_hover(twin: Twin, **state: object) -> None:
    twin.reset(state=TwinState(rotor_speed=(twin.airframe.hover_rotor_speed(),) * 4, **state))


def pwm_with(twin: Twin, raised: tuple[int, ...], delta: float) -> np.ndarray:
    """Hover PWM with the listed motors (1-based, Betaflight order) raised by `delta` µs."""
    pwm = np.full(4, twin.airframe.hover_pwm())
    pwm[[m - 1 for m in raised]] += delta
    return pwm


def frames(twin: Twin, pwm: np.ndarray, steps: int) -> list[SensorFrame]:
    return [twin.step(pwm) for _ in range(steps)]


AXES = {"roll": 0, "pitch": 1, "yaw": 2}


@pytest.mark.parametrize(("axis", "raised", "sign"), [
    ("roll", (3, 4), +1),  # left motors up: right wing down
    ("roll", (1, 2), -1),
    ("pitch", (2, 4), +1),  # front motors up: nose up
    ("pitch", (1, 3), -1),
    ("yaw", (2, 3), +1),  # the counter-clockwise props twist the body clockwise from above: nose right
    ("yaw", (1, 4), -1),
])
def test_each_axis_turns_the_frd_way(rig: Twin, axis: str, raised: tuple[int, ...], sign: int) -> None:
    spinning_at_hover(rig)
    gyro = frames(rig, pwm_with(rig, raised, 100.0), 50)[-1].gyro
    for rates in (gyro, rig.truth().body_rates):
        assert sign * rates[AXES[axis]] > 0.1, rates
        assert abs(rates[AXES[axis]]) == pytest.approx(np.abs(rates).max()), f"{axis} not dominant: {rates}"


@pytest.mark.parametrize("axis", list(AXES))
@pytest.mark.parametrize("sign", [+1, -1])
def test_the_papers_largest_step_is_reachable_well_inside_half_a_second(rig: Twin, axis: str,
                                                                       sign: int) -> None:
    """Ω* ~ U[-5.24, 5.24] rad/s: full differential about hover must get there in < 0.5 s."""
    hover = rig.airframe.hover_pwm()
    positive = {"roll": (3, 4), "pitch": (2, 4), "yaw": (2, 3)}[axis]
    pwm = np.array([2000.0 if (m in positive) == (sign > 0) else 2 * hover - 2000.0 for m in range(1, 5)])
    spinning_at_hover(rig)
    for frame in frames(rig, pwm, 400):
        if sign * frame.gyro[AXES[axis]] >= 5.24:
            assert frame.t_us < 400_000
            return
    pytest.fail(f"{axis} never reached {sign * 5.24} rad/s")


def test_hover_pwm_holds_the_free_body() -> None:
    twin = Twin(rig="free")
    hover = twin.airframe.hover_rotor_speed()
    twin.reset(state=TwinState(position=(0.0, 0.0, -2.0), rotor_speed=(hover,) * 4))
    pwm = np.full(4, twin.airframe.hover_pwm())
    for _ in range(500):
        twin.step(pwm)
        assert abs(twin.truth().acceleration[2]) < 0.5
    truth = twin.truth()
    assert abs(truth.velocity[2]) < 0.05 and truth.position[2] == pytest.approx(-2.0, abs=0.05)


def test_without_thrust_the_free_body_falls_at_g() -> None:
    twin = Twin(rig="free")
    twin.reset(state=TwinState(position=(0.0, 0.0, -2.0)))
    frame = twin.step(np.full(4, 1000.0))
    assert twin.truth().acceleration[2] == pytest.approx(G, abs=1e-6)  # NED: down is positive
    np.testing.assert_allclose(frame.accel, 0.0, atol=1e-6)  # free fall: no specific force


def rise_time(twin: Twin, start: float, target: float) -> float:
    """Seconds until the rotor speed covers 1 - 1/e of a commanded step (linear between samples)."""
    twin.reset(state=TwinState(rotor_speed=(start,) * 4))
    pwm = np.full(4, float(twin.airframe.motor.pwm_for_rotor_speed(target)))
    level = start + (target - start) * (1.0 - math.exp(-1.0))
    before_t, before_w = 0.0, start
    for frame in frames(twin, pwm, 200):
        t, w = frame.t_us * 1e-6, frame.rotor_speed[0]
        np.testing.assert_array_equal(frame.rotor_speed, w)  # all four motors alike
        if (w - level) * (target - start) >= 0.0:
            return before_t + (t - before_t) * (level - before_w) / (w - before_w)
        before_t, before_w = t, w
    raise AssertionError("the rotor never got there")


def test_motor_lag_matches_tau_up_and_tau_down(rig: Twin) -> None:
    motor = rig.airframe.motor
    assert rise_time(rig, 300.0, 900.0) == pytest.approx(motor.tau_up, rel=0.05)
    assert rise_time(rig, 900.0, 300.0) == pytest.approx(motor.tau_down, rel=0.05)
    assert motor.tau_down != motor.tau_up  # so the two checks do tell them apart


def test_accelerometer_reads_minus_g_level_at_rest(rig: Twin) -> None:
    frame = rig.reset()
    np.testing.assert_allclose(frame.accel, [0.0, 0.0, -G], atol=1e-9)
    for frame in frames(rig, np.full(4, 1000.0), 100):
        np.testing.assert_allclose(frame.accel, [0.0, 0.0, -G], atol=1e-9)
        np.testing.assert_allclose(frame.gyro, 0.0, atol=1e-12)
    free = Twin(rig="free")
    free.reset()
    settled = frames(free, np.full(4, 1000.0), 1000)[-1]  # on its landing gear
    np.testing.assert_allclose(settled.accel, [0.0, 0.0, -G], atol=0.05)
    np.testing.assert_allclose(settled.gyro, 0.0, atol=1e-3)


def test_accelerometer_follows_the_attitude(rig: Twin) -> None:
    roll = math.radians(30.0)  # right wing down: gravity shows on body +y... as specific force on -y
    frame = rig.reset(state=TwinState(attitude=(math.cos(roll / 2), math.sin(roll / 2), 0.0, 0.0)))
    np.testing.assert_allclose(frame.accel, [0.0, -G * math.sin(roll), -G * math.cos(roll)], atol=1e-9)
    pitch = math.radians(20.0)  # nose up: specific force leans onto +x
    frame = rig.reset(state=TwinState(attitude=(math.cos(pitch / 2), 0.0, math.sin(pitch / 2), 0.0)))
    np.testing.assert_allclose(frame.accel, [G * math.sin(pitch), 0.0, -G * math.cos(pitch)], atol=1e-9)


def run(twin: Twin, seed: int | None, pwms: np.ndarray) -> list[SensorFrame]:
    return [twin.reset(seed)] + [twin.step(p) for p in pwms]


def same(a: list[SensorFrame], b: list[SensorFrame]) -> bool:
    return all(x.t_us == y.t_us
               and all(u.tobytes() == v.tobytes() for u, v in zip(x[1:4], y[1:4], strict=True))
               for x, y in zip(a, b, strict=True))


def test_noisy_runs_repeat_exactly_with_the_same_seed() -> None:
    pwms = np.random.default_rng(0).uniform(1000.0, 2000.0, size=(200, 4))
    twin = Twin(noise=NOISE)
    first = run(twin, 3, pwms)
    assert same(run(twin, 3, pwms), first)
    assert same(run(Twin(noise=NOISE), 3, pwms), first)
    assert not same(run(twin, 4, pwms), first)


def test_noise_is_off_by_default_and_seeded_when_on(rig: Twin) -> None:
    assert not rig.noise.enabled
    pwms = np.full((50, 4), 1300.0)
    assert same(run(rig, 1, pwms), run(rig, 2, pwms))  # nothing random to seed
    noisy = Twin(noise=NOISE)
    gyro = np.array([f.gyro for f in run(noisy, 5, np.full((4000, 4), 1000.0))[1:]])  # at rest
    np.testing.assert_allclose(gyro.mean(axis=0), NOISE.gyro_bias, atol=0.01)
    np.testing.assert_allclose(gyro.std(axis=0), NOISE.gyro_std, rtol=0.1)


def test_time_advances_one_step_per_call(rig: Twin) -> None:
    assert rig.reset().t_us == 0
    assert [f.t_us for f in frames(rig, np.full(4, 1000.0), 3)] == [1000, 2000, 3000]


@pytest.mark.parametrize("bad", [
    np.array([1500.0, np.nan, 1500.0, 1500.0]), [1500.0, 1500.0, np.inf, 1500.0], [-np.inf] * 4,
    np.full(3, 1500.0), np.full(5, 1500.0), np.full((4, 1), 1500.0), np.full((2, 2), 1500.0), None, 1500.0,
], ids=["nan", "inf", "-inf", "3 values", "5 values", "4x1", "2x2", "None", "scalar"])
def test_wrong_pwm_raises_value_error_and_does_not_step(rig: Twin, bad: object) -> None:
    rig.reset()
    with pytest.raises(ValueError, match="pwm"):
        rig.step(bad)  # type: ignore[arg-type]
    assert rig.t_us == 0


def test_integer_pwm_is_pwm(rig: Twin) -> None:
    """Firmware speaks whole microseconds: an integer array must step like its float twin."""
    rig.reset()
    as_int = rig.step(np.full(4, 1600))
    rig.reset()
    assert same([as_int], [rig.step(np.full(4, 1600.0))])
    rig.reset()
    assert same([rig.step([1600, 1600, 1600, 1600])], [as_int])


@pytest.mark.slow
def test_twin_demo_json_prints_its_figures_as_one_object(tmp_path, capsys) -> None:
    import argparse
    import json

    from fcemu.sim_bridge import showcase

    assert showcase.main(argparse.Namespace(out=str(tmp_path / "demo.png"), json=True)) == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures["airframe"] == "iris" and (tmp_path / "demo.png").stat().st_size > 0
    assert set(figures["differentials"]) == {"roll", "pitch", "yaw"}
    assert all(d["peak_rate_rad_s"] > 0 for d in figures["differentials"].values())
