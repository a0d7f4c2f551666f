"""Flight tasks on their own (HOLD, LAND), and HOLD closed-loop with the PID in the MuJoCo twin."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fcemu.firmware.controller import RateSetpoint
from fcemu.firmware.estimator import AttitudeEstimator
from fcemu.firmware.loop import FlightLoop, TickSample
from fcemu.firmware.params import ParamTable
from fcemu.firmware.pid_controller import PIDRateController
from fcemu.firmware.sensors import SensorFrame
from fcemu.firmware.timing import LockstepClock
from fcemu.firmware.vehicle import HOLD, IN_AIR, OFFBOARD, ON_GROUND, Vehicle
from fcemu.firmware.vehicle.flight_tasks import (
    FlightInputs,
    HoldTask,
    LandTask,
    OffboardTask,
    PositionFix,
    tilt_for_acceleration,
)
from fcemu.firmware.vehicle.land_detector import LandDetector
from fcemu.firmware.vehicle.param_adapter import VehicleSettings

REST = SensorFrame(0, np.zeros(3), np.array([0.0, 0.0, -9.81]), np.zeros(4))
HOVER = ParamTable()["MPC_THR_HOVER"]


def inputs() -> FlightInputs:
    inp = FlightInputs(AttitudeEstimator(), VehicleSettings.from_params(ParamTable()), LandDetector(), REST)
    inp.estimator.level_from_accel(0.0, 0.0, -9.81)
    return inp


def fix(t_us: int, position=(0.0, 0.0, -5.0), velocity=(0.0, 0.0, 0.0)) -> PositionFix:
    return PositionFix(t_us, position, velocity)


def test_hold_without_a_position_fix_holds_level_and_zero_vertical_speed() -> None:
    inp = inputs()
    hold = HoldTask(inp)
    hold.activate(0, on_ground=False, failsafe=False)
    sp = hold.update(1000)
    assert sp.throttle == pytest.approx(HOVER) and np.allclose(sp.rates, 0.0)
    inp.estimator.vz = 1.0  # sinking at 1 m/s: more thrust
    assert hold.update(2000).throttle == pytest.approx(HOVER + 0.12)
    inp.estimator.vz = -1.0  # rising: less
    assert hold.update(3000).throttle == pytest.approx(HOVER - 0.12)
    assert hold.landed_state == IN_AIR


def test_hold_with_a_position_fix_brakes_then_holds_where_it_stopped() -> None:
    inp = inputs()
    hold = HoldTask(inp)
    hold.activate(0, on_ground=False, failsafe=False)
    inp.fix = fix(0, velocity=(2.0, 0.0, -1.0))  # flying north and climbing: brake
    sp = hold.update(1000)
    assert hold.target is None and sp.rates[1] > 0.3  # pitch up
    assert sp.throttle == pytest.approx(HOVER - 0.12)  # climbing at 1 m/s: less thrust
    inp.fix = fix(1000)  # stopped
    hold.update(1000)
    assert hold.target == (0.0, 0.0, -5.0)
    inp.fix = fix(2000, position=(1.0, 0.0, -5.0))  # drifted 1 m north: pitch up to go back south
    sp = hold.update(2000)
    assert sp.rates[1] > 0.3 and abs(sp.rates[0]) < 1e-9
    inp.fix = fix(3000, position=(0.0, 1.0, -5.0))  # 1 m east: roll left
    sp = hold.update(3000)
    assert sp.rates[0] < -0.3 and abs(sp.rates[1]) < 1e-9
    inp.fix = fix(4000, position=(0.0, 0.0, -4.0))  # 1 m low: climb
    assert hold.update(4000).throttle == pytest.approx(HOVER + 0.12)
    # a stale fix is not used: vertical speed from the estimator, level
    sp = hold.update(4000 + 300_000)
    assert sp.throttle == pytest.approx(HOVER) and np.allclose(sp.rates, 0.0)


def test_tilt_for_acceleration_follows_heading() -> None:
    roll, pitch = tilt_for_acceleration(2.0, 0.0, 0.0)  # accelerate north facing north: nose down
    assert pitch < 0 and roll == 0
    roll, pitch = tilt_for_acceleration(2.0, 0.0, math.pi / 2)  # facing east: north is to the left
    assert roll < 0 and abs(pitch) < 1e-9
    assert max(map(abs, tilt_for_acceleration(100.0, 100.0, 0.3))) <= math.radians(20.0) + 1e-12


def test_hold_entered_on_the_ground_stays_there_at_idle() -> None:
    inp = inputs()
    hold = HoldTask(inp)
    hold.activate(0, on_ground=True, failsafe=False)
    inp.fix = fix(0, position=(0.0, 0.0, 0.0))
    assert hold.update(1000).throttle == 0.0 and hold.landed_state == ON_GROUND


def test_offboard_on_the_ground_stays_there_through_a_jolt_until_the_thrust_rises() -> None:
    """Disarm is allowed once ON_GROUND is reported: a jolt on one tick must not take it back."""
    inp = inputs()
    task = OffboardTask(inp)
    task.activate(0, on_ground=False, failsafe=False)
    inp.offboard = RateSetpoint(np.zeros(3), 0.0)
    jolt = SensorFrame(0, np.array([0.5, 0.0, 0.0]), np.array([0.0, 0.0, -11.0]), np.zeros(4))
    inp.frame = jolt  # at idle but bouncing: not yet landed
    task.update(1000)
    assert task.landed_state == IN_AIR
    inp.frame = REST
    task.update(2000)
    assert task.landed_state == ON_GROUND
    inp.frame = jolt
    task.update(3000)
    assert task.landed_state == ON_GROUND
    inp.offboard = RateSetpoint(np.zeros(3), HOVER)
    task.update(4000)
    assert task.landed_state == IN_AIR
    inp.offboard = RateSetpoint(np.zeros(3), 0.0)
    task.update(5000)
    assert task.landed_state == IN_AIR  # still jolting: the latch was released by the thrust
    task.activate(6000, on_ground=True, failsafe=False)
    assert task.landed_state == ON_GROUND


def test_land_task_holds_for_a_failsafe_then_descends_and_sees_touchdown() -> None:
    inp = inputs()
    land = LandTask(inp)
    land.activate(0, on_ground=False, failsafe=True)
    assert land.update(500_000).throttle == pytest.approx(HOVER) and land.landed_state == IN_AIR
    sp = land.update(1_000_000)  # FS_HOLD_T 1 s: descending at FS_DESC_SPD 0.7 m/s from rest
    assert sp.throttle == pytest.approx(HOVER - 0.12 * 0.7) and not land.touchdown
    t = 1_000_000
    while not land.touchdown and t < 5_000_000:  # on the ground, vz stays 0
        t += 1000
        land.update(t)
    assert land.touchdown == "landed" and t == pytest.approx(1_000_000 + 1_500_000, abs=2000)


class PositionSource:
    """The free rig's position, fed to the vehicle at 50 Hz as the SITL does; records the track."""

    def __init__(self, vehicle: Vehicle, twin) -> None:
        self.vehicle, self.twin = vehicle, twin
        self.track: list[tuple[int, np.ndarray]] = []

    def publish(self, sample: TickSample) -> None:
        if sample.t_us % 20_000 == 0:
            truth = self.twin.truth()
            self.vehicle.position_fix(tuple(truth.position.tolist()), tuple(truth.velocity.tolist()))
            self.track.append((sample.t_us, truth.position.copy()))


