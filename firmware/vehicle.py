"""The vehicle's state machine: arming, modes, setpoint arbitration and the failsafe.

`Vehicle` is what the flight loop calls each tick (a `Commander`: sensors in, armed /
setpoint / controller out). Ground-station requests reach it as plain method calls
(`request_arm`, `request_mode`, `offboard_setpoint`, `sticks`, `set_param`), made between
ticks by whatever carries them (firmware/mavlink/bridge.py); it never does I/O. Every
time it uses is the loop clock's, so the failsafe is timed in simulated time, and a stuck
ground-station process cannot stall it.

Modes are PX4's custom modes. MANUAL and STABILIZED self-level (sticks are tilt angles),
ACRO flies stick rates through Betaflight's Actual curves, OFFBOARD flies SET_ATTITUDE_TARGET
body rates and thrust. LAND (PX4 AUTO.LAND) is also the failsafe:

  offboard setpoints older than COM_OF_LOSS_T (or sticks older than COM_RC_LOSS_T in a stick
  mode, once sticks have been seen) → LAND, with the PID: hold level and zero vertical speed
  for FS_HOLD_T, then descend level at FS_DESC_SPD; disarm when the vertical speed stays
  near zero for 0.5 s after at least 1 s of descent (touchdown), or after FS_DESC_MAX_T.
  The vehicle stays in LAND when the stream returns; the ground station chooses a mode.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from firmware.controller import RateSetpoint
from firmware.estimator import GRAVITY, AttitudeEstimator
from firmware.loop import Command
from firmware.params import CONTROLLERS, ParamTable
from firmware.sensors import SensorFrame
from firmware.stick_rates import ActualRates, StickRates

# PX4 custom modes (px4_custom_mode.h): main mode in bits 16-23, sub mode in 24-31.
MANUAL, ALTCTL, POSCTL, AUTO, ACRO, OFFBOARD, STABILIZED = 1, 2, 3, 4, 5, 6, 7
AUTO_LAND = 6
MODE_NAMES = {MANUAL: "MANUAL", ACRO: "ACRO", STABILIZED: "STABILIZED", OFFBOARD: "OFFBOARD",
              (AUTO, AUTO_LAND): "LAND"}
LAND = (AUTO, AUTO_LAND)
STICK_MODES = (MANUAL, STABILIZED, ACRO)

# MAV_RESULT
ACCEPTED, TEMPORARILY_REJECTED, DENIED, UNSUPPORTED, FAILED = 0, 1, 2, 3, 4
# MAV_LANDED_STATE
ON_GROUND, IN_AIR, LANDING = 1, 2, 4
FORCE_ARM_MAGIC = 21196  # MAV_CMD_COMPONENT_ARM_DISARM param2 that skips the checks (PX4, ArduPilot)
ARM_THROTTLE_MAX = 0.1
LANDED_VZ = 0.15  # m/s
LANDED_HOLD_US = 500_000
DESCENT_MIN_US = 1_000_000
VZ_GAIN = 0.12  # throttle per m/s of vertical-speed error
_ZERO3 = np.zeros(3)


def custom_mode(mode: int | tuple[int, int]) -> int:
    main, sub = mode if isinstance(mode, tuple) else (mode, 0)
    return (main << 16) | (sub << 24)


def mode_from_custom(value: int) -> int | tuple[int, int]:
    main, sub = (value >> 16) & 0xFF, (value >> 24) & 0xFF
    return (main, sub) if main == AUTO else main


class Vehicle:
    def __init__(self, params: ParamTable, controllers: Mapping[str, object], fallback: str = "pid",
                 selected: str | None = None) -> None:
        self.params = params
        self.controllers = controllers
        self.fallback = fallback if fallback in controllers else next(iter(controllers))
        self.estimator = AttitudeEstimator()
        self.armed = False
        self.mode: int | tuple[int, int] = STABILIZED
        self.failsafe = ""  # why LAND was entered by the vehicle itself; "" otherwise
        self.counters: dict[str, int] = {}
        self.outbox: list[tuple[int, str]] = []  # (MAV_SEVERITY, text) for the ground station
        self.landed_state = ON_GROUND
        self.now_us = 0
        self._frame: SensorFrame | None = None
        self._offb: RateSetpoint | None = None
        self._offb_us = -(1 << 62)
        self._sticks = (0.0, 0.0, 0.0, 0.0)  # roll, pitch-up, yaw in [-1, 1]; throttle 0..1
        self._sticks_us: int | None = None
        self._land_start_us = 0
        self._land_from_ground = False
        self._landed_since: int | None = None
        self._last_est_us: int | None = None
        self._setpoint = RateSetpoint(_ZERO3, 0.0)
        self._command = Command(False, self._setpoint, self.fallback)
        if selected is not None:
            params.set("CTRL_SEL", CONTROLLERS.index(selected))
        self._apply_all()

    # ---- parameters -------------------------------------------------------------------
    def set_param(self, name: str, value: float) -> str:
        problem = self.params.set(name, value)
        if problem:
            self._count("param_rejected")
            return problem
        if name == "CTRL_SEL" and self.controller_name() not in self.controllers:
            self._say(4, f"controller {CONTROLLERS[int(value)]} is not loaded; flying {self.fallback}")
        self._apply_all()
        return ""

    def _apply_all(self) -> None:
        p = self.params
        # What the tick reads, as plain attributes: parameters change only through here.
        self._of_loss_us = p["COM_OF_LOSS_T"] * 1e6
        self._rc_loss_us = p["COM_RC_LOSS_T"] * 1e6
        name = self.controller_name()
        self._selected = name if name in self.controllers else self.fallback
        curves = []
        for a in "RPY":
            center = p[f"RATE_{a}_CENTER"]
            curves.append(ActualRates(center, max(p[f"RATE_{a}_MAX"], center), p[f"RATE_{a}_EXPO"]))
        self._rates = StickRates(*curves)
        pid = getattr(self.controllers.get("pid"), "pid", None)
        if pid is not None and hasattr(pid, "set_gains"):
            axes = ("ROLL", "PITCH", "YAW")
            gains = pid.gains.with_(
                kp=tuple(p[f"PID_{a}_P"] for a in axes), ki=tuple(p[f"PID_{a}_I"] for a in axes),
                kd=tuple(p[f"PID_{a}_D"] for a in axes), kff=tuple(p[f"PID_{a}_FF"] for a in axes),
                gyro_lowpass_hz=p["IMU_GYRO_CUTOFF"], dterm_lowpass_hz=p["IMU_DGYRO_CUTOFF"])
            if gains != pid.gains:
                pid.set_gains(gains)

    def controller_name(self) -> str:
        return CONTROLLERS[int(self.params["CTRL_SEL"])]

    # ---- requests from the ground station ----------------------------------------------
    def request_arm(self, arm: bool, force: bool = False) -> tuple[int, str]:
        if not arm:
            if self.armed:
                # PX4's rule: a disarm in the air would drop the vehicle; only forced.
                if not force and not self._landed():
                    self._count("disarm_denied")
                    self._say(3, "Disarming denied: not landed")
                    return TEMPORARILY_REJECTED, "not landed"
                self._disarm("forced by request" if force else "disarmed by request")
            return ACCEPTED, ""
        if self.armed:
            return ACCEPTED, ""
        problem = "" if force else self.arming_problem()
        if problem:
            self._count("arm_denied")
            self._say(3, f"Arming denied: {problem}")
            return DENIED, problem
        self.armed = True
        self.failsafe = ""
        self._landed_since = None
        self._say(6, f"Armed in {self.mode_name()}")
        return ACCEPTED, ""

    def arming_problem(self) -> str:
        f = self._frame
        if f is None or not f.is_finite():
            return "sensors not alive"
        if abs(math.sqrt(sum(a * a for a in f.accel.tolist())) / GRAVITY - 1.0) > 0.3:
            return "accelerometer implausible"
        if self.controller_name() not in self.controllers and self.fallback not in self.controllers:
            return "no controller loaded"
        if self.mode in STICK_MODES and self._sticks_live() and self._sticks[3] > ARM_THROTTLE_MAX:
            return "throttle not low"
        if self.mode == OFFBOARD and not self._offboard_live():
            return "no offboard setpoint stream"
        if self.mode == LAND:
            return "in LAND; choose a flight mode"
        return ""

    def request_mode(self, mode: int | tuple[int, int]) -> tuple[int, str]:
        if mode not in MODE_NAMES:
            self._count("mode_unsupported")
            return DENIED, "mode not available (no position estimate)"
        if mode == OFFBOARD and not self._offboard_live():
            self._count("offboard_denied")
            self._say(4, "OFFBOARD denied: no setpoint stream")
            return DENIED, "no offboard setpoint stream"
        if mode == LAND and self.mode != LAND:
            self._enter_land("")
        elif mode != self.mode:
            self.mode = mode
            self.failsafe = ""
            self._say(6, f"Mode {self.mode_name()}")
        return ACCEPTED, ""

    def offboard_setpoint(self, rates: tuple[float, float, float], thrust: float) -> bool:
        if not (all(math.isfinite(r) and abs(r) <= 50.0 for r in rates) and 0.0 <= thrust <= 1.0):
            self._count("setpoint_rejected")
            return False
        self._offb = RateSetpoint(np.array(rates, dtype=float), float(thrust))
        self._offb_us = self.now_us
        return True

    def sticks(self, roll: float, pitch_up: float, yaw: float, throttle: float) -> bool:
        values = (roll, pitch_up, yaw, throttle)
        if not all(math.isfinite(v) for v in values) or not (0.0 <= throttle <= 1.0) \
                or max(abs(roll), abs(pitch_up), abs(yaw)) > 1.0:
            self._count("sticks_rejected")
            return False
        self._sticks = values
        self._sticks_us = self.now_us
        return True

    # ---- the tick ------------------------------------------------------------------------
    def command(self, t_us: int, frame: SensorFrame) -> Command:
        self.now_us = t_us
        self._frame = frame
        g, a = frame.gyro.tolist(), frame.accel.tolist()
        # The estimator integrates over the sensors' own clock: a tick the loop skipped (a deadline
        # miss) advances the loop clock but not the IMU.
        last = self._last_est_us
        dt = 0.001 if last is None else (frame.t_us - last) * 1e-6
        self._last_est_us = frame.t_us
        est = self.estimator
        if (last is None or dt <= 0.0) and not self.armed:
            est.level_from_accel(*a)
        elif 0.0 < dt < 0.1 and math.isfinite(g[0] + g[1] + g[2] + a[0] + a[1] + a[2]):
            est.update(g[0], g[1], g[2], a[0], a[1], a[2], dt)
        if not self.armed:
            est.vz = 0.0
            self.landed_state = ON_GROUND
            return self._emit(False, self._setpoint)
        self._check_failsafe(t_us)
        if not self.armed:  # the failsafe may have disarmed
            return self._emit(False, self._setpoint)
        sp = self._compute_setpoint(t_us)
        self._setpoint = sp
        return self._emit(True, sp)

    def _emit(self, armed: bool, sp: RateSetpoint) -> Command:
        """The tick's Command, reused while nothing in it changed (most ticks)."""
        cmd, name = self._command, self._controller()
        if cmd.armed is not armed or cmd.setpoint is not sp or cmd.controller != name:
            cmd = self._command = Command(armed, sp, name)
        return cmd

    def _controller(self) -> str:
        return self.fallback if self.mode == LAND else self._selected

    def _check_failsafe(self, t_us: int) -> None:
        mode = self.mode
        if mode == OFFBOARD and t_us - self._offb_us > self._of_loss_us:
            self._enter_land("offboard setpoint loss")
        elif mode in STICK_MODES and self._sticks_us is not None \
                and t_us - self._sticks_us > self._rc_loss_us:
            self._enter_land("manual control loss")
            self._sticks_us = None

    def _enter_land(self, reason: str) -> None:
        self._land_from_ground = self.landed_state == ON_GROUND
        self.mode = LAND
        self.failsafe = reason
        self._land_start_us = self.now_us
        self._landed_since = None
        self._count("failsafe" if reason else "land")
        self._say(2 if reason else 6, f"Failsafe: {reason}: LAND" if reason else "Landing")

    def _compute_setpoint(self, t_us: int) -> RateSetpoint:
        p = self.params
        mode = self.mode
        if mode == OFFBOARD:
            self.landed_state = IN_AIR
            return self._offb if self._offb is not None else RateSetpoint(_ZERO3, 0.0)
        if mode == LAND:
            return self._land(t_us)
        roll, pitch_up, yaw, thr = self._sticks if self._sticks_us is not None else (0.0, 0.0, 0.0, 0.0)
        if mode == ACRO:
            rates = self._rates.rates(roll, pitch_up, yaw)
        else:
            tilt = math.radians(p["STAB_ANGLE_MAX"])
            rates = self._level_rates(roll * tilt, pitch_up * tilt, self._rates.yaw.rate(yaw))
        self.landed_state = ON_GROUND if thr < 0.5 * p["MPC_THR_HOVER"] and self._at_rest() else IN_AIR
        return RateSetpoint(np.array(rates), thr)

    def _level_rates(self, roll_sp: float, pitch_sp: float, yaw_rate: float) -> tuple[float, float, float]:
        k = self.params["STAB_ANGLE_P"]
        roll, pitch, _ = self.estimator.euler()
        return (k * (roll_sp - roll), k * (pitch_sp - pitch), yaw_rate)

    def _land(self, t_us: int) -> RateSetpoint:
        p, est = self.params, self.estimator
        elapsed = t_us - self._land_start_us
        hold_us = p["FS_HOLD_T"] * 1e6 if self.failsafe else 0.0
        descending = elapsed >= hold_us
        vz_sp = p["FS_DESC_SPD"] if descending else 0.0
        cos_tilt = max(est.tilt_cos(), 0.5)
        thr = p["MPC_THR_HOVER"] / cos_tilt + VZ_GAIN * (est.vz - vz_sp)
        thr = min(max(thr, 0.1), 0.95)
        self.landed_state = LANDING if descending else IN_AIR
        if descending:
            if elapsed - hold_us > DESCENT_MIN_US and abs(est.vz) < LANDED_VZ:
                if self._landed_since is None:
                    self._landed_since = t_us
                elif t_us - self._landed_since >= LANDED_HOLD_US:
                    self._disarm("landed")
            else:
                self._landed_since = None
            if elapsed - hold_us > p["FS_DESC_MAX_T"] * 1e6:
                self._disarm("descent time limit")
        return RateSetpoint(np.array(self._level_rates(0.0, 0.0, 0.0)), thr)

    def _disarm(self, why: str) -> None:
        self.armed = False
        self.landed_state = ON_GROUND
        self._say(6, f"Disarmed: {why}")

    # ---- helpers ------------------------------------------------------------------------
    def _offboard_live(self) -> bool:
        """PX4's rule: OFFBOARD (and arming in it) only while setpoints arrive within the timeout."""
        return self.now_us - self._offb_us <= self._of_loss_us

    def _sticks_live(self) -> bool:
        return self._sticks_us is not None and self.now_us - self._sticks_us <= self._rc_loss_us

    def _landed(self) -> bool:
        """The land detector's verdict; LAND entered on the ground; or (where no mode sets it) the
        stick modes' test on the current setpoint: thrust well below hover, the airframe at rest."""
        if self.landed_state == ON_GROUND:
            return True
        if self.mode == LAND and self._land_from_ground:
            return self._at_rest()
        return self._setpoint.throttle < 0.5 * self.params["MPC_THR_HOVER"] and self._at_rest()

    def _at_rest(self) -> bool:
        f = self._frame
        if f is None:
            return True
        a = math.sqrt(sum(v * v for v in f.accel.tolist()))
        return abs(a / GRAVITY - 1.0) < 0.03 and max(abs(v) for v in f.gyro.tolist()) < 0.2

    def mode_name(self) -> str:
        return MODE_NAMES.get(self.mode, str(self.mode))

    def _count(self, what: str) -> None:
        self.counters[what] = self.counters.get(what, 0) + 1

    def _say(self, severity: int, text: str) -> None:
        if len(self.outbox) < 32:
            self.outbox.append((severity, text))
