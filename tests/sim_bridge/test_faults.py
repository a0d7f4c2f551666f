"""Faults in the twin: each acts where a real one would (the gyro's reading, the ESC telemetry, the
speed command, the thrust, the supply), and MAVLink's INJECT_FAILURE maps onto them as documented."""

from __future__ import annotations

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
    assert np.isnan(one[10:, 2]).sum() > 10 and not np.isnan(one[:, [0, 1, 3]]).any()
    # what the vehicle did is the same: the fault is in the reading only
    twin_truth = [f.t_us for f in _fly(twin, Fault("gyro", "garbage"))]
    assert twin_truth == [f.t_us for f in clean]


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
