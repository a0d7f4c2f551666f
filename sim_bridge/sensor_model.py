"""What the gyro, accelerometer and ESC telemetry report of the truth: bias and white noise.

The twin draws each frame's noise from its own generator; the batched environment draws
many frames ahead per vehicle (`NoiseStreams`), the same numbers in the same order, which
keeps the two bit-identical. Delays and the ESC bus's losses are `plant.AirframeEffects`'.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SensorNoise:
    """Sensor imperfections; all zero by default, as in the paper's twin."""

    gyro_std: float = 0.0  # rad/s, white noise per sample
    gyro_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)  # rad/s, FRD
    accel_std: float = 0.0  # m/s^2
    accel_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotor_speed_std: float = 0.0  # rad/s

    @property
    def enabled(self) -> bool:
        return bool(self.gyro_std or self.accel_std or self.rotor_speed_std
                    or any(self.gyro_bias) or any(self.accel_bias))


class SensorModel:
    """What the gyro, accelerometer and ESC telemetry report: truth + bias + white noise, FRD.

    The noise of one frame is `DRAWS` standard normal draws in a fixed order (gyro 3,
    accelerometer 3, rotor speed 4): a vehicle drawing each frame's on its own and a
    batch drawing many frames ahead (`NoiseStreams`) read the same numbers.
    """

    DRAWS = 10

    def __init__(self, noise: SensorNoise | None = None) -> None:
        self.noise = noise or SensorNoise()
        self.enabled = self.noise.enabled
        self._gyro_bias = np.asarray(self.noise.gyro_bias, dtype=np.float64)
        self._accel_bias = np.asarray(self.noise.accel_bias, dtype=np.float64)

    def read(self, gyro: np.ndarray, accel: np.ndarray | None, rotor_speed: np.ndarray,
             z: np.ndarray, gyro_std: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """Readings of the true rates (..., 3), specific force (None: not wanted), rotor speeds (..., 4).

        `gyro_std` replaces the noise's gyro std, e.g. per vehicle (n, 1) of randomised airframes.
        """
        n = self.noise
        std = n.gyro_std if gyro_std is None else gyro_std
        gyro = gyro + (self._gyro_bias + std * z[..., 0:3])
        if accel is not None:
            accel = accel + (self._accel_bias + n.accel_std * z[..., 3:6])
        rotor_speed = rotor_speed + n.rotor_speed_std * z[..., 6:10]
        return gyro, accel, rotor_speed


class NoiseStreams:
    """One seeded stream per vehicle of a batch, `width` draws per frame: standard normal, or `uniform`
    on [0, 1).

    Draws `block` frames at a time per vehicle: the same numbers, in the same order, as a
    generator drawing each frame when it is needed (numpy fills arrays draw by draw).
    """

    def __init__(self, n: int, width: int = SensorModel.DRAWS, block: int = 256,
                 uniform: bool = False) -> None:
        self.block, self.uniform = block, uniform
        self._rngs = [np.random.default_rng() for _ in range(n)]
        self._draws = np.zeros((n, block, width))
        self._pos = np.zeros(n, dtype=np.int64)

    def reseed(self, i: int, seed: int | None) -> None:
        self._rngs[i] = np.random.default_rng(seed)
        self._refill(i)

    def next(self, idx: np.ndarray) -> np.ndarray:
        """The next frame's draws of vehicles `idx`, (len(idx), width)."""
        pos = self._pos[idx]
        z = self._draws[idx, pos]
        pos += 1
        self._pos[idx] = pos
        for i in idx[pos == self.block]:
            self._refill(i)
        return z

    def _refill(self, i: int) -> None:
        rng = self._rngs[i]
        if self.uniform:
            rng.random(out=self._draws[i])
        else:
            rng.standard_normal(out=self._draws[i])
        self._pos[i] = 0
