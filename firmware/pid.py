"""Betaflight-style rate PID: rad/s error in, normalised axis demand (the mixer's input) out.

Per axis, in Betaflight's order (`pidController` in `src/main/flight/pid.c`):

    gyro_f  = gyro lowpass2(gyro lowpass(gyro))        # before everything
    e       = Ω* − gyro_f
    P       = kp·e                                     # yaw: through a PT1 (Betaflight's yaw_lowpass_hz)
    I      += ki·dt·e·relax·dyn_ci, clamped to ±iterm_limit
    D       = −kd·d/dt[dterm lowpass2(dterm lowpass(gyro_f))]   # on measurement, not on error
    F       = kff·ff lowpass(dΩ*/dt)                   # setpoint rate of change
    demand  = clamp(P + I + D + F, ±pidsum_limit)

Units. Rates are rad/s, time s. The gains are GymFC's (Koch et al. 2018): its PID took
the error in deg/s and its Betaflight-ported mixer divided the PID sum by Betaflight's
PID_MIXER_SCALING = 1000, so a demand here is (kp·e + ...)·GAIN_SCALE with
GAIN_SCALE = (180/π)/1000 per rad/s, and the paper's [2, 10, 0.005] mean what they meant
there. `iterm_limit` and `pidsum_limit` are in demand units, where 1.0 spans the whole
motor output range (Betaflight's pidsum_limit 500 is 0.5 here).

I-term relax (Betaflight's SETPOINT type): a PT1 (`iterm_relax_cutoff_hz`) of the setpoint
gives a high-pass |Ω* − lpf(Ω*)|; the I accumulation is scaled by
max(0, 1 − hpf / iterm_relax_threshold), so I does not wind up while the setpoint moves
fast. "*_inc" modes relax only the growth of |I|, as Betaflight's RP_INC/RPY_INC.
I-term windup (Betaflight's `iterm_windup`): when the mixer's last motor-mix range
exceeds `iterm_windup`, I accumulation is scaled down to zero at range 1.

The class is pure: no I/O, no clock. It runs at a fixed nominal period, as Betaflight
does (a jittering measured dt would put spikes into D); `set_dt` changes that period.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from fcemu.firmware.filters import LOWPASS_TYPES, PT1Filter, make_lowpass

GAIN_SCALE = math.degrees(1.0) / 1000.0  # demand per (gain · rad/s): GymFC's deg/s over PID_MIXER_SCALING
RELAX_MODES = ("off", "rp", "rpy", "rp_inc", "rpy_inc")

Triple = tuple[float, float, float]


def _triple(value: float | Sequence[float], name: str) -> Triple:
    if isinstance(value, int | float):
        return (float(value),) * 3
    values = tuple(float(v) for v in value)
    if len(values) != 3:
        raise ValueError(f"{name} needs one value per axis (roll, pitch, yaw), got {value!r}")
    return values  # type: ignore[return-value]


@dataclass(frozen=True)
class PIDGains:
    """Gains and settings, each per-axis field as (roll, pitch, yaw). Units: see module doc."""

    kp: Triple
    ki: Triple
    kd: Triple
    kff: Triple = (0.0, 0.0, 0.0)
    iterm_limit: Triple = (0.4, 0.4, 0.4)  # demand units (Betaflight iterm_limit 400)
    pidsum_limit: Triple = (0.5, 0.5, 0.4)  # demand units (Betaflight 500 / 500 / 400)
    gyro_lowpass_hz: float = 0.0  # <= 0: off (the twin's gyro is noise-free by default)
    gyro_lowpass_type: str = "pt1"
    gyro_lowpass2_hz: float = 0.0  # Betaflight's second gyro stage (gyro_lpf2); <= 0: off
    gyro_lowpass2_type: str = "pt1"
    dterm_lowpass_hz: float = 100.0
    dterm_lowpass_type: str = "pt1"
    dterm_lowpass2_hz: float = 0.0  # Betaflight's second D-term stage (dterm_lpf2); <= 0: off
    dterm_lowpass2_type: str = "pt1"
    yaw_p_lowpass_hz: float = 0.0  # Betaflight's yaw_lowpass_hz: a PT1 on the yaw P term; <= 0: off
    ff_lowpass_hz: float = 0.0  # smooths dΩ*/dt; <= 0: off
    iterm_relax: str = "rp"
    iterm_relax_cutoff_hz: float = 15.0
    iterm_relax_threshold: float = math.radians(40.0)  # rad/s of setpoint high-pass for zero I growth
    iterm_windup: float = 1.0  # motor-mix range above which I accumulation fades; 1.0 = off

    def __post_init__(self) -> None:
        for name in ("kp", "ki", "kd", "kff", "iterm_limit", "pidsum_limit"):
            object.__setattr__(self, name, _triple(getattr(self, name), name))
        for kind in (self.gyro_lowpass_type, self.dterm_lowpass_type, self.gyro_lowpass2_type,
                     self.dterm_lowpass2_type):
            if kind not in LOWPASS_TYPES:
                raise ValueError(f"unknown lowpass type {kind!r}; choose one of {LOWPASS_TYPES}")
        if self.iterm_relax not in RELAX_MODES:
            raise ValueError(f"iterm_relax must be one of {RELAX_MODES}, got {self.iterm_relax!r}")
        if self.iterm_relax != "off" and self.iterm_relax_threshold <= 0.0:
            raise ValueError("iterm_relax_threshold must be positive")
        if not 0.0 < self.iterm_windup <= 1.0:
            raise ValueError(f"iterm_windup must be in (0, 1], got {self.iterm_windup}")
        if min(self.iterm_limit + self.pidsum_limit) < 0.0:
            raise ValueError("iterm_limit and pidsum_limit must be >= 0")

    @classmethod
    def from_dict(cls, raw: dict[str, Any]) -> PIDGains:
        known = {f.name for f in fields(cls)}
        unknown = set(raw) - known
        if unknown:
            raise ValueError(f"unknown PID settings {sorted(unknown)}; known: {sorted(known)}")
        return cls(**raw)

    def to_dict(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    def with_(self, **changes: Any) -> PIDGains:
        return replace(self, **changes)


class _Axis:
    """One axis' state and precomputed coefficients, in plain floats (a few µs per tick)."""

    __slots__ = (  # noqa: RUF023 - grouped: coefficients, filters, state, last terms
        "i_inc_only", "ilim", "kd", "kff", "ki_dt", "kp", "relax", "relax_inv", "sumlim",
        "dterm_lpf", "dterm_lpf2", "ff_lpf", "gyro_lpf", "gyro_lpf2", "p_lpf", "relax_lpf",
        "d_prev", "iterm", "sp_prev",
        "d", "f", "i", "p",
    )

    def __init__(self) -> None:
        self.iterm = 0.0
        self.p = self.i = self.d = self.f = 0.0


