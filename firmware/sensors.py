"""What the flight controller reads each tick."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class SensorFrame(NamedTuple):
    """One sample of the vehicle's sensors, body frame FRD, SI units.

    `accel` is specific force (at rest, level: [0, 0, -g]); `rotor_speed` is the ESC
    telemetry in rad/s, in Betaflight motor order (1 rear-right, 2 front-right,
    3 rear-left, 4 front-left). A NamedTuple: immutable and cheap to build 1000 times a second.
    """

    t_us: int
    gyro: np.ndarray
    accel: np.ndarray
    rotor_speed: np.ndarray

    def is_finite(self) -> bool:
        return bool(
            np.isfinite(self.gyro).all()
            and np.isfinite(self.accel).all()
            and np.isfinite(self.rotor_speed).all()
        )
