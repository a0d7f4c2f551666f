"""The pilot's tune read from a Betaflight blackbox log's header: its rate PID as an fcemu PID preset.

`log_tune` maps Betaflight's rate PID onto fcemu's (`firmware/presets/pid_betaflight.json`'s shape).
The P/I/D gains times flight/pid.h's PTERM_SCALE, ITERM_SCALE and DTERM_SCALE are fcemu's gains
(Betaflight's pidCoefficient), feedforward times FEEDFORWARD_SCALE (3.5+; before, the D-term's
setpoint weight as a feedforward); D rests at d_min in 4.0-4.5; yaw Ki is x2.5 without integrated
yaw (4.0+); TPA is held at `hover_throttle` (Betaflight's mixer throttle, 0..1 of the motor output
range), on P and D in 3.x and D alone in 4.x unless tpa_mode is PD; `iterm_windup` is a motor-mix
threshold before 4.6 and the I-term limit after; each lowpass becomes one of fcemu's (PT1, biquad)
with the same low-frequency lag; the mixer takes the idle and airmode. What fcemu's PID does not
model (anti-gravity, d_min's dynamics, notches, RPM filter, ...) is listed with its values in
"not_modelled", and every header key read in "source". The header itself is read by
`blackbox_header`.
"""

from __future__ import annotations

import math
import re
import struct
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from fcemu.evaluation.blackbox_header import (
    _PT_CORRECTION,
    _Header,
    _lowpass,
    _text,
    yaw_motors_reversed,
)
from fcemu.evaluation.identify_log import LogError
from fcemu.firmware.pid import PIDGains

PTERM_SCALE, ITERM_SCALE, DTERM_SCALE = 0.032029, 0.244381, 0.000529  # flight/pid.h, all versions
FEEDFORWARD_SCALE = 0.013754  # flight/pid.h since 3.5: Kf = FEEDFORWARD_SCALE * F / 100
ITERM_RELAX_THRESHOLD_DPS = 40.0  # flight/pid.h ITERM_RELAX_SETPOINT_THRESHOLD (4.0+)
FCEMU_BIQUAD_MAX_HZ = 450.0  # fcemu's rate loop runs at 1 kHz: a biquad's cutoff must stay below 500 Hz
FEATURE_AIRMODE = 1 << 22  # fc/feature.h
_RELAX_MODES = ("off", "rp", "rpy", "rp_inc", "rpy_inc")  # flight/pid.h itermRelax_e
_NOT_MODELLED_KEYS = """
anti-gravity: anti_gravity_mode anti_gravity_gain anti_gravity_threshold anti_gravity_cutoff_hz
anti-gravity: anti_gravity_p_gain
D-min/D-max dynamics: d_min d_max d_min_gain d_min_advance d_max_gain d_max_advance
feedforward shaping: feedforward_transition feedforward_averaging feedforward_smooth_factor feedforward_boost
feedforward shaping: feedforward_jitter_factor feedforward_max_rate_limit ff_interpolate_sp ff_spike_limit
feedforward shaping: ff_max_rate_limit ff_boost feedforward_yaw_hold_gain feedforward_yaw_hold_time
3.x setpoint weight transition: setpointRelaxRatio setpoint_relaxation_ratio
static gyro notches: gyro_notch_hz gyro_notch_cutoff
D-term notch: dterm_notch_hz dterm_notch_cutoff
dynamic notch: dyn_notch_count dyn_notch_q dyn_notch_min_hz dyn_notch_max_hz dyn_notch_width_percent
dynamic notch: dyn_notch_range
RPM filter: dshot_bidir gyro_rpm_notch_harmonics gyro_rpm_notch_q gyro_rpm_notch_min rpm_notch_lpf
RPM filter: rpm_filter_q dterm_rpm_notch_harmonics dterm_rpm_notch_q dterm_rpm_notch_min rpm_filter_harmonics
RPM filter: rpm_filter_weights rpm_filter_min_hz rpm_filter_fade_range_hz rpm_filter_lpf_hz
TPA dynamics: tpa_mode tpa_rate dynThrPID tpa_breakpoint tpa_curve_type tpa_low_rate tpa_low_breakpoint
TPA dynamics: tpa_low_always
throttle boost: throttle_boost throttle_boost_cutoff
absolute control: abs_control_gain
integrated yaw: use_integrated_yaw
battery compensation: vbat_pid_compensation vbat_pid_gain vbat_sag_compensation
RC smoothing: rc_smoothing_type rc_smoothing rc_smoothing_cutoffs rc_smoothing_filter_type
RC smoothing: rc_smoothing_auto_factor rc_smoothing_active_cutoffs rc_smoothing_active_cutoffs_ff_sp_thr
RC smoothing: rc_interpolation rc_interpolation_interval rc_interpolation_channels
setpoint acceleration limits: acc_limit acc_limit_yaw rateAccelLimit yawRateAccelLimit
yaw P limit: yaw_p_limit
D-term averaging: dterm_average_count
dynamic idle: dyn_idle_min_rpm dyn_idle_p_gain dyn_idle_i_gain dyn_idle_d_gain dyn_idle_max_increase
thrust linearization: thrust_linear
motor output / throttle limits: motor_output_limit throttle_limit_type throttle_limit_percent
S-term: s_roll s_pitch s_yaw
TPA dynamics: tpa_curve_stall_throttle tpa_curve_pid_thr0 tpa_curve_pid_thr100 tpa_curve_expo tpa_speed_type
setpoint PID attenuation: spa_roll_center spa_roll_width spa_roll_mode spa_pitch_center spa_pitch_width
setpoint PID attenuation: spa_pitch_mode spa_yaw_center spa_yaw_width spa_yaw_mode
PID at zero throttle: pidAtMinThrottle pid_at_min_throttle
mixer type (fcemu's is Betaflight's LEGACY): mixer_type
EZ landing: ez_landing_threshold ez_landing_limit ez_landing_speed
"""
_NOT_MODELLED: dict[str, list[str]] = {}  # what fcemu's PID lacks: its header keys
for _line in _NOT_MODELLED_KEYS.strip().splitlines():
    _what, _keys = _line.rsplit(": ", 1)
    _NOT_MODELLED.setdefault(_what, []).extend(_keys.split())