@pytest.mark.parametrize("with_fix", [True, False])
def test_hold_in_the_free_twin_keeps_altitude_after_a_climb(with_fix: bool) -> None:
    from fcemu.sim_bridge.airframe import load_airframe
    from fcemu.sim_bridge.link import InProcessLink
    from fcemu.sim_bridge.twin import Twin

    twin = Twin(rig="free")
    link = InProcessLink(twin)
    hover = load_airframe().hover_throttle()
    params = ParamTable()
    params.set_default("MPC_THR_HOVER", hover)
    pid = PIDRateController.from_preset()
    vehicle = Vehicle(params, {"pid": pid})
    source = PositionSource(vehicle, twin)
    loop = FlightLoop(link, link.reset(seed=0), {"pid": pid}, vehicle, LockstepClock(), 1000.0,
                      [source] if with_fix else [], fallback="pid")
    loop.tick(0)
    vehicle.offboard_setpoint((0.0, 0.0, 0.0), min(1.0, hover + 0.1))
    assert vehicle.request_mode(OFFBOARD)[0] == 0 and vehicle.request_arm(True)[0] == 0
    for k in range(1500):  # climb for 1.5 s
        vehicle.offboard_setpoint((0.0, 0.0, 0.0), min(1.0, hover + 0.1))
        loop.tick(1000 * (k + 1))
    entered = twin.truth().position.copy()
    assert entered[2] < -0.5 and twin.truth().velocity[2] < -0.5  # climbing
    assert vehicle.request_mode(HOLD)[0] == 0 and vehicle.mode == HOLD
    positions = []
    for k in range(1500, 6500):  # 5 s of HOLD
        loop.tick(1000 * (k + 1))
        positions.append(twin.truth().position.copy())
    track = np.array(positions)
    settled = track[-2000:]  # the last 2 s
    assert vehicle.armed and vehicle.landed_state == IN_AIR
    vz = (settled[-1, 2] - settled[0, 2]) / 2.0
    if with_fix:  # stopped within a few metres of where HOLD began, then altitude and position held
        target = np.array(vehicle.tasks[HOLD].target)
        assert abs(target[2] - entered[2]) < 3.0 and np.abs(target[:2] - entered[:2]).max() < 0.5
        assert np.ptp(settled[:, 2]) < 0.1 and abs(vz) < 0.03, (np.ptp(settled[:, 2]), vz)
        assert np.abs(settled - target).max() < 0.2
    else:  # the IMU alone: the climb stopped, what remains is the estimate's error (a slow drift)
        assert abs(vz) < 0.3, vz
    assert not loop.faults
