"""Flight tasks: what each mode flies, as a rate setpoint and throttle per tick (PX4's FlightTasks).

Each task reads the vehicle's current inputs (`FlightInputs`: estimator, settings, sticks,
offboard setpoint, external position fix) and says where it thinks the vehicle is
(`landed_state`). `activate` is called on entering the mode and on arming in it.

The vertical channel of LAND and HOLD is one law: throttle = hover / cos(tilt) + VZ_GAIN · (vz −
vz_sp), vz from the estimator, or from the position source while its fix is fresh. With a fix,
HOLD brakes to a stop and holds the position where it stopped: position error → velocity
setpoint → acceleration → tilt (PX4's position and velocity P loops, without the
attitude-setpoint machinery: the tilt goes through the same angle P as STABILIZED).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import numpy as np

from fcemu.firmware.controller import RateSetpoint
from fcemu.firmware.estimator import GRAVITY, AttitudeEstimator
from fcemu.firmware.sensors import SensorFrame
from fcemu.firmware.vehicle.land_detector import LOW_THRUST, LandDetector
from fcemu.firmware.vehicle.modes import IN_AIR, LANDING, ON_GROUND
from fcemu.firmware.vehicle.param_adapter import VehicleSettings

VZ_GAIN = 0.12  # throttle per m/s of vertical-speed error
THROTTLE_MIN, THROTTLE_MAX = 0.1, 0.95  # what the vertical-speed law may command in the air
FIX_TIMEOUT_US = 200_000  # a position fix older than this is not used
HOLD_POS_P = 1.0  # m/s of velocity setpoint per m of position error (PX4 MPC_XY_P, MPC_Z_P)
HOLD_VEL_P = 1.8  # m/s² per m/s of velocity error (PX4 MPC_XY_VEL_P_ACC)
HOLD_VEL_MAX = 2.0  # m/s, horizontal and vertical
HOLD_TILT_MAX = math.radians(20.0)
HOLD_STOPPED = 0.3  # m/s: below this on every axis the brake is over and the position is held
_ZERO3 = np.zeros(3)
IDLE = RateSetpoint(_ZERO3, 0.0)


class PositionFix(NamedTuple):
    t_us: int  # loop time it arrived
    position: tuple[float, float, float]  # NED m
    velocity: tuple[float, float, float]  # NED m/s


@dataclass(slots=True)
class FlightInputs:
    """What the tasks read: the vehicle's estimate, settings and latest inputs."""

    estimator: AttitudeEstimator
    settings: VehicleSettings
    detector: LandDetector
    frame: SensorFrame | None = None
    sticks: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)  # roll, pitch-up, yaw ±1; thr 0..1
    sticks_us: int | None = None
    offboard: RateSetpoint | None = None
    offboard_us: int = -(1 << 62)
    fix: PositionFix | None = None

    def fresh_fix(self, t_us: int) -> PositionFix | None:
        fix = self.fix
        return fix if fix is not None and t_us - fix.t_us <= FIX_TIMEOUT_US else None


class FlightTask(Protocol):
    landed_state: int

    def activate(self, t_us: int, on_ground: bool, failsafe: bool) -> None: ...

    def update(self, t_us: int) -> RateSetpoint: ...


def level_rates(inp: FlightInputs, roll_sp: float, pitch_sp: float, yaw_rate: float
                ) -> tuple[float, float, float]:
    k = inp.settings.stab_angle_p
    roll, pitch, _ = inp.estimator.euler()
    return (k * (roll_sp - roll), k * (pitch_sp - pitch), yaw_rate)


def vertical_throttle(inp: FlightInputs, vz: float, vz_sp: float) -> float:
    thr = inp.settings.hover_throttle / max(inp.estimator.tilt_cos(), 0.5) + VZ_GAIN * (vz - vz_sp)
    return min(max(thr, THROTTLE_MIN), THROTTLE_MAX)


class StickTask:
    """MANUAL and STABILIZED: sticks are tilt angles (self-levelling); ACRO: sticks are rates."""

    def __init__(self, inp: FlightInputs, acro: bool) -> None:
        self.inp = inp
        self.acro = acro
        self.landed_state = ON_GROUND

    def activate(self, t_us: int, on_ground: bool, failsafe: bool) -> None:
        self.landed_state = ON_GROUND if on_ground else IN_AIR

    def update(self, t_us: int) -> RateSetpoint:
        inp = self.inp
        s = inp.settings
        roll, pitch_up, yaw, thr = inp.sticks if inp.sticks_us is not None else (0.0, 0.0, 0.0, 0.0)
        if self.acro:
            rates = s.rates.rates(roll, pitch_up, yaw)
        else:
            tilt = s.stab_tilt_max
            rates = level_rates(inp, roll * tilt, pitch_up * tilt, s.rates.yaw.rate(yaw))
        self.landed_state = inp.detector.from_thrust(thr, inp.frame, s.hover_throttle, self.landed_state)
        return RateSetpoint(np.array(rates), thr)


