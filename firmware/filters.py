"""Betaflight's gyro and D-term filters: PT1, biquad lowpass and biquad notch.

Coefficients and difference equations follow Betaflight's `src/main/common/filter.c`
(`pt1FilterGain`, `biquadFilterUpdate`, `biquadFilterApply`), with exact `math.sin`/`cos`
where Betaflight uses its polynomial `sin_approx`/`cos_approx` (they agree to ~1e-6).

Every filter works on a float or on a numpy array of any shape: its state starts as the
scalar 0.0 and broadcasts to the first input's shape, so one instance can filter three
axes at once (`apply(np.array([p, q, r]))`) or one axis in plain floats, which is several
times faster for the few numbers a rate loop handles per tick. A cutoff <= 0 disables a
filter: `apply` then returns its input unchanged.
"""

from __future__ import annotations

import math
from typing import TypeVar

import numpy as np

BUTTERWORTH_Q = 1.0 / math.sqrt(2.0)

Signal = TypeVar("Signal", float, np.ndarray)


def pt1_gain(cutoff_hz: float, dt: float) -> float:
    """Betaflight's `pt1FilterGain`: k = dt / (RC + dt), RC = 1 / (2π f_c).

    Equivalently k = ω·dt / (ω·dt + 1) with ω = 2π f_c (the form in Betaflight ≥ 4.3).
    """
    rc = 1.0 / (2.0 * math.pi * cutoff_hz)
    return dt / (rc + dt)


def notch_q(center_hz: float, cutoff_hz: float) -> float:
    """Betaflight's `filterGetNotchQ`: Q = f0·f1 / (f0² − f1²), f1 the lower -3 dB edge."""
    if not 0.0 < cutoff_hz < center_hz:
        raise ValueError(f"notch cutoff {cutoff_hz} Hz must lie between 0 and the centre {center_hz} Hz")
    return center_hz * cutoff_hz / (center_hz * center_hz - cutoff_hz * cutoff_hz)


class PT1Filter:
    """First-order lowpass: y[n] = y[n−1] + k·(x[n] − y[n−1]), k from `pt1_gain`."""

    __slots__ = ("cutoff_hz", "dt", "enabled", "k", "state")

    def __init__(self, cutoff_hz: float, dt: float) -> None:
        self.state: float | np.ndarray = 0.0
        self.configure(cutoff_hz, dt)

    def configure(self, cutoff_hz: float, dt: float) -> None:
        """Set cutoff and sample period; keeps the state (Betaflight's `pt1FilterUpdateCutoff`)."""
        if dt <= 0.0:
            raise ValueError(f"dt must be positive, got {dt}")
        self.cutoff_hz, self.dt = float(cutoff_hz), float(dt)
        self.enabled = cutoff_hz > 0.0
        self.k = pt1_gain(cutoff_hz, dt) if self.enabled else 1.0

    def reset(self, value: float | np.ndarray = 0.0) -> None:
        """Start over as if the input had always been `value` (steady state)."""
        self.state = np.array(value, dtype=float) if isinstance(value, np.ndarray) else float(value)

    def apply(self, x: Signal) -> Signal:
        if not self.enabled:
            return x
        y = self.state + self.k * (x - self.state)
        self.state = y
        return y


class _Biquad:
    """A biquad in Betaflight's transposed direct form II (`biquadFilterApply`):

        y  = b0·x + s1
        s1 = b1·x − a1·y + s2
        s2 = b2·x − a2·y

    with coefficients already divided by a0.
    """

    __slots__ = ("a1", "a2", "b0", "b1", "b2", "dt", "enabled", "s1", "s2")

    def __init__(self) -> None:
        self.b0, self.b1, self.b2, self.a1, self.a2 = 1.0, 0.0, 0.0, 0.0, 0.0
        self.s1: float | np.ndarray = 0.0
        self.s2: float | np.ndarray = 0.0
        self.enabled = False
        self.dt = 0.0

    def _set(self, b0: float, b1: float, b2: float, a0: float, a1: float, a2: float) -> None:
        self.b0, self.b1, self.b2 = b0 / a0, b1 / a0, b2 / a0
        self.a1, self.a2 = a1 / a0, a2 / a0

    @staticmethod
    def _omega(freq_hz: float, dt: float) -> float:
        if dt <= 0.0:
            raise ValueError(f"dt must be positive, got {dt}")
        if freq_hz >= 0.5 / dt:
            raise ValueError(f"{freq_hz} Hz is at or above the Nyquist frequency {0.5 / dt:g} Hz")
        return 2.0 * math.pi * freq_hz * dt

    @property
    def coefficients(self) -> tuple[float, float, float, float, float]:
        """(b0, b1, b2, a1, a2), normalised by a0."""
        return self.b0, self.b1, self.b2, self.a1, self.a2

    def reset(self, value: float | np.ndarray = 0.0) -> None:
        """Start in steady state at `value` (both shapes have unit DC gain)."""
        v = np.array(value, dtype=float) if isinstance(value, np.ndarray) else float(value)
        self.s1 = (1.0 - self.b0) * v
        self.s2 = (self.b2 - self.a2) * v

    def apply(self, x: Signal) -> Signal:
        if not self.enabled:
            return x
        y = self.b0 * x + self.s1
        self.s1 = self.b1 * x - self.a1 * y + self.s2
        self.s2 = self.b2 * x - self.a2 * y
        return y


