"""The mode state machine: which modes exist, which transitions and arming requests are allowed.

Modes are PX4's custom modes (px4_custom_mode.h: main mode in bits 16-23, sub mode in 24-31).
MANUAL and STABILIZED self-level (sticks are tilt angles), ACRO flies stick rates, OFFBOARD flies
SET_ATTITUDE_TARGET body rates and thrust, HOLD (PX4 AUTO.LOITER) holds level, altitude and, where
a position source publishes, position; LAND (PX4 AUTO.LAND) descends and disarms on touchdown and
is also the failsafe. The machine decides; what each mode flies is its flight task
(firmware/vehicle/flight_tasks.py) and the facts it decides on (sensors alive, stream live, landed)
come from the vehicle.
"""

from __future__ import annotations

from typing import NamedTuple

Mode = int | tuple[int, int]

MANUAL, ALTCTL, POSCTL, AUTO, ACRO, OFFBOARD, STABILIZED = 1, 2, 3, 4, 5, 6, 7
AUTO_LOITER, AUTO_LAND = 3, 6
HOLD: Mode = (AUTO, AUTO_LOITER)
LAND: Mode = (AUTO, AUTO_LAND)
MODE_NAMES: dict[Mode, str] = {MANUAL: "MANUAL", ACRO: "ACRO", STABILIZED: "STABILIZED",
                               OFFBOARD: "OFFBOARD", HOLD: "HOLD", LAND: "LAND"}
STICK_MODES = (MANUAL, STABILIZED, ACRO)
AUTO_MODES = (HOLD, LAND)

# MAV_RESULT
ACCEPTED, TEMPORARILY_REJECTED, DENIED, UNSUPPORTED, FAILED = 0, 1, 2, 3, 4
# MAV_LANDED_STATE
ON_GROUND, IN_AIR, LANDING = 1, 2, 4
FORCE_ARM_MAGIC = 21196  # MAV_CMD_COMPONENT_ARM_DISARM param2 that skips the checks (PX4, ArduPilot)
OFFBOARD_LOSS, STICKS_LOSS = "offboard setpoint loss", "manual control loss"
# MAV_SEVERITY
CRITICAL, ERROR, WARNING, INFO = 2, 3, 4, 6


def custom_mode(mode: Mode) -> int:
    main, sub = mode if isinstance(mode, tuple) else (mode, 0)
    return (main << 16) | (sub << 24)


def mode_from_custom(value: int) -> Mode:
    return mode_from_parts((value >> 16) & 0xFF, (value >> 24) & 0xFF)


def mode_from_parts(main: int, sub: int) -> Mode:
    return (main, sub) if main == AUTO else main


def mode_name(mode: Mode) -> str:
    return MODE_NAMES.get(mode, str(mode))


class Reply(NamedTuple):
    result: int  # MAV_RESULT
    text: str = ""


class Events:
    """What happened, for the ground station: counters and (MAV_SEVERITY, text) messages."""

    def __init__(self) -> None:
        self.counters: dict[str, int] = {}
        self.outbox: list[tuple[int, str]] = []

    def count(self, what: str) -> None:
        self.counters[what] = self.counters.get(what, 0) + 1

    def say(self, severity: int, text: str) -> None:
        if len(self.outbox) < 32:
            self.outbox.append((severity, text))


class ModeMachine:
    """Armed state, mode and failsafe reason, changed only through the rules here."""

    def __init__(self, events: Events) -> None:
        self.events = events
        self.armed = False
        self.mode: Mode = STABILIZED
        self.failsafe = ""  # why LAND was entered by the vehicle itself; "" otherwise

    def arming_problem(self, sensor_problem: str, controller_loaded: bool, throttle_low: bool,
                       offboard_live: bool) -> str:
        """Why arming would be refused now ("" if it would not)."""
        if sensor_problem:
            return sensor_problem
        if not controller_loaded:
            return "no controller loaded"
        if self.mode in STICK_MODES and not throttle_low:
            return "throttle not low"
        if self.mode == OFFBOARD and not offboard_live:
            return "no offboard setpoint stream"
        if self.mode == LAND:
            return "in LAND; choose a flight mode"
        return ""

    def request_arm(self, problem: str) -> Reply:
        if self.armed:
            return Reply(ACCEPTED)
        if problem:
            self.events.count("arm_denied")
            self.events.say(ERROR, f"Arming denied: {problem}")
            return Reply(DENIED, problem)
        self.armed = True
        self.failsafe = ""
        self.events.say(INFO, f"Armed in {mode_name(self.mode)}")
        return Reply(ACCEPTED)

    def request_disarm(self, force: bool, landed: bool) -> Reply:
        """PX4's rule: a disarm in the air would drop the vehicle, so only a forced one is taken."""
        if not self.armed:
            return Reply(ACCEPTED)
        if not force and not landed:
            self.events.count("disarm_denied")
            self.events.say(ERROR, "Disarming denied: not landed")
            return Reply(TEMPORARILY_REJECTED, "not landed")
        self.disarm("forced by request" if force else "disarmed by request")
        return Reply(ACCEPTED)

    def disarm(self, why: str) -> None:
        self.armed = False
        self.events.say(INFO, f"Disarmed: {why}")

    def request_mode(self, mode: Mode, offboard_live: bool) -> Reply:
        if mode not in MODE_NAMES:
            self.events.count("mode_unsupported")
            return Reply(DENIED, "mode not available")
        if mode == OFFBOARD and not offboard_live:
            self.events.count("offboard_denied")
            self.events.say(WARNING, "OFFBOARD denied: no setpoint stream")
            return Reply(DENIED, "no offboard setpoint stream")
        if mode == LAND and self.mode != LAND:
            self.enter_land("")
        elif mode != self.mode:
            self.mode = mode
            self.failsafe = ""
            self.events.say(INFO, f"Mode {mode_name(mode)}")
        return Reply(ACCEPTED)

    def enter_land(self, reason: str) -> None:
        self.mode = LAND
        self.failsafe = reason
        self.events.count("failsafe" if reason else "land")
        self.events.say(CRITICAL if reason else INFO, f"Failsafe: {reason}: LAND" if reason else "Landing")

    def check_failsafe(self, offboard_lost: bool, sticks_lost: bool) -> str:
        """Setpoint or stick loss in a mode that flies them → LAND; returns the reason ("" if none)."""
        mode = self.mode
        reason = ""
        if mode == OFFBOARD and offboard_lost:
            reason = OFFBOARD_LOSS
        elif mode in STICK_MODES and sticks_lost:
            reason = STICKS_LOSS
        if reason:
            self.enter_land(reason)
        return reason