class OffboardTask:
    """The companion computer's body rates and thrust, as they came."""

    def __init__(self, inp: FlightInputs) -> None:
        self.inp = inp
        self.landed_state = ON_GROUND

    def activate(self, t_us: int, on_ground: bool, failsafe: bool) -> None:
        self.landed_state = ON_GROUND if on_ground else IN_AIR

    def update(self, t_us: int) -> RateSetpoint:
        inp = self.inp
        sp = inp.offboard if inp.offboard is not None else IDLE
        hover = inp.settings.hover_throttle
        # Flying thrust (most ticks) is decided here without a call into the land detector.
        self.landed_state = (IN_AIR if sp.throttle >= LOW_THRUST * hover
                             else inp.detector.from_thrust(sp.throttle, inp.frame, hover, self.landed_state))
        return sp


class LandTask:
    """Level, zero vertical speed for FS_HOLD_T (failsafe only), then descend at FS_DESC_SPD;
    `touchdown` says why to disarm once the land detector sees the ground or time runs out."""

    def __init__(self, inp: FlightInputs) -> None:
        self.inp = inp
        self.landed_state = IN_AIR
        self.touchdown = ""
        self.from_ground = False
        self._start_us = 0
        self._failsafe = False

    def activate(self, t_us: int, on_ground: bool, failsafe: bool) -> None:
        self.from_ground = on_ground
        self._start_us = t_us
        self._failsafe = failsafe
        self.touchdown = ""
        self.inp.detector.reset()

    def update(self, t_us: int) -> RateSetpoint:
        inp = self.inp
        s, est = inp.settings, inp.estimator
        elapsed = t_us - self._start_us
        hold_us = s.fs_hold_us if self._failsafe else 0.0
        descending = elapsed >= hold_us
        thr = vertical_throttle(inp, est.vz, s.fs_desc_spd if descending else 0.0)
        self.landed_state = LANDING if descending else IN_AIR
        if descending:
            descent_us = elapsed - hold_us
            if inp.detector.touchdown(t_us, descent_us, est.vz):
                self.touchdown = "landed"
            if descent_us > s.fs_desc_max_us:
                self.touchdown = "descent time limit"
        return RateSetpoint(np.array(level_rates(inp, 0.0, 0.0, 0.0)), thr)


class HoldTask:
    """PX4's AUTO.LOITER for a rate-loop vehicle: level, zero vertical speed; with a fresh position
    fix, brake to a stop and hold the position where it stopped. Entered on the ground it stays
    there at idle, as PX4's land detector keeps a landed vehicle landed."""

    def __init__(self, inp: FlightInputs) -> None:
        self.inp = inp
        self.landed_state = IN_AIR
        self.on_ground = False
        self.target: tuple[float, float, float] | None = None

    def activate(self, t_us: int, on_ground: bool, failsafe: bool) -> None:
        self.on_ground = on_ground
        self.target = None

    def update(self, t_us: int) -> RateSetpoint:
        inp = self.inp
        if self.on_ground:
            self.landed_state = ON_GROUND
            return RateSetpoint(np.array(level_rates(inp, 0.0, 0.0, 0.0)), 0.0)
        self.landed_state = IN_AIR
        fix = inp.fresh_fix(t_us)
        if fix is None:
            return RateSetpoint(np.array(level_rates(inp, 0.0, 0.0, 0.0)),
                                vertical_throttle(inp, inp.estimator.vz, 0.0))
        if self.target is None and max(map(abs, fix.velocity)) < HOLD_STOPPED:
            self.target = fix.position
        if self.target is None:
            vel_sp = [0.0, 0.0, 0.0]
        else:
            vel_sp = [_clamp(HOLD_POS_P * (t - p), HOLD_VEL_MAX)
                      for t, p in zip(self.target, fix.position, strict=True)]
        acc_n = HOLD_VEL_P * (vel_sp[0] - fix.velocity[0])
        acc_e = HOLD_VEL_P * (vel_sp[1] - fix.velocity[1])
        roll_sp, pitch_sp = tilt_for_acceleration(acc_n, acc_e, inp.estimator.euler()[2])
        return RateSetpoint(np.array(level_rates(inp, roll_sp, pitch_sp, 0.0)),
                            vertical_throttle(inp, fix.velocity[2], vel_sp[2]))


def tilt_for_acceleration(acc_n: float, acc_e: float, yaw: float) -> tuple[float, float]:
    """Roll and pitch (FRD, rad) that tilt the thrust to give this horizontal NED acceleration."""
    c, s = math.cos(yaw), math.sin(yaw)
    forward, right = c * acc_n + s * acc_e, -s * acc_n + c * acc_e
    return (_clamp(math.atan2(right, GRAVITY), HOLD_TILT_MAX),
            _clamp(math.atan2(-forward, GRAVITY), HOLD_TILT_MAX))


def _clamp(value: float, limit: float) -> float:
    return min(max(value, -limit), limit)