class BiquadLowpass(_Biquad):
    """Second-order lowpass, RBJ cookbook / Betaflight `FILTER_LPF` (Butterworth at Q = 1/√2).

    ω = 2π f_c·dt, α = sin ω / (2Q); b1 = 1 − cos ω, b0 = b2 = b1/2,
    a0 = 1 + α, a1 = −2 cos ω, a2 = 1 − α.
    """

    __slots__ = ("cutoff_hz", "q")

    def __init__(self, cutoff_hz: float, dt: float, q: float = BUTTERWORTH_Q) -> None:
        super().__init__()
        self.configure(cutoff_hz, dt, q)

    def configure(self, cutoff_hz: float, dt: float, q: float | None = None) -> None:
        """Set cutoff, period (and Q); keeps the state, like `biquadFilterUpdateLPF`."""
        self.cutoff_hz, self.dt = float(cutoff_hz), float(dt)
        self.q = float(q) if q is not None else getattr(self, "q", BUTTERWORTH_Q)
        self.enabled = cutoff_hz > 0.0
        if not self.enabled:
            return
        omega = self._omega(cutoff_hz, dt)
        sn, cs = math.sin(omega), math.cos(omega)
        alpha = sn / (2.0 * self.q)
        b1 = 1.0 - cs
        self._set(b1 * 0.5, b1, b1 * 0.5, 1.0 + alpha, -2.0 * cs, 1.0 - alpha)


class BiquadNotch(_Biquad):
    """Notch, RBJ cookbook / Betaflight `FILTER_NOTCH`, zero gain at `center_hz`.

    Q from the lower -3 dB edge `cutoff_hz` (Betaflight's `dterm_notch_cutoff`) via `notch_q`.
    b0 = b2 = 1, b1 = −2 cos ω, a0 = 1 + α, a1 = −2 cos ω, a2 = 1 − α.
    """

    __slots__ = ("center_hz", "cutoff_hz", "q")

    def __init__(self, center_hz: float, cutoff_hz: float, dt: float) -> None:
        super().__init__()
        self.configure(center_hz, cutoff_hz, dt)

    def configure(self, center_hz: float, cutoff_hz: float, dt: float) -> None:
        self.center_hz, self.cutoff_hz, self.dt = float(center_hz), float(cutoff_hz), float(dt)
        self.enabled = center_hz > 0.0 and cutoff_hz > 0.0
        if not self.enabled:
            self.q = 0.0
            return
        self.q = notch_q(center_hz, cutoff_hz)
        omega = self._omega(center_hz, dt)
        sn, cs = math.sin(omega), math.cos(omega)
        alpha = sn / (2.0 * self.q)
        self._set(1.0, -2.0 * cs, 1.0, 1.0 + alpha, -2.0 * cs, 1.0 - alpha)


Lowpass = PT1Filter | BiquadLowpass
LOWPASS_TYPES = ("pt1", "biquad")


def make_lowpass(kind: str, cutoff_hz: float, dt: float) -> Lowpass:
    """A lowpass by Betaflight's type name ("pt1" or "biquad")."""
    if kind == "pt1":
        return PT1Filter(cutoff_hz, dt)
    if kind == "biquad":
        return BiquadLowpass(cutoff_hz, dt)
    raise ValueError(f"unknown lowpass type {kind!r}; choose one of {LOWPASS_TYPES}")
