"""The header of a Betaflight blackbox log (as orangebox decodes it) read for fcemu: the firmware and
its version, the logging interval, the gyro filters' lag and the rates that turn sticks into a
setpoint (the pilot's tune read from it is `blackbox_tune`'s).

What the header holds, and what it means, changed over Betaflight's versions (3.0 to 4.6 and the
calendar-versioned 2025.x): names (`rcRate` → `rc_rate` → `rc_rates`, `gyro_lowpass_hz` →
`gyro_lpf1_static_hz`, `d_min` → `d_max`), units (`P interval` "1/4" of the loops in 3.0-3.3, the
loops per frame since) and meanings (`iterm_windup`: a motor-mix threshold before 4.6, the I-term
limit after). Each reading below follows the version that wrote the header; the Betaflight source a
rule comes from is named where it is used (src/main/blackbox/blackbox.c writes the header).
`hover_throttle` is Betaflight's mixer throttle (0..1 of the motor output range, the logged
`setpoint[3]` / 1000 in 4.x); the dynamic lowpasses are held there.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from scipy.signal import group_delay

from fcemu.evaluation.identify_log import LogError
from fcemu.firmware.filters import BiquadLowpass, notch_q, pt1_gain

SETPOINT_RATE_LIMIT = 1998.0  # fc/rc.c
LAG_BAND_HZ = np.linspace(5.0, 30.0, 26)  # the rate loop's band: the lag is the mean group delay here
FEATURE_DYNAMIC_FILTER = 1 << 29  # fc/feature.h (dynamic filter: 3.3-4.2)
_PT_CORRECTION = {1: 1.0, 2: 1.553773974, 3: 1.961459177}  # common/filter.c CUTOFF_CORRECTION_PT2/3
_OTHERS = {"inav": "an INAV", "emuflight": "an EmuFlight", "rotorflight": "a Rotorflight",
           "cleanflight": "a Cleanflight", "butterflight": "a Butterflight", "baseflight": "a Baseflight"}
_LOWPASS_KEYS = {  # stage: (type keys, static Hz keys, dynamic (min, max) keys, dynamic expo key)
    "gyro": (("gyro_lpf1_type", "gyro_lowpass_type", "gyro_soft_type"),
             ("gyro_lpf1_static_hz", "gyro_lowpass_hz"), ("gyro_lpf1_dyn_hz", "gyro_lowpass_dyn_hz"),
             "gyro_lpf1_dyn_expo"),
    "gyro2": (("gyro_lpf2_type", "gyro_lowpass2_type"), ("gyro_lpf2_static_hz", "gyro_lowpass2_hz"), (), ""),
    "dterm": (("dterm_lpf1_type", "dterm_filter_type"),
              ("dterm_lpf1_static_hz", "dterm_lowpass_hz", "dterm_lpf_hz"),
              ("dterm_lpf1_dyn_hz", "dterm_lowpass_dyn_hz"), "dterm_lpf1_dyn_expo"),
    "dterm2": (("dterm_lpf2_type", "dterm_filter2_type"), ("dterm_lpf2_static_hz", "dterm_lowpass2_hz"),
               (), ""),
}

Stage = tuple[str, np.ndarray, np.ndarray, float]  # (what, b, a, sample rate Hz)


class _Header:
    """The header, with the keys read recorded (a preset's "source")."""

    def __init__(self, headers: Mapping[str, Any], path: str | Path) -> None:
        self.raw, self.path, self.used = headers, path, {}
        self.version = firmware(headers, path)

    def get(self, *names: str) -> Any:
        for name in names:
            if name in self.raw:
                self.used[name] = self.raw[name]
                return self.raw[name]
        return None

    def nums(self, *names: str) -> list[float] | None:
        value = self.get(*names)
        values = value.split(",") if isinstance(value, str) else value if isinstance(value, list) else [value]
        try:
            return None if value is None else [float(v) for v in values]
        except (TypeError, ValueError):
            return None

    def num(self, *names: str, default: float = 0.0) -> float:
        values = self.nums(*names)
        return values[0] if values else default

    def triple(self, *names: str) -> np.ndarray | None:
        values = self.nums(*names)
        return np.array(values) if values is not None and len(values) == 3 else None

    def looptime_us(self) -> float:
        looptime = self.num("looptime")
        if looptime <= 0:
            raise LogError(f"{self.path}: the header has no looptime: the log's timing cannot be read")
        return looptime


def firmware(headers: Mapping[str, Any], path: str | Path = "blackbox log") -> tuple[int, ...]:
    """Betaflight's version ((4, 2, 8); (2025, 12, 1) for the calendar versions), or a one-line
    LogError naming the firmware that is not Betaflight. Betaflight writes `Firmware type:Cleanflight`
    up to 4.5 and `Betaflight` since, and names itself in `Firmware revision`."""
    revision = str(headers.get("Firmware revision", "")).strip()
    kind = str(headers.get("Firmware type", "")).strip()
    name = (revision.split() or [kind])[0]
    if name.lower() == "betaflight" or (not revision and kind.lower() == "betaflight"):
        found = re.search(r"(\d+)\.(\d+)(?:\.(\d+))?", revision)
        if not found:
            raise LogError(f"{path}: a Betaflight blackbox log of unknown version (Firmware revision "
                           f"{revision!r}): its header cannot be read")
        version = tuple(int(part or 0) for part in found.groups())
        if version < (3, 0):
            raise LogError(f"{path}: a Betaflight {_text(version)} blackbox log: only 3.0 and later are read "
                           "(older versions scale their PID gains differently)")
        return version
    label = " ".join(revision.split()[:2]) or kind or "no Firmware type or revision"
    what = _OTHERS.get(name.lower(), "an unknown firmware's")
    raise LogError(f"{path}: {what} blackbox log ({label}): only Betaflight's are read (its units and fields "
                   "differ)")


def _text(version: tuple[int, ...]) -> str:
    return ".".join(map(str, version))


def _float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        return 0.0


def logged_interval_s(headers: Mapping[str, Any], path: str | Path = "blackbox log") -> float:
    """Seconds between logged main frames, as the header sets them. `looptime` is the gyro loop's
    period (3.x-4.1: gyro.targetLooptime, gyro_sync_denom already in it; 4.2+: the sample period), the
    PID loop runs every `pid_process_denom` of them and the blackbox once per PID loop (fc_core.c)."""
    h = _Header(headers, path)
    pid_loops = max(1.0, h.num("pid_process_denom", default=1.0))
    if h.version < (3, 3) and h.num("gyro_lowpass_hz") == 0:
        pid_loops = 2.0  # fc_core.c setPidUpdateCountDown (3.0-3.2): no gyro lowpass, PID every 2nd loop
    pid_us = h.looptime_us() * pid_loops
    raw = h.get("P interval")
    interval = "" if raw is None else str(raw).strip()
    if "/" in interval:  # 3.0-3.3: `num` of every `denom` PID loops (blackbox-log-viewer reads it so)
        num, denom = (_float(part) for part in interval.split("/", 1))
        if num <= 0 or denom <= 0:
            raise LogError(f"{path}: P interval {interval!r} is not a share of the loops")
        return pid_us * denom / num * 1e-6
    loops = float(interval) if interval else h.num("I interval") / max(1.0, h.num("P ratio", default=1.0))
    if loops <= 0:  # P interval 0: I-frames only (blackbox.c blackboxInit)
        loops = h.num("I interval", default=32.0)
    return pid_us * loops * 1e-6


def _lowpass(h: _Header, stage: str, hover: float | None) -> tuple[str, float, str]:
    """(kind, cutoff Hz (0: off), how it was set) of one of Betaflight's lowpass stages. A dynamic one
    sits at `hover` (sensors/gyro.c dynLpfGyroUpdate, flight/pid.c dynLpfDTermUpdate) or its minimum."""
    types, statics, dynamics, expo_key = _LOWPASS_KEYS[stage]
    # common/filter.h: PT1, BIQUAD; FIR (a moving average) before 3.4; PT2, PT3 since 4.3
    v = h.version
    kinds = ("pt1", "biquad") + (("fir",) if v < (3, 4) else ("pt2", "pt3") if v >= (4, 3) else ())
    code = int(h.num(*types))
    if not 0 <= code < len(kinds):
        raise LogError(f"{h.path}: lowpass type {code} ({types[0]}) is not one of Betaflight {_text(v)}'s")
    kind, hz = kinds[code], h.num(*statics)
    how = f"{kind.upper()} {hz:g} Hz"
    dynamic = h.nums(*dynamics) if dynamics else None
    if dynamic and len(dynamic) == 2 and dynamic[0] > 0:
        low, high = dynamic
        how = f"{kind.upper()} dynamic {low:g}-{high:g} Hz at "
        if hover is None:
            return kind, low, how + "its minimum (no hover throttle given)"
        # the curve's expo: 4.2+ D-term, 4.3+ gyro (default 5, logged since 4.5); dynThrottle before
        expo = h.num(expo_key, default=5.0 if v >= ((4, 3) if stage == "gyro" else (4, 2)) else 0.0)
        if expo > 0:
            hz = (high - low) * (hover * (1 - hover) * expo / 10 + hover) + low
        else:
            hz = max(hover * (1 - hover * hover / 3) * 1.5 * high, low)
        how += f"{hz:.1f} Hz (throttle {hover:.2f})"
    return kind, hz, how


def _lowpass_tf(kind: str, hz: float, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """(b, a) of one of Betaflight's lowpasses at sample rate fs (common/filter.c)."""
    if kind == "biquad":
        b0, b1, b2, a1, a2 = BiquadLowpass(hz, 1.0 / fs).coefficients
        return np.array([b0, b1, b2]), np.array([1.0, a1, a2])
    if kind == "fir":  # firFilterDenoiseInit: a moving average over fs / hz samples, at most 120
        taps = int(np.clip(round(fs / hz), 1, 120))
        return np.full(taps, 1.0 / taps), np.ones(1)
    order = {"pt1": 1, "pt2": 2, "pt3": 3}[kind]
    k = pt1_gain(hz * _PT_CORRECTION[order], 1.0 / fs)
    b, a = np.ones(1), np.ones(1)
    for _ in range(order):
        b, a = np.convolve(b, [k]), np.convolve(a, [1.0, k - 1.0])
    return b, a


def _notch_tf(center_hz: float, q: float, fs: float, weight: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    omega = 2.0 * math.pi * center_hz / fs
    alpha, cos = math.sin(omega) / (2.0 * q), math.cos(omega)
    a = np.array([1.0 + alpha, -2.0 * cos, 1.0 - alpha]) / (1.0 + alpha)
    b = np.array([1.0, -2.0 * cos, 1.0]) / (1.0 + alpha)
    return weight * b + (1.0 - weight) * a, a  # rpm_filter_weights blend a notch with its input


def _delay_s(b: np.ndarray, a: np.ndarray, fs: float) -> float:
    return float(np.mean(group_delay((b, a), w=LAG_BAND_HZ, fs=fs)[1])) / fs


def gyro_filter_lag_s(headers: Mapping[str, Any], hover_throttle: float | None = None,
                      motor_hz: float | None = None, path: str | Path = "blackbox log") -> tuple[float, str]:
    """(seconds, what was counted): how far the logged, filtered `gyroADC` lags the raw gyro, as the
    mean group delay over 5-30 Hz of Betaflight's gyro filter chain (sensors/gyro_init.c,
    gyro_filter_impl.c): lowpass 1 (dynamic: at `hover_throttle`, else its minimum), lowpass 2, the
    static notches, the dynamic notch (approximate: its notches put at dyn_notch_min_hz, the most lag
    they can add) and the RPM filter (only given `motor_hz`, the motors' speed; its notches follow
    them). Since 4.2 lowpass 2 filters every gyro sample (or the samples are averaged) and the rest run
    at the PID rate; before, all run at the gyro rate. The hardware lowpass acts before the raw gyro."""
    h = _Header(headers, path)
    sample_hz = 1e6 / h.looptime_us()
    denom = max(1, int(h.num("pid_process_denom", default=1.0)))
    loop_hz = sample_hz / denom if h.version >= (4, 2) else sample_hz
    stages: list[Stage] = []
    left = ["the gyro's hardware lowpass (before the raw gyro)"]
    for stage, name, fs in (("gyro2", "lowpass 2", sample_hz), ("gyro", "lowpass 1", loop_hz)):
        kind, hz, how = _lowpass(h, stage, hover_throttle)
        if hz > 0 and (kind != "biquad" or hz < fs / 2):
            stages.append((f"{name} {how}", *_lowpass_tf(kind, hz, fs), fs))
        elif hz > 0:
            left.append(f"{name} {how} (above Nyquist: Betaflight leaves it off)")
        elif stage == "gyro2" and h.version >= (4, 2) and denom > 1:
            average = np.full(denom, 1 / denom)
            stages.append((f"the average of {denom} samples", average, np.ones(1), sample_hz))
    for center, cut in zip(h.nums("gyro_notch_hz") or [], h.nums("gyro_notch_cutoff") or [], strict=False):
        if 0 < cut < center < loop_hz / 2:
            q = notch_q(center, cut)
            stages.append((f"notch {center:g}/{cut:g} Hz", *_notch_tf(center, q, loop_hz), loop_hz))
    dynamic = int(h.num("features")) & FEATURE_DYNAMIC_FILTER
    q, low = h.num("dyn_notch_q") / 100, h.num("dyn_notch_min_hz")
    centers: list[float] = []
    if "dyn_notch_count" in h.raw:  # 4.3+: dyn_notch_count notches per axis
        centers = [low] * int(h.num("dyn_notch_count"))
    elif "dyn_notch_q" in h.raw and dynamic:  # 4.1-4.2 (gyroanalyse.c): one, or two width% either side
        width = h.num("dyn_notch_width_percent") / 100
        centers = [low * (1 - width), low * (1 + width)] if width else [low]
    elif h.version >= (3, 3) and dynamic:
        left.append("the dynamic notch (on; its settings are not in this version's header)")
    for center in centers if q > 0 and low > 0 else []:
        stages.append((f"dynamic notch {center:g} Hz Q {q:g} (at its lowest: approximate)",
                       *_notch_tf(center, q, loop_hz), loop_hz))
    harmonics = int(h.num("rpm_filter_harmonics", "gyro_rpm_notch_harmonics"))
    if harmonics and h.num("dshot_bidir"):
        rpm_q = h.num("rpm_filter_q", "gyro_rpm_notch_q", default=500.0) / 100
        rpm_min = h.num("rpm_filter_min_hz", "gyro_rpm_notch_min", default=100.0)
        weights = [w / 100 for w in h.nums("rpm_filter_weights") or [100.0] * harmonics]
        for k, weight in enumerate(weights[:harmonics] if motor_hz else [], start=1):
            center = max(k * motor_hz, rpm_min)  # type: ignore[operator]  # rpm_filter.c: held at its minimum
            if center < loop_hz / 2 and weight > 0:
                stages += [(f"RPM notch {center:.0f} Hz Q {rpm_q:g} (motor {m})",
                            *_notch_tf(center, rpm_q, loop_hz, weight), loop_hz) for m in range(1, 5)]
        if not motor_hz:
            bound = 4 * _delay_s(*_notch_tf(rpm_min, rpm_q, loop_hz), loop_hz)
            left.append(f"the RPM filter (no motor speed given; 4 motors' notches at its {rpm_min:g} Hz "
                        f"minimum would add {bound * 1e3:.2f} ms)")
    delays = [_delay_s(b, a, fs) for _, b, a, fs in stages]
    lag = float(sum(delays))
    parts = "; ".join(f"{what} {d * 1e3:.3f} ms" for (what, *_), d in zip(stages, delays, strict=True))
    return lag, (f"gyroADC lags the raw gyro by {lag * 1e3:.3f} ms (mean group delay over 5-30 Hz): "
                 f"{parts or 'no filters'}; not counted: {'; '.join(left)}")




def stick_setpoint_dps(headers: Mapping[str, Any], rc_command: np.ndarray,
                       path: str | Path = "blackbox log") -> np.ndarray:
    """(N, 3) roll, pitch, yaw rate setpoints in deg/s (Betaflight's axes and signs, as its logged
    `setpoint[0..2]`) from the logged `rcCommand[0..2]` (after the deadband, ±500) through the log's
    rates (fc/rc.c calculateSetpointRate, applyRates). 3.3-4.1 choose a rates type the header does
    not give: Betaflight's (the default) is assumed; 4.3+'s quick_rates_rc_expo is assumed off."""
    h = _Header(headers, path)
    rc = np.asarray(rc_command, dtype=float)
    if rc.ndim != 2 or rc.shape[1] != 3:
        raise ValueError(f"rc_command must be (N, 3), got {rc.shape}")

    def per_axis(name: str, roll_pitch: tuple[str, str], yaw: tuple[str, str]) -> np.ndarray:
        values = h.triple(name)  # 3.3+: one per axis; 3.0-3.2: roll/pitch and yaw apart
        return values if values is not None else np.array([h.num(*roll_pitch)] * 2 + [h.num(*yaw)])

    rc_rate = per_axis("rc_rates", ("rcRate", "rc_rate"), ("rcYawRate", "rc_rate_yaw"))
    expo = per_axis("rc_expo", ("rcExpo", "rc_expo"), ("rcYawExpo", "rc_expo_yaw")) / 100
    rates = h.triple("rates")
    rates = np.zeros(3) if rates is None else rates
    divider = 500.0
    if h.version >= (4, 2):  # rcCommandDivider: full stick reaches 1 past the deadband
        divider = 500.0 - np.array([h.num("deadband")] * 2 + [h.num("yaw_deadband")])
    x = rc / divider
    ax = np.abs(x)
    kind = int(h.num("rates_type"))
    if kind == 0:  # BETAFLIGHT
        rate = np.where(rc_rate > 200, rc_rate / 100 + 14.54 * (rc_rate / 100 - 2), rc_rate / 100)
        curved = x * ax ** 3 * expo + x * (1 - expo)
        stick = np.abs(curved) if h.version < (3, 1) else ax  # 3.0's super rate on the expo'd stick (mw.c)
        out = 200 * rate * curved / np.where(rates > 0, np.clip(1 - stick * rates / 100, 0.01, 1.0), 1.0)
    elif kind == 1:  # RACEFLIGHT
        out = 10 * rc_rate * (1 + expo * (x * x - 1)) * x * (1 + ax * rates / 100)
    elif kind == 2:  # KISS
        use = 1 / np.clip(1 - ax * rates / 100, 0.01, 1.0)
        out = np.clip(2000 * use * (x ** 3 * expo + x * (1 - expo)) * rc_rate / 1000, -1998, 1998)
    elif kind == 3:  # ACTUAL
        center = rc_rate * 10
        out = x * center + np.maximum(0, rates * 10 - center) * ax * (x ** 5 * expo + x * (1 - expo))
    elif kind == 4:  # QUICK
        rate = np.maximum(rc_rate * 2, 1e-9)
        ratio = np.maximum(rates * 10, rate) / rate
        curve = ax ** 3 * expo + ax * (1 - expo)
        out = np.clip(x * rate / np.clip(1 - curve * (ratio - 1) / ratio, 0.01, 1.0), -1998, 1998)
    else:
        raise LogError(f"{path}: rates_type {kind} is not one of Betaflight {_text(h.version)}'s")
    limit = h.triple("rate_limits")  # 4.0+; SETPOINT_RATE_LIMIT before
    limit = np.full(3, SETPOINT_RATE_LIMIT) if limit is None else limit
    return np.clip(out, -limit, limit)


def yaw_motors_reversed(headers: Mapping[str, Any]) -> bool | None:
    """`yaw_motors_reversed` where the header has it, else None (unknown): Betaflight (3.0 to 2025.12)
    never writes it to the blackbox header; a CLI dump (`get yaw_motors_reversed`) says."""
    value = headers.get("yaw_motors_reversed")
    return None if value is None else str(value).strip().upper() in ("1", "ON", "TRUE")