class RatePID:
    """Three-axis rate PID; `update` returns [roll, pitch, yaw] demands for the mixer."""

    def __init__(self, gains: PIDGains, dt: float = 0.001) -> None:
        self._axes = (_Axis(), _Axis(), _Axis())
        self.gains = gains
        self.dt = float(dt)
        self._configure(reset_state=True)

    @property
    def terms(self) -> dict[str, list[float]]:
        """The last P, I, D, F per axis (demand units), for telemetry and tests."""
        return {t: [getattr(a, t) for a in self._axes] for t in ("p", "i", "d", "f")}

    def set_gains(self, gains: PIDGains) -> None:
        """New gains and filter settings in flight; keeps I and filter states (clamped to new limits)."""
        self.gains = gains
        self._configure(reset_state=False)

    def set_dt(self, dt: float) -> None:
        """A new nominal period (another loop rate); keeps the state."""
        self.dt = float(dt)
        self._configure(reset_state=False)

    def reset(self) -> None:
        """Forget everything (on arming); the next update re-seeds the filters from the gyro."""
        for ax in self._axes:
            ax.iterm = 0.0
            ax.p = ax.i = ax.d = ax.f = 0.0
            ax.sp_prev = 0.0
            ax.d_prev = None
            ax.relax_lpf.reset(0.0)
            ax.ff_lpf.reset(0.0)
            ax.p_lpf.reset(0.0)

    def take_over(self, setpoint: Sequence[float], gyro: Sequence[float]) -> None:
        """Start mid-flight from another controller, as Betaflight's PID does when NEURAL drops.

        There its filters and setpoint derivative ran all along and only the I-term is reset;
        here they start where the gyro and the setpoint are (the gyro's filters as after `reset`,
        from the next update's sample), so neither D nor feedforward kicks. The I-term starts at
        zero rather than at the other controller's last output: that output is a snapshot of a
        controller being handed over for bad inputs, often mid-oscillation (seeded from it, a
        late-telemetry hand-over flew 10x worse than from zero).
        """
        self.reset()
        for ax, sp, raw in zip(self._axes, setpoint, gyro, strict=True):
            ax.sp_prev = sp
            ax.relax_lpf.reset(sp)
            ax.p_lpf.reset(ax.kp * (sp - raw))

    def _configure(self, reset_state: bool) -> None:
        g, dt = self.gains, self.dt
        if dt <= 0.0:
            raise ValueError(f"dt must be positive, got {dt}")
        relax_axes = {"off": 0, "rp": 2, "rp_inc": 2, "rpy": 3, "rpy_inc": 3}[g.iterm_relax]
        for i, ax in enumerate(self._axes):
            ax.kp = g.kp[i] * GAIN_SCALE
            ax.ki_dt = g.ki[i] * GAIN_SCALE * dt
            ax.kd = g.kd[i] * GAIN_SCALE / dt
            ax.kff = g.kff[i] * GAIN_SCALE / dt
            ax.ilim = g.iterm_limit[i]
            ax.sumlim = g.pidsum_limit[i]
            ax.relax = i < relax_axes
            ax.i_inc_only = g.iterm_relax.endswith("_inc")
            ax.relax_inv = 1.0 / g.iterm_relax_threshold if ax.relax else 0.0
            if reset_state:
                ax.gyro_lpf = make_lowpass(g.gyro_lowpass_type, g.gyro_lowpass_hz, dt)
                ax.gyro_lpf2 = make_lowpass(g.gyro_lowpass2_type, g.gyro_lowpass2_hz, dt)
                ax.dterm_lpf = make_lowpass(g.dterm_lowpass_type, g.dterm_lowpass_hz, dt)
                ax.dterm_lpf2 = make_lowpass(g.dterm_lowpass2_type, g.dterm_lowpass2_hz, dt)
                ax.p_lpf = PT1Filter(g.yaw_p_lowpass_hz if i == 2 else 0.0, dt)
                ax.relax_lpf = PT1Filter(g.iterm_relax_cutoff_hz, dt)
                ax.ff_lpf = PT1Filter(g.ff_lowpass_hz, dt)
            else:
                old = (ax.gyro_lpf, ax.gyro_lpf2, ax.dterm_lpf, ax.dterm_lpf2)
                ax.gyro_lpf = _reconfigured(old[0], g.gyro_lowpass_type, g.gyro_lowpass_hz, dt)
                ax.gyro_lpf2 = _reconfigured(old[1], g.gyro_lowpass2_type, g.gyro_lowpass2_hz, dt)
                ax.dterm_lpf = _reconfigured(old[2], g.dterm_lowpass_type, g.dterm_lowpass_hz, dt)
                ax.dterm_lpf2 = _reconfigured(old[3], g.dterm_lowpass2_type, g.dterm_lowpass2_hz, dt)
                new = (ax.gyro_lpf, ax.gyro_lpf2, ax.dterm_lpf, ax.dterm_lpf2)
                if any(a is not b for a, b in zip(old, new, strict=True)):
                    ax.d_prev = None  # a new filter type: re-seed from the next gyro sample
                ax.p_lpf.configure(g.yaw_p_lowpass_hz if i == 2 else 0.0, dt)
                ax.relax_lpf.configure(g.iterm_relax_cutoff_hz, dt)
                ax.ff_lpf.configure(g.ff_lowpass_hz, dt)
                ax.iterm = min(max(ax.iterm, -ax.ilim), ax.ilim)
        self._windup_inv = 1.0 / (1.0 - g.iterm_windup) if g.iterm_windup < 1.0 else 0.0
        if reset_state:
            self.reset()

    def update(self, setpoint: Sequence[float], gyro: Sequence[float], mix_range: float = 0.0) -> list[float]:
        """Setpoint and gyro in rad/s FRD (plain floats are fastest); `mix_range` is the mixer's
        last motor-mix range, for the I-term windup guard. Returns the three axis demands."""
        dyn_ci = 1.0
        if self._windup_inv and mix_range > 0.0:
            dyn_ci = min(max((1.0 - mix_range) * self._windup_inv, 0.0), 1.0)
        out = [0.0, 0.0, 0.0]
        for i, ax in enumerate(self._axes):
            sp = setpoint[i]
            raw = gyro[i]
            if ax.d_prev is None:  # first tick after reset: start the filters where the gyro is
                ax.gyro_lpf.reset(raw)
                ax.gyro_lpf2.reset(raw)
                ax.dterm_lpf.reset(raw)
                ax.dterm_lpf2.reset(raw)
                ax.d_prev = raw
            g = ax.gyro_lpf2.apply(ax.gyro_lpf.apply(raw))
            err = sp - g

            i_err = err
            if ax.relax:
                hpf = abs(sp - ax.relax_lpf.apply(sp))
                iterm = ax.iterm
                if not (ax.i_inc_only and ((iterm > 0.0 and i_err < 0.0) or (iterm < 0.0 and i_err > 0.0))):
                    factor = 1.0 - hpf * ax.relax_inv
                    i_err *= factor if factor > 0.0 else 0.0
            iterm = ax.iterm + ax.ki_dt * dyn_ci * i_err
            lim = ax.ilim
            iterm = lim if iterm > lim else -lim if iterm < -lim else iterm
            ax.iterm = iterm

            p = ax.p_lpf.apply(ax.kp * err)
            gd = ax.dterm_lpf2.apply(ax.dterm_lpf.apply(g))
            d = ax.kd * (ax.d_prev - gd)
            ax.d_prev = gd
            f = ax.kff * ax.ff_lpf.apply(sp - ax.sp_prev) if ax.kff else 0.0
            ax.sp_prev = sp

            total = p + iterm + d + f
            lim = ax.sumlim
            out[i] = lim if total > lim else -lim if total < -lim else total
            ax.p, ax.i, ax.d, ax.f = p, iterm, d, f
        return out


def _reconfigured(filt: Any, kind: str, cutoff_hz: float, dt: float) -> Any:
    """The same filter with new settings and its state kept, or a fresh one if the type changed."""
    fresh = make_lowpass(kind, cutoff_hz, dt)
    if type(fresh) is type(filt):
        filt.configure(cutoff_hz, dt)
        return filt
    return fresh
