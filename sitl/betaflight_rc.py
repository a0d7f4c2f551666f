"""Betaflight's sticks and throttle for fcemu's rate setpoints and collective (`RcMap`).

Sticks. Betaflight's channel map is AETR1234 and its rate axes are FLU-like (stick forward =
nose down, its yaw sign flipped in `updateRcCommands`), so for FRD rates: roll and yaw channels
= 1500 + 500·x, pitch = 1500 − 500·x. With ACTUAL rates whose centre sensitivity equals the
maximum rate R (no expo), Betaflight's setpoint is exactly R·(channel − 1500)/500 deg/s, so
`RcMap.setpoint` knows the command Betaflight flies to the µs it was sent with.

Throttle. Betaflight's mixer throttle is `rcLookupThrottle((ch − min_check)·1000 // (2000 −
min_check))`, linear by default, over its output range [1000 + motor_idle, 2000] µs; fcemu's
throttle is a fraction of [1000, 2000] µs. `RcMap.fcemu_throttle` converts, so both mixers put
the same µs on the motors at zero demand.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

MIN_CHECK_US = 1050  # Betaflight's min_check default
MOTOR_IDLE = 0.055  # Betaflight's motor_idle 550 (percent · 100), PWM protocol


@dataclass(frozen=True)
class RcMap:
    """FRD rate setpoints and throttle ↔ Betaflight RC channels (AETR1234, arm on AUX1)."""

    rate_dps: float = 400.0  # ACTUAL rates: centre sensitivity = max rate, no expo → linear
    min_check_us: int = MIN_CHECK_US
    motor_idle: float = MOTOR_IDLE

    def settings(self) -> list[str]:
        r = round(self.rate_dps / 10)
        if r * 10 != self.rate_dps or not 1 <= r <= 255:
            raise ValueError(f"rate must be a multiple of 10 deg/s in 10..2550, got {self.rate_dps}")
        axes = ("roll", "pitch", "yaw")
        return [f"set {a}_{key} = {r}" for a in axes for key in ("rc_rate", "srate")] \
            + [f"set {a}_expo = 0" for a in axes]

    def stick_channels(self, rates_frd: Sequence[float]) -> tuple[int, int, int]:
        """(roll, pitch, yaw) channel µs for FRD rates in rad/s, rounded to the µs."""
        per_us = self.rate_dps / 500.0
        p, q, r = (math.degrees(float(v)) / per_us for v in rates_frd)
        return (_channel(1500 + p), _channel(1500 - q), _channel(1500 + r))

    def setpoint(self, channels: tuple[int, int, int]) -> np.ndarray:
        """The FRD rates (rad/s) Betaflight flies for those stick channels."""
        roll, pitch, yaw = channels
        per_us = self.rate_dps / 500.0
        return np.radians([(roll - 1500) * per_us, (1500 - pitch) * per_us, (yaw - 1500) * per_us])

    def quantise(self, rates_frd: np.ndarray) -> np.ndarray:
        """Commands as Betaflight will fly them: (..., 3) rad/s in, the same shape out."""
        flat = np.asarray(rates_frd, dtype=float).reshape(-1, 3)
        out = np.array([self.setpoint(self.stick_channels(r)) for r in flat])
        return out.reshape(np.shape(rates_frd))

    def throttle_channel(self, fcemu_throttle: float) -> int:
        """The throttle channel nearest to fcemu's throttle (fraction of 1000..2000 µs)."""
        out_low = 1000.0 + 1000.0 * self.motor_idle
        frac = (1000.0 + 1000.0 * fcemu_throttle - out_low) / (2000.0 - out_low)
        return _channel(self.min_check_us + frac * (2000 - self.min_check_us))

    def bf_throttle(self, channel: int) -> float:
        """Betaflight's mixer throttle (0..1 of its output range) for a throttle channel."""
        tmp = min(max(channel, self.min_check_us), 2000)
        return ((tmp - self.min_check_us) * 1000 // (2000 - self.min_check_us)) / 1000.0

    def fcemu_throttle(self, channel: int) -> float:
        """fcemu's throttle giving the same zero-demand motor output as Betaflight at `channel`."""
        out_low = 1000.0 + 1000.0 * self.motor_idle
        return (out_low + (2000.0 - out_low) * self.bf_throttle(channel) - 1000.0) / 1000.0


def _channel(us: float) -> int:
    return int(min(max(round(us), 1000), 2000))
