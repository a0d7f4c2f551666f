"""The mode state machine alone: transitions, arming and disarming rules, failsafe."""

from __future__ import annotations

from fcemu.firmware.vehicle import modes as m


def machine() -> m.ModeMachine:
    return m.ModeMachine(m.Events())


def test_modes_that_exist_and_the_offboard_rule() -> None:
    mm = machine()
    assert mm.request_mode(m.POSCTL, offboard_live=True).result == m.DENIED
    assert mm.request_mode((m.AUTO, 4), offboard_live=True).result == m.DENIED  # AUTO.MISSION
    denied = m.Reply(m.DENIED, "no offboard setpoint stream")
    assert mm.request_mode(m.OFFBOARD, offboard_live=False) == denied
    assert mm.events.counters == {"mode_unsupported": 2, "offboard_denied": 1}
    for mode in (m.ACRO, m.HOLD, m.OFFBOARD, m.MANUAL, m.STABILIZED):
        assert mm.request_mode(mode, offboard_live=True).result == m.ACCEPTED and mm.mode == mode
    assert mm.request_mode(m.LAND, offboard_live=False).result == m.ACCEPTED
    assert mm.mode == m.LAND and mm.events.counters["land"] == 1 and mm.failsafe == ""


def test_arming_rules() -> None:
    mm = machine()
    ok = {"sensor_problem": "", "controller_loaded": True, "throttle_low": True, "offboard_live": True}
    assert mm.arming_problem(**ok) == ""
    assert mm.arming_problem(**{**ok, "sensor_problem": "sensors not alive"}) == "sensors not alive"
    assert mm.arming_problem(**{**ok, "throttle_low": False}) == "throttle not low"  # STABILIZED
    mm.mode = m.HOLD
    assert mm.arming_problem(**{**ok, "throttle_low": False, "offboard_live": False}) == ""
    mm.mode = m.LAND
    assert "LAND" in mm.arming_problem(**ok)
    assert mm.request_arm("in LAND") == m.Reply(m.DENIED, "in LAND")
    assert mm.request_arm("").result == m.ACCEPTED and mm.armed


def test_disarm_in_the_air_only_when_forced() -> None:
    mm = machine()
    mm.request_arm("")
    assert mm.request_disarm(force=False, landed=False) == m.Reply(m.TEMPORARILY_REJECTED, "not landed")
    assert mm.armed and mm.events.counters["disarm_denied"] == 1
    assert mm.request_disarm(force=True, landed=False).result == m.ACCEPTED and not mm.armed
    mm.request_arm("")
    assert mm.request_disarm(force=False, landed=True).result == m.ACCEPTED and not mm.armed
    assert m.FORCE_ARM_MAGIC == 21196


def test_failsafe_only_in_the_modes_that_fly_a_stream() -> None:
    mm = machine()
    mm.mode = m.HOLD
    assert mm.check_failsafe(offboard_lost=True, sticks_lost=True) == "" and mm.mode == m.HOLD
    mm.mode = m.OFFBOARD
    assert mm.check_failsafe(offboard_lost=False, sticks_lost=True) == ""
    assert mm.check_failsafe(offboard_lost=True, sticks_lost=False) == m.OFFBOARD_LOSS
    assert mm.mode == m.LAND and mm.failsafe == m.OFFBOARD_LOSS
    mm.mode = m.ACRO
    assert mm.check_failsafe(offboard_lost=True, sticks_lost=True) == m.STICKS_LOSS
