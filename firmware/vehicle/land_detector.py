"""The land detector: is the vehicle on the ground (PX4's land_detector, reduced to what the
firmware measures: thrust, specific force, body rates and its vertical speed estimate)."""

from __future__ import annotations

import math

from fcemu.firmware.estimator import GRAVITY
from fcemu.firmware.sensors import SensorFrame
from fcemu.firmware.vehicle.modes import IN_AIR, ON_GROUND

LANDED_VZ = 0.15  # m/s
LANDED_HOLD_US = 500_000
DESCENT_MIN_US = 1_000_000
REST_ACCEL_TOL = 0.03  # | |a|/g - 1 |
REST_GYRO_MAX = 0.2  # rad/s
LOW_THRUST = 0.5  # of hover throttle


class LandDetector:
    def __init__(self) -> None:
        self._still_since: int | None = None

    def reset(self) -> None:
        self._still_since = None

    @staticmethod
    def at_rest(frame: SensorFrame | None) -> bool:
        """Specific force ≈ g and no rotation (also true in a steady hover: pair it with thrust)."""
        if frame is None:
            return True
        a = math.sqrt(sum(v * v for v in frame.accel.tolist()))
        return (abs(a / GRAVITY - 1.0) < REST_ACCEL_TOL
                and max(abs(v) for v in frame.gyro.tolist()) < REST_GYRO_MAX)

    def from_thrust(self, throttle: float, frame: SensorFrame | None, hover: float,
                    before: int = IN_AIR) -> int:
        """Thrust well below hover and the airframe at rest: on the ground. Once on the ground
        (`before`), it stays there until the thrust rises, as PX4's landed state does: a jolt of the
        idling motors on one tick would otherwise refuse a disarm the vehicle had just invited."""
        if throttle >= LOW_THRUST * hover:
            return IN_AIR
        return ON_GROUND if before == ON_GROUND or self.at_rest(frame) else IN_AIR

    def touchdown(self, t_us: int, descent_us: float, vz: float) -> bool:
        """During a descent: vertical speed near zero for LANDED_HOLD_US after DESCENT_MIN_US."""
        if descent_us > DESCENT_MIN_US and abs(vz) < LANDED_VZ:
            if self._still_since is None:
                self._still_since = t_us
            return t_us - self._still_since >= LANDED_HOLD_US
        self._still_since = None
        return False