_FLOAT_BITS = ("anti_gravity_gain", "yawRateAccelLimit", "rateAccelLimit")  # 3.0/3.1 log floats' bits


def _fcemu_lowpass(kind: str, hz: float, fs: float) -> tuple[str, float, str]:
    """A Betaflight lowpass as one of fcemu's (pt1, biquad) that keeps its low-frequency lag; a biquad
    at or above FCEMU_BIQUAD_MAX_HZ becomes a PT1 (fcemu's 1 kHz loop cannot run it)."""
    if hz <= 0 or kind == "pt1":
        return "pt1", max(hz, 0.0), ""
    if kind == "fir":  # a moving average's lag (taps - 1) / 2 samples as a PT1's 1 / (2π f)
        taps = int(np.clip(round(fs / hz), 1, 120))
        return "pt1", fs / (math.pi * max(taps - 1, 1)), f"FIR {hz:g} Hz as a PT1 of its lag"
    order = {"biquad": 2, "pt2": 2, "pt3": 3}[kind]  # n PT1s at c·f lag n / (2π c f); a biquad √2 / (2π f)
    biquad = hz if kind == "biquad" else math.sqrt(2) * _PT_CORRECTION[order] * hz / order
    if biquad >= FCEMU_BIQUAD_MAX_HZ:
        return "pt1", biquad / math.sqrt(2), f"{kind.upper()} as a PT1 of its lag (a biquad there: too fast)"
    return "biquad", biquad, "" if kind == "biquad" else f"{kind.upper()} as a biquad of its lag"


def _tpa(h: _Header, hover: float | None) -> tuple[float, float, str]:
    """(factor on P, factor on D, what) of TPA at the hover throttle: 1 - rate × the throttle's share
    above the breakpoint (fc/rc.c on the throttle stick to 4.2, pid.c pidUpdateTpaFactor since). It
    scales P and D in 3.x, D alone in 4.x unless tpa_mode is PD (0; logged since 4.4, default D)."""
    rate = h.num("tpa_rate", "dynThrPID") / 100
    breakpoint = (h.num("tpa_breakpoint", default=1500.0) - 1000) / 1000
    d_only = h.version >= (4, 0) and h.num("tpa_mode", default=1.0) == 1
    if rate <= 0 or hover is None:
        return 1.0, 1.0, "TPA " + ("off" if rate <= 0 else "left out (no hover throttle given)")
    factor = 1.0 - rate * float(np.clip((hover - breakpoint) / max(1 - breakpoint, 1e-3), 0.0, 1.0))
    what = f"TPA (rate {rate * 100:g}, breakpoint {breakpoint * 1000 + 1000:g}) at throttle {hover:.2f}"
    return (1.0 if d_only else factor), factor, f"{what}: {factor:.3f} x {'D' if d_only else 'P and D'}"


