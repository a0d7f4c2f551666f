"""The vehicle state machine on the loop clock: arming checks, modes, setpoints, failsafe."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fcemu.firmware import vehicle as v
from fcemu.firmware.params import ParamTable
from fcemu.firmware.sensors import SensorFrame

REST = SensorFrame(0, np.zeros(3), np.array([0.0, 0.0, -9.81]), np.zeros(4))


class Dummy:
    name = "dummy"

    def reset(self) -> None: ...

    def update(self, setpoint, frame, dt):
        return np.full(4, 1500.0)


def make(**params) -> v.Vehicle:
    table = ParamTable()
    for k, val in params.items():
        assert table.set(k, val) == ""
    veh = v.Vehicle(table, {"pid": Dummy(), "neural": Dummy()})
    veh.command(0, REST)
    return veh


def run(veh: v.Vehicle, start_us: int, seconds: float, frame: SensorFrame = REST, every=None):
    t = start_us
    cmd = None
    for k in range(round(seconds * 1000)):
        t += 1000
        if every is not None:
            every(k, t)
        cmd = veh.command(t, frame._replace(t_us=t))
    return t, cmd


def test_px4_custom_mode_encoding() -> None:
    assert v.custom_mode(v.OFFBOARD) == 6 << 16 and v.custom_mode(v.LAND) == (4 << 16) | (6 << 24)
    assert v.mode_from_custom(v.custom_mode(v.ACRO)) == v.ACRO
    assert v.mode_from_custom(v.custom_mode(v.LAND)) == v.LAND


def test_arming_checks() -> None:
    veh = v.Vehicle(ParamTable(), {"pid": Dummy()})
    assert veh.request_arm(True)[0] == v.DENIED  # no sensor frame yet
    veh.command(0, REST._replace(gyro=np.array([np.nan, 0, 0])))
    assert "sensors" in veh.request_arm(True)[1]
    veh.command(1000, REST)
    veh.request_mode(v.ACRO)
    veh.sticks(0, 0, 0, 0.6)
    assert "throttle" in veh.request_arm(True)[1]
    assert veh.request_arm(True, force=True)[0] == v.ACCEPTED
    veh.request_arm(False)
    veh.sticks(0, 0, 0, 0.0)
    assert veh.request_arm(True) == (v.ACCEPTED, "") and veh.armed
    assert veh.counters["arm_denied"] == 3 and any("denied" in t for _, t in veh.outbox)


def test_offboard_only_while_setpoints_stream() -> None:
    veh = make()
    assert veh.request_mode(v.OFFBOARD)[0] == v.DENIED
    veh.offboard_setpoint((0.1, 0.2, 0.3), 0.5)
    assert veh.request_mode(v.OFFBOARD)[0] == v.ACCEPTED
    assert veh.request_arm(True)[0] == v.ACCEPTED
    _, cmd = run(veh, 0, 0.1)
    assert cmd.armed and np.allclose(cmd.setpoint.rates, (0.1, 0.2, 0.3)) and cmd.setpoint.throttle == 0.5
    assert cmd.controller == "pid"
    assert not veh.offboard_setpoint((math.nan, 0, 0), 0.5) and not veh.offboard_setpoint((0, 0, 0), 1.5)
    assert veh.counters["setpoint_rejected"] == 2
    assert veh.request_mode((4, 4))[0] == v.DENIED  # AUTO.MISSION: no missions


def test_offboard_loss_triggers_land_within_timeout_then_disarms() -> None:
    veh = make(COM_OF_LOSS_T=0.3, FS_HOLD_T=0.5)
    veh.offboard_setpoint((0, 0, 0), 0.7)
    veh.request_mode(v.OFFBOARD)
    veh.request_arm(True)
    t, _ = run(veh, 0, 1.0, every=lambda k, t: k < 500 and veh.offboard_setpoint((0, 0, 0), 0.7))
    # the last setpoint was at 0.5 s: LAND by 0.8 s
    assert veh.mode == v.LAND and veh.failsafe == "offboard setpoint loss"
    assert veh.counters["failsafe"] == 1
    _, cmd = run(veh, t, 0.01)
    assert cmd.controller == "pid" and cmd.setpoint.throttle == pytest.approx(0.745, abs=0.05)
    # on the ground at rest the vertical speed estimate is zero: touchdown after the hold + 1.5 s
    t, cmd = run(veh, t, 2.5)
    assert not veh.armed and not cmd.armed and veh.landed_state == v.ON_GROUND
    assert veh.request_mode(v.OFFBOARD)[0] == v.DENIED  # the stream is gone


def test_failsafe_time_is_the_loop_clock() -> None:
    veh = make(COM_OF_LOSS_T=0.5)
    veh.offboard_setpoint((0, 0, 0), 0.7)
    veh.request_mode(v.OFFBOARD)
    veh.request_arm(True)
    run(veh, 0, 0.45)
    assert veh.mode == v.OFFBOARD  # 0.45 s of loop time, however long that took in wall time
    run(veh, 450_000, 0.1)
    assert veh.mode == v.LAND


def test_acro_sticks_through_actual_rates_and_rc_loss() -> None:
    veh = make(COM_RC_LOSS_T=0.2)
    veh.request_mode(v.ACRO)
    veh.sticks(0, 0, 0, 0)
    veh.request_arm(True)
    veh.sticks(1.0, -0.5, 0.0, 0.6)
    t, cmd = run(veh, 0, 0.05)
    rates = veh.settings.rates.rates(1.0, -0.5, 0.0)
    assert np.allclose(cmd.setpoint.rates, rates)
    assert cmd.setpoint.rates[0] == pytest.approx(math.radians(670))
    assert cmd.setpoint.throttle == 0.6
    run(veh, t, 0.3)
    assert veh.mode == v.LAND and veh.failsafe == "manual control loss"


def test_stabilized_levels_the_vehicle() -> None:
    veh = make()
    veh.estimator.level_from_accel(0.0, -9.81 * math.sin(0.2), -9.81 * math.cos(0.2))  # rolled right
    veh.request_arm(True)
    cmd = veh.command(1000, REST)
    assert cmd.setpoint.rates[0] < -0.5  # roll back left


def test_params_switch_controller_and_reach_the_pid() -> None:
    veh = make()
    assert veh.command(1000, REST).controller == "pid"
    assert veh.set_param("CTRL_SEL", 1) == ""
    assert veh.command(2000, REST).controller == "neural"
    assert veh.set_param("CTRL_SEL", 5) and veh.counters["param_rejected"] == 1
    assert veh.set_param("COM_OF_LOSS_T", 2.0) == "" and veh.params["COM_OF_LOSS_T"] == 2.0


def test_land_mode_by_request_descends_without_hold() -> None:
    veh = make(FS_HOLD_T=5.0)
    veh.sticks(0, 0, 0, 0)
    veh.request_arm(True)
    assert veh.request_mode(v.LAND) == (v.ACCEPTED, "")
    run(veh, 0, 0.01)
    assert veh.landed_state == v.LANDING and veh.failsafe == ""


def test_disarm_in_flight_needs_force_but_not_on_the_ground() -> None:
    veh = make()
    veh.offboard_setpoint((0, 0, 0), 0.8)
    veh.request_mode(v.OFFBOARD)
    assert veh.request_arm(True)[0] == v.ACCEPTED
    climbing = REST._replace(accel=np.array([0.0, 0.0, -11.0]))
    t, _ = run(veh, 0, 0.1, frame=climbing, every=lambda k, t: veh.offboard_setpoint((0, 0, 0), 0.8))
    assert veh.request_arm(False) == (v.TEMPORARILY_REJECTED, "not landed") and veh.armed
    assert veh.counters["disarm_denied"] == 1 and any("not landed" in m for _, m in veh.outbox)
    assert veh.request_arm(False, force=True)[0] == v.ACCEPTED and not veh.armed
    # on the ground with the thrust cut, a plain disarm is accepted
    veh.request_arm(True)
    veh.offboard_setpoint((0, 0, 0), 0.0)
    run(veh, t, 0.05)
    assert veh.request_arm(False)[0] == v.ACCEPTED and not veh.armed


def test_a_failsafe_land_entered_on_the_ground_may_be_disarmed() -> None:
    veh = make(COM_RC_LOSS_T=0.2)
    veh.sticks(0, 0, 0, 0)
    assert veh.request_arm(True)[0] == v.ACCEPTED
    run(veh, 0, 0.5)  # the sticks stop: LAND, while still on the ground
    assert veh.mode == v.LAND and veh.armed
    assert veh.request_arm(False)[0] == v.ACCEPTED and not veh.armed


def test_hold_is_px4_auto_loiter_entered_and_left_by_mode_requests() -> None:
    assert v.custom_mode(v.HOLD) == (4 << 16) | (3 << 24)
    assert v.mode_from_custom(v.custom_mode(v.HOLD)) == v.HOLD
    veh = make(CTRL_SEL=1)  # the policy flies OFFBOARD; HOLD, like LAND, flies the fallback PID
    veh.offboard_setpoint((0, 0, 0), 0.8)
    veh.request_mode(v.OFFBOARD)
    veh.request_arm(True)
    climbing = REST._replace(accel=np.array([0.0, 0.0, -11.0]))
    t, cmd = run(veh, 0, 0.1, frame=climbing, every=lambda k, t: veh.offboard_setpoint((0, 0, 0), 0.8))
    assert cmd.controller == "neural" and veh.landed_state == v.IN_AIR
    assert veh.request_mode(v.HOLD) == (v.ACCEPTED, "") and veh.mode_name() == "HOLD"
    t, cmd = run(veh, t, 1.0)  # no setpoints needed in HOLD: no failsafe
    assert veh.mode == v.HOLD and veh.armed and cmd.controller == "pid" and not veh.failsafe
    assert cmd.setpoint.throttle == pytest.approx(0.745, abs=0.15) and veh.landed_state == v.IN_AIR
    assert veh.request_arm(False)[0] == v.TEMPORARILY_REJECTED  # in the air
    assert veh.request_mode(v.STABILIZED)[0] == v.ACCEPTED and veh.mode == v.STABILIZED


def test_hold_on_the_ground_idles_and_may_be_disarmed() -> None:
    veh = make()
    assert veh.request_mode(v.HOLD)[0] == v.ACCEPTED  # disarmed, on the ground
    assert veh.request_arm(True)[0] == v.ACCEPTED
    _, cmd = run(veh, 0, 0.1)
    assert cmd.armed and cmd.setpoint.throttle == 0.0 and veh.landed_state == v.ON_GROUND
    assert veh.request_arm(False)[0] == v.ACCEPTED and not veh.armed


def test_the_land_detector_runs_in_offboard() -> None:
    veh = make()
    veh.offboard_setpoint((0, 0, 0), 0.0)
    veh.request_mode(v.OFFBOARD)
    veh.request_arm(True)
    t, _ = run(veh, 0, 0.05, every=lambda k, t: veh.offboard_setpoint((0, 0, 0), 0.0))
    assert veh.landed_state == v.ON_GROUND  # idle thrust, at rest
    t, _ = run(veh, t, 0.05, every=lambda k, t: veh.offboard_setpoint((0, 0, 0), 0.7))
    assert veh.landed_state == v.IN_AIR  # flying thrust
    t, _ = run(veh, t, 0.05, frame=REST._replace(gyro=np.array([1.0, 0.0, 0.0])),
               every=lambda k, t: veh.offboard_setpoint((0, 0, 0), 0.1))
    assert veh.landed_state == v.IN_AIR  # low thrust but rotating: not on the ground
