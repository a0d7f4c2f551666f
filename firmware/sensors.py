"""What the flight controller reads each tick."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class SensorFrame(NamedTuple):
    """One sample of the vehicle's sensors, body frame FRD, SI units.

    `accel` is specific force (at rest, level: [0, 0, -g]); `rotor_speed` is the ESC
    telemetry in rad/s, in Betaflight motor order (1 rear-right, 2 front-right,
    3 rear-left, 4 front-left). A NamedTuple: immutable and cheap to build 1000 times a second.

    Every input has an age: `gyro_t_us` is when the gyro sample was taken and `rotor_speed_t_us`
    (4,) when each motor's telemetry was, on the frame's clock. A bus that drops a frame leaves the
    old sample with its old time; a late one arrives with its true time. None (the default): sampled
    at `t_us`, as a frame that says nothing of its ages.
    """

    t_us: int
    gyro: np.ndarray
    accel: np.ndarray
    rotor_speed: np.ndarray
    gyro_t_us: int | None = None
    rotor_speed_t_us: np.ndarray | None = None

    def gyro_age_us(self) -> int:
        return 0 if self.gyro_t_us is None else self.t_us - self.gyro_t_us

    def rotor_speed_age_us(self) -> np.ndarray:
        if self.rotor_speed_t_us is None:
            return np.zeros(4, dtype=np.int64)
        return self.t_us - np.asarray(self.rotor_speed_t_us, dtype=np.int64)

    def is_finite(self) -> bool:
        return bool(
            np.isfinite(self.gyro).all()
            and np.isfinite(self.accel).all()
            and np.isfinite(self.rotor_speed).all()
        )