def log_tune(headers: Mapping[str, Any], path: str | Path = "blackbox log",
             hover_throttle: float | None = None) -> dict[str, Any]:
    """The log's own rate PID as an fcemu PID preset (firmware/presets/pid_betaflight.json's shape, plus
    "not_modelled" and "source"), held at `hover_throttle` where Betaflight's gains move with it."""
    h = _Header(headers, path)
    v = h.version
    pids = [h.nums(f"{axis}PID") for axis in ("roll", "pitch", "yaw")]
    if any(pid is None or len(pid) < 3 for pid in pids):
        raise LogError(f"{path}: the header lacks rollPID, pitchPID or yawPID: no PID to read")
    p, i, d = np.array([pid[:3] for pid in pids]).T  # type: ignore[index]
    notes: list[str] = []
    rest_d, d_min = d.copy(), h.triple("d_min")
    if d_min is not None and "d_max" not in h.raw:  # 4.0-4.5: D rests at d_min, rises to D on sharp moves
        rest_d = np.where((d_min > 0) & (d_min < d), d_min, d)
        notes.append(f"D at its resting d_min {d_min.tolist()} (D {d.tolist()} on sharp moves)")
    tpa_p, tpa_d, tpa_text = _tpa(h, hover_throttle)
    kp, ki, kd = p * PTERM_SCALE * tpa_p, i * ITERM_SCALE, rest_d * DTERM_SCALE * tpa_d
    if v >= (4, 0) and not h.num("use_integrated_yaw"):
        ki[2] *= 2.5  # pidInitConfig: yaw Ki x2.5 unless integrated yaw (4.0+)
        notes.append("yaw Ki x2.5 (pidInitConfig, integrated yaw off)")
    if v < (3, 5) and kd[2]:
        kd[2] = 0.0  # pidController: no yaw D before 3.5
        notes.append(f"yaw D {d[2]:g} unused (no yaw D before 3.5)")
    if v >= (3, 5):
        weight = h.nums("ff_weight", "feedforward_weight") or [0.0] * 3
        kff = np.array(weight[:3]) * FEEDFORWARD_SCALE / 100
        notes.append(f"feedforward {weight} x FEEDFORWARD_SCALE/100")
    else:  # 3.0-3.4: D acts on c·setpoint - gyro; c·Kd on the setpoint's derivative is a feedforward
        c = h.num("dtermSetpointWeight", "dterm_setpoint_weight") / (127 if (3, 2) <= v < (3, 4) else 100)
        kff = np.array([kd[0] * c, kd[1] * c, 0.0])
        notes.append(f"D-term setpoint weight {c:.3f} as feedforward c x Kd")
    if "pidsum_limit" in h.raw:
        pidsum = np.array([h.num("pidsum_limit")] * 2 + [h.num("pidsum_limit_yaw", default=400.0)]) / 1000
    else:
        pidsum = np.full(3, 0.5)  # 3.0/3.1: pidsum_limit (a float, default 0.5) is not in the header
    windup = h.num("iterm_windup", "itermWindupPointPercent", default=100.0)
    if v >= (4, 6):  # pid_init.c: the I-term limit is iterm_windup % of pidsum_limit; no mix-range windup
        iterm_limit, windup_f = pidsum * windup / 100, 1.0
    else:  # itermLimit is not in the header: its default (3.2-3.5 150, 4.0-4.5 400; 3.0/3.1 none)
        iterm_limit = pidsum.copy() if v < (3, 2) else np.full(3, 0.15 if v < (4, 0) else 0.4)
        windup_f = float(np.clip(windup / 100, 0.01, 1.0))
    relax, relax_hz = "off", 15.0
    if "iterm_relax" in h.raw:  # 4.1+
        relax, relax_hz = _RELAX_MODES[int(h.num("iterm_relax"))], h.num("iterm_relax_cutoff", default=15.0)
        if relax != "off" and h.num("iterm_relax_type", default=1.0) == 0:
            notes.append("iterm_relax_type GYRO relaxed on the setpoint instead (fcemu's only type)")
    elif v >= (4, 0):
        relax, relax_hz = "rp", 20.0
        notes.append("I-term relax: 4.0's defaults RP, setpoint, 20 Hz (not in its header)")
    gyro_hz = 1e6 / h.looptime_us()  # a FIR (3.0-3.3) ran on every gyro sample, the D-term at the PID rate
    pid_hz = gyro_hz / max(1.0, h.num("pid_process_denom", default=1.0))
    lp = {}
    for stage in ("gyro", "gyro2", "dterm", "dterm2"):
        kind, hz, how = _lowpass(h, stage, hover_throttle)
        lp[stage] = _fcemu_lowpass(kind, hz, gyro_hz if "gyro" in stage else pid_hz)
        if hz > 0:
            notes.append(f"{stage} lowpass {how}" + (f" ({lp[stage][2]})" if lp[stage][2] else ""))
    yaw_lpf = h.num("yaw_lowpass_hz", "yaw_lpf_hz")
    ff_lpf = lp["dterm"][1] if v < (3, 2) and kff.any() else 0.0  # 3.0/3.1 filter D after the setpoint
    gains = PIDGains(
        kp=tuple(kp), ki=tuple(ki), kd=tuple(kd), kff=tuple(kff), iterm_limit=tuple(iterm_limit),
        pidsum_limit=tuple(pidsum), gyro_lowpass_hz=lp["gyro"][1], gyro_lowpass_type=lp["gyro"][0],
        gyro_lowpass2_hz=lp["gyro2"][1], gyro_lowpass2_type=lp["gyro2"][0], dterm_lowpass_hz=lp["dterm"][1],
        dterm_lowpass_type=lp["dterm"][0], dterm_lowpass2_hz=lp["dterm2"][1], yaw_p_lowpass_hz=yaw_lpf,
        dterm_lowpass2_type=lp["dterm2"][0], ff_lowpass_hz=ff_lpf, iterm_relax=relax, iterm_windup=windup_f,
        iterm_relax_cutoff_hz=relax_hz, iterm_relax_threshold=math.radians(ITERM_RELAX_THRESHOLD_DPS))
    idle_setting = h.get("motor_idle", "dshot_idle_value", "digitalIdleOffset")
    output = h.nums("motorOutput") or [0.0, 2047.0]
    if output[-1] > 2000 and idle_setting is not None:  # DShot: idle in 0.01 % of the output range
        idle = float(idle_setting) / 10000
    else:  # analog: motorOutput starts at minthrottle (µs)
        idle = float(np.clip((output[0] - 1000) / 1000, 0.0, 0.99))
    airmode = bool(int(h.num("features")) & FEATURE_AIRMODE)
    mixer: dict[str, Any] = {"table": "betaflight", "idle": round(idle, 6), "airmode": airmode}
    if (yaw_reversed := yaw_motors_reversed(h.raw)) is not None:
        mixer["yaw_reversed"] = yaw_reversed
    shown = {what: [k for k in keys if k in h.raw] for what, keys in _NOT_MODELLED.items()}
    not_modelled = [f"{what}: " + ", ".join(f"{k}={_shown(k, h.raw[k], v)}" for k in keys)
                    for what, keys in shown.items() if keys]
    source = {**h.used, **{k: h.raw[k] for keys in shown.values() for k in keys}}
    craft = str(h.raw.get("Craft name") or "").strip()
    name = re.sub(r"\W+", "_", craft or Path(str(path)).stem).strip("_").lower() or "log"
    gains_text = np.array(pids)[:, :3].astype(int).tolist()
    description = (
        f"The rate PID of {Path(str(path)).name} (Betaflight {_text(v)}, craft {craft or '?'}) on fcemu's "
        f"PID: P/I/D {gains_text} scaled by pid.h's PTERM_SCALE {PTERM_SCALE}, ITERM_SCALE {ITERM_SCALE} "
        f"and DTERM_SCALE {DTERM_SCALE} (our gains are Betaflight's pidCoefficient); {'; '.join(notes)}; "
        f"{tpa_text}; PID sum limit {pidsum.tolist()} and I-term limit {iterm_limit.tolist()} (Betaflight's "
        f"/ 1000), I-term windup {windup_f:g}; I-term relax {relax}, {relax_hz:g} Hz; yaw P lowpass "
        f"{yaw_lpf:g} Hz; mixer idle {idle:.4f} (the idle setting / 10000, or minthrottle), airmode "
        f"{'on' if airmode else 'off (feature bit 22 clear: a switch may still turn it on)'}.")
    pid = {k: [round(x, 9) for x in val] if isinstance(val, list) else round(val, 9) if isinstance(val, float)
           else val for k, val in gains.to_dict().items()}
    return {"name": f"pid_log_{name}", "description": description, "pid": pid, "mixer": mixer,
            "not_modelled": not_modelled, "source": source}


def _shown(key: str, value: Any, version: tuple[int, ...]) -> Any:
    if key in _FLOAT_BITS and version < (3, 2) and isinstance(value, int) and value > 0xFFFF:
        return round(struct.unpack("<f", struct.pack("<I", value & 0xFFFFFFFF))[0], 4)
    return value
