"""Betaflight "Actual" rates: stick deflection in [-1, 1] → body rate in rad/s.

Betaflight's `applyActualRates` (src/main/fc/rc.c), per axis, in deg/s:

    expo   = |x| · (x⁵ · e + x · (1 − e))
    rate   = x · center + max(0, max_rate − center) · expo

so the slope at the centre is `center` deg/s per full stick and full stick gives
`max_rate`. Defaults are Betaflight 4.3's Actual profile (70 / 670 deg/s, expo 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class ActualRates:
    center_dps: float = 70.0
    max_dps: float = 670.0
    expo: float = 0.0

    def __post_init__(self) -> None:
        if not (0.0 <= self.center_dps <= self.max_dps <= 2000.0):
            raise ValueError(f"need 0 <= center <= max <= 2000 deg/s, got {self.center_dps}, {self.max_dps}")
        if not 0.0 <= self.expo <= 1.0:
            raise ValueError(f"expo must be in [0, 1], got {self.expo}")

    def rate(self, stick: float) -> float:
        """Rad/s for a stick deflection (clamped to [-1, 1]; NaN counts as centred)."""
        x = stick if -1.0 <= stick <= 1.0 else (0.0 if stick != stick else math.copysign(1.0, stick))
        e = self.expo
        expo = abs(x) * (x ** 5 * e + x * (1.0 - e))
        return math.radians(x * self.center_dps + max(0.0, self.max_dps - self.center_dps) * expo)


@dataclass(frozen=True)
class StickRates:
    """Roll, pitch, yaw rate curves; sticks → FRD rates (roll right, pitch nose-up, yaw right +)."""

    roll: ActualRates = ActualRates()
    pitch: ActualRates = ActualRates()
    yaw: ActualRates = ActualRates()

    def rates(self, roll: float, pitch_up: float, yaw: float) -> tuple[float, float, float]:
        return self.roll.rate(roll), self.pitch.rate(pitch_up), self.yaw.rate(yaw)
