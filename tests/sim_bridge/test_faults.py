"""Faults in the twin: each acts where a real one would (the gyro's reading, the ESC telemetry, the
speed command, the thrust, the supply), and MAVLink's INJECT_FAILURE maps onto them as documented."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from fcemu.sim_bridge.faults import (
    GYRO_RANGE,
    Fault,
    FaultInjector,
    FaultSpecError,
    from_mavlink,
    mavlink_injector,
)
from fcemu.sim_bridge.twin import Twin, TwinState

HOVER = TwinState(rotor_speed=(780.0,) * 4)
PWM = np.array([1700.0, 1720.0, 1690.0, 1710.0])


def _fly(twin: Twin, fault: Fault | None, ticks: int = 60, at: int = 10, seed: int = 1) -> list:
    twin.reset(0, HOVER)
    frames = []
    for k in range(ticks):
        if k == at and fault is not None:
            twin.faults = FaultInjector(twin.dt, twin.airframe.motor.max_rotor_speed, seed)
            twin.faults.inject(fault)
        frames.append(twin.step(PWM + 30.0 * math.sin(k / 5.0)))
    twin.faults = None
    return frames


@pytest.fixture(scope="module")
def twin() -> Twin:
    return Twin(rig="rig")


def test_no_fault_changes_nothing(twin) -> None:
    clean = _fly(twin, None)
    twin.reset(0, HOVER)
    twin.faults = FaultInjector(twin.dt, 1100.0)  # present, empty
    frames = [twin.step(PWM + 30.0 * math.sin(k / 5.0)) for k in range(60)]
    twin.faults = None
    assert all(np.array_equal(a.gyro, b.gyro) and np.array_equal(a.rotor_speed, b.rotor_speed)
               for a, b in zip(clean, frames, strict=True))


def test_sensor_faults_change_the_reading_not_the_flight(twin) -> None:
    clean = _fly(twin, None)
    gyro = lambda frames: np.array([f.gyro for f in frames])  # noqa: E731
    speed = lambda frames: np.array([f.rotor_speed for f in frames])  # noqa: E731
    stuck = gyro(_fly(twin, Fault("gyro", "stuck")))
    assert np.all(stuck[10:] == gyro(clean)[10]) and np.array_equal(stuck[:10], gyro(clean)[:10])
    assert np.isnan(gyro(_fly(twin, Fault("gyro", "off")))[10:]).all()
    delayed = speed(_fly(twin, Fault("esc-telemetry", "delayed", value=0.005)))
    assert np.array_equal(delayed[20:], speed(clean)[15:-5])
    slow = gyro(_fly(twin, Fault("gyro", "slow", value=0.01)))
    assert np.array_equal(slow[10:20], np.repeat(gyro(clean)[10:11], 10, axis=0))
    wrong = gyro(_fly(twin, Fault("gyro", "wrong")))
    assert np.allclose(wrong[10:] - gyro(clean)[10:], 0.5)
    garbage = gyro(_fly(twin, Fault("gyro", "garbage")))[10:]
    assert np.all(np.abs(garbage) <= GYRO_RANGE) and np.std(garbage) > 10.0
    one = speed(_fly(twin, Fault("esc-telemetry", "intermittent", instance=3, value=0.5)))
    repeated = (one[11:, 2] == one[10:-1, 2]).sum()  # a lost frame: the last sample again
    assert repeated > 10 and np.array_equal(one[:, [0, 1, 3]], speed(clean)[:, [0, 1, 3]])
    # what the vehicle did is the same: the fault is in the reading only
    twin_truth = [f.t_us for f in _fly(twin, Fault("gyro", "garbage"))]
    assert twin_truth == [f.t_us for f in clean]


def test_every_sample_carries_the_time_a_real_bus_gives_it(twin) -> None:
    """A lost frame keeps the last sample and its time, a delayed one arrives with its true time, a
    stuck sensor reports on time; fault-free frames say nothing of their ages (sampled at t_us)."""
    clean = _fly(twin, None)
    assert all(f.gyro_t_us is None and f.rotor_speed_t_us is None for f in clean)
    assert all(f.gyro_age_us() == 0 and not f.rotor_speed_age_us().any() for f in clean)
    lost = _fly(twin, Fault("esc-telemetry", "intermittent", instance=2, value=0.5))
    ages = np.array([f.rotor_speed_age_us() for f in lost])
    assert not ages[:, [0, 2, 3]].any() and ages[10:, 1].max() >= 2000 and (ages[10:, 1] == 0).sum() > 10
    for f, g in itertools.pairwise(lost[10:]):  # held: the same sample, the same time
        if g.rotor_speed_age_us()[1]:
            assert g.rotor_speed[1] == f.rotor_speed[1] and g.rotor_speed_t_us[1] == f.rotor_speed_t_us[1]
    late = _fly(twin, Fault("esc-telemetry", "delayed", value=0.005))
    assert [f.rotor_speed_age_us().tolist() for f in late[15:]] == [[5000] * 4] * 45
    assert [f.rotor_speed_t_us[0] for f in late[15:]] == [f.t_us for f in clean[10:-5]]
    gyro_late = _fly(twin, Fault("gyro", "delayed", value=0.003))
    assert [f.gyro_age_us() for f in gyro_late[10:16]] == [0, 1000, 2000, 3000, 3000, 3000]
    slow = _fly(twin, Fault("gyro", "slow", value=0.01))
    assert [f.gyro_age_us() for f in slow[10:21]] == [*range(0, 10000, 1000), 0]
    assert all(f.gyro_age_us() == 0 for f in _fly(twin, Fault("gyro", "stuck")))
    off = _fly(twin, Fault("esc-telemetry", "off"))
    assert np.isnan(off[-1].rotor_speed).all() and off[-1].rotor_speed_age_us().tolist() == [49000] * 4


def test_bursts_lose_frames_in_runs_at_their_long_run_rate(twin) -> None:
    """Gilbert–Elliott: runs of lost frames 20 ms long on average, 5 % of frames lost in the long run."""
    injector = FaultInjector(0.001, 1100.0, seed=4)
    injector.inject(Fault("esc-telemetry", "burst", 0, 0.05, 0.02))
    lost = []
    for k in range(200_000):
        _, _, _, times = injector.read(np.zeros(3), np.full(4, float(k)), k * 1000)
        lost.append(times[0] != k * 1000)
    lost = np.array(lost)
    starts = np.flatnonzero(lost[1:] & ~lost[:-1])
    assert lost.mean() == pytest.approx(0.05, rel=0.25)
    assert lost.sum() / len(starts) == pytest.approx(20.0, rel=0.25)
    with pytest.raises(FaultSpecError):
        Fault("esc-telemetry", "burst", 0, 1.0)
    with pytest.raises(FaultSpecError):
        Fault("esc-telemetry", "intermittent", 0, 0.1, 0.02)
    assert Fault("esc-telemetry", "burst").describe() == "esc-telemetry burst 0.02 s @ 0.01"


def test_motor_faults_act_on_the_rotor(twin) -> None:
    clean = np.array([f.rotor_speed for f in _fly(twin, None)])
    off = np.array([f.rotor_speed for f in _fly(twin, Fault("motor", "off", instance=2))])
    # spun down, and its telemetry says so
    assert off[-1, 1] < 0.3 * clean[-1, 1] and np.allclose(off[:10], clean[:10])
    _fly(twin, None, ticks=1)
    twin.faults = FaultInjector(twin.dt, 1100.0)
    twin.faults.inject(Fault("motor", "thrust", instance=1, value=0.7))
    twin.step(PWM)
    ctrl = twin.data.ctrl.copy()
    speeds = twin.rotor_speed
    assert ctrl[0] == pytest.approx(0.7 * twin.motors.kf * speeds[0] ** 2)
    assert ctrl[1] == pytest.approx(twin.motors.kf * speeds[1] ** 2)
    twin.faults = None
    weak = np.array([f.rotor_speed for f in _fly(twin, Fault("battery", "wrong", value=0.75), ticks=200)])
    assert np.all(weak[-1] < 0.8 * clean[-1] * 1.05)


def test_a_payload_slows_every_axis_by_its_share_and_is_put_down_with_the_fault(twin) -> None:
    """Half the mass again: each body rate's change under the same torques is two thirds of what
    it was (inertia × 1.5), and the twin carries nothing once the fault is cleared or at reset."""
    def rates(fault: Fault | None, ticks: int) -> np.ndarray:
        return np.array([f.gyro for f in _fly(twin, fault, ticks=ticks, at=0)])

    clean, loaded = rates(None, 40), rates(Fault("payload", "mass", value=0.5), 40)
    change = lambda r: r[-1] - r[1]  # noqa: E731
    moving = np.abs(change(clean)) > 1e-3
    assert moving.any()
    np.testing.assert_allclose(change(loaded)[moving] / change(clean)[moving], 1 / 1.5, rtol=0.05)
    twin.step(PWM)  # the fault gone: the next step flies without it
    assert twin.model.body_mass[twin.model.body("base").id] == pytest.approx(twin.airframe.base_mass)
    twin.faults = FaultInjector(twin.dt, 1100.0)
    twin.faults.inject(Fault("payload", "mass"))
    twin.step(PWM)
    assert twin.model.body_mass[twin.model.body("base").id] == pytest.approx(
        twin.airframe.base_mass + 0.3 * twin.airframe.mass)
    twin.reset(0, HOVER)
    twin.faults = None
    assert twin.model.body_mass[twin.model.body("base").id] == pytest.approx(twin.airframe.base_mass)
    with pytest.raises(FaultSpecError, match="outside"):
        Fault("payload", "mass", value=4.0)


def test_mavlink_mapping() -> None:
    assert from_mavlink(0, 2, 0) == [Fault("gyro", "stuck")]
    assert from_mavlink(101, 1, 2) == [Fault("motor", "off", 2)]
    assert from_mavlink(101, 4, 1) == [Fault("motor", "thrust", 1)]
    assert from_mavlink(101, 6, 3) == [Fault("esc-telemetry", "delayed", 3)]
    assert from_mavlink(100, 4, 0) == [Fault("battery", "wrong")]
    assert from_mavlink(101, 0, 0) == []
    assert isinstance(from_mavlink(4, 1, 0), str) and isinstance(from_mavlink(100, 2, 0), str)
    assert isinstance(from_mavlink(101, 1, 7), str) and isinstance(from_mavlink(0, 9, 0), str)
    with pytest.raises(FaultSpecError):
        Fault("motor", "thrust", 1, 1.5)
    twin = Twin(rig="rig")
    inject = mavlink_injector(twin)
    assert inject(101, 2, 1) == (True, "esc-telemetry 1 stuck")
    assert inject(0, 1, 0)[0] and len(twin.faults.faults) == 2
    assert inject(101, 0, 0)[0] and [f.target for f in twin.faults.faults] == ["gyro"]
    assert inject(0, 0, 0)[0] and not twin.faults
