"""The step response of a rate loop from a flight log, by PID-Analyzer's method.

PID-Analyzer (Plasmatree/PID-Analyzer, `PID-Analyzer.py`, class `Trace`) needs no step in the
log: it cuts the log into overlapping windows (`winstacker`), tapers each with a Hanning window,
and deconvolves the gyro against the setpoint with a Wiener filter in the frequency domain
(`wiener_deconvolution`), H = G·conj(S) / (|S|² + 1/SNR(f)). The inverse transform is the loop's
impulse response over that window and its running sum (`stack_response`) the step response.
Windows with too little setpoint in them say nothing and are left out (`low_high_mask`); the
rest are averaged (`weighted_mode_avr`).

Taken from PID-Analyzer 0.52 (line numbers of its `PID-Analyzer.py`):

- `FRAME_S` = 1 s windows (`Trace.framelen`, l. 32), `RESPONSE_S` = 0.5 s of response
  (`resplen`, l. 33), `OVERLAP` = 16 windows over each window's length (`superpos`, l. 36;
  the window moves by a 16th of its length, l. 201), the Hanning taper (`np.hanning`, l. 64),
  each window zero-padded to the next multiple of `PAD_TO` = 1024 samples (l. 213);
- the signal-to-noise ratio (l. 218-222): SNR = 10 below `CUT_HZ` = 25 Hz (`cutfreq`, l. 34)
  and 1e-8 above, the step between the two smoothed by a Gaussian whose σ is a sixth of the
  bins under the cut (σ ≈ CUT_HZ/3 ≈ 8 Hz; scipy truncates it at 4σ, so 1/SNR leaps at ~58 Hz).
  The deconvolution trusts the setpoint up to ~25 Hz and nothing from ~58 Hz up;
- the input thresholds, on the largest |setpoint| in the tapered window, deg/s:
  `MIN_INPUT_DEG_S` = 20 (windows at or under it are noise, l. 67) and `HIGH_INPUT_DEG_S` = 500
  (`Trace.threshold`, l. 37; the "low input" / "high input" curves of its plots, l. 75-77; no
  high-input curve unless `MIN_HIGH_WINDOWS` = 10 windows have one, l. 103);
- the weighted mode (l. 307-339), `average="mode"`, the default: per time, a histogram of the
  windows' responses over `MODE_RANGE` -1.5 … 3.5 in 1000 bins, smoothed by a Gaussian of σ 7
  bins, each column scaled to a peak of 1, and the mean of the bins weighted by that squared.

Where this module differs, and why:

- Units. PID-Analyzer's thresholds and its 1/SNR term are absolute: they assume deg/s. fcemu's
  rates are rad/s, so the arrays are scaled by `deg_per_unit` (180/π by default; 1.0 for a
  deg/s log) first. (1/SNR is left as it is at every log rate, though |S|² grows as the square
  of the samples per window: the leap at ~58 Hz is so steep that scaling 1/SNR to the log
  rate moves no result here by more than ~0.1 %.)
- The running sum starts `LEAD_S` = 0.1 s before the step, not at it. The Wiener filter's
  |S|²/(|S|² + 1/SNR) is real, so its smearing of the impulse response is symmetric in time:
  summing from t = 0 (PID-Analyzer's `cumsum` of `[:rlen]`) drops the half of it that lands
  before the step, which makes a loop that answers at once look like it settles at 0.5-0.7 and
  biases the final value of any loop faster than ~20 ms by a few %. Summing from -0.1 s gives
  the true response smoothed by a symmetric kernel: final ≈ 1, the half-way time unbiased.
- Every full window is used (PID-Analyzer drops the last `superpos` shifts of the log).
- `inputs="all"` (the default) averages every window over `MIN_INPUT_DEG_S`, as PID-Analyzer's
  `resp_sm` (l. 69) does; "low" and "high" are its two plotted curves.
- `average="median"` (per time) and `average="mean"` are offered besides the mode. The mean is
  not robust: on a log of clean steps a few windows, whose setpoint spectrum has near-zeros
  that 1/SNR = 0.1 does not cover, swing it by ±10 (the mode and the median do not move).

What the method can resolve: the band limit turns a jump (a pure delay) into a ~8 ms ramp
(10-90 %) centred on it with ~10 % ringing (peak ~1.10), so the 90 % rise of a loop that
jumps is its delay + ~3.7 ms; loops slower than that come out as they are, to within the
windows' leakage, which reads slow loops a little fast: a first-order lag's 90 % rise comes out
~2 % early at τ = 10 ms and ~10 % early at τ = 20 ms (final ~0.99) with PID-Analyzer's 1 s
windows, ~4 % early at τ = 20 ms with `frame_s` = 2 s.

Times: a step is taken to happen at t = 0, half a sample before the first sample after it
(midway between the last sample before the step and the first after), so `t_s[k]` = (k + ½)·dt
and a loop that only delays by d samples crosses half its final value at d·dt at any log rate.
Rise and delay times are interpolated linearly between samples.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.ndimage import gaussian_filter1d

FRAME_S = 1.0  # window length, s (PID-Analyzer Trace.framelen)
RESPONSE_S = 0.5  # step response kept, s (Trace.resplen)
OVERLAP = 16  # windows that overlap each point (Trace.superpos): the window moves by FRAME_S/16
CUT_HZ = 25.0  # the setpoint counts as input below this (Trace.cutfreq)
SNR = 10.0  # signal-to-noise ratio below CUT_HZ (wiener_deconvolution: sn = 10·(…))
PAD_TO = 1024  # each window is zero-padded to the next multiple of this many samples
MIN_INPUT_DEG_S = 20.0  # a window whose tapered |setpoint| never exceeds this is left out
HIGH_INPUT_DEG_S = 500.0  # Trace.threshold: "high input" windows exceed it
MIN_HIGH_WINDOWS = 10  # fewer high-input windows than this: no high-input response (low_high_mask)
LEAD_S = 0.1  # the running sum of the impulse response starts this long before the step, s
FINAL_S = (0.2, 0.5)  # the response's final value: its mean over this span after the step, s
RISE_FRACTION = 0.9  # rise time: the first time the response reaches this fraction of its final value
MODE_RANGE = (-1.5, 3.5)  # average="mode": the histogram's range (weighted_mode_avr's vertrange)
MODE_BINS = 1000  # … its bins
MODE_SIGMA_BINS = 7.0  # … the Gaussian smoothing along the response axis, in bins (filt_width)


@dataclass(frozen=True)
class StepResponse:
    """The average step response of the windows with input enough; 1.0 is the setpoint."""

    t_s: np.ndarray  # (K,) time after the step, s: (k + ½)·dt, up to RESPONSE_S
    response: np.ndarray  # (K,) the step response
    windows: int  # windows that had input enough and were averaged
    peak: float  # the response's largest value
    final: float  # its mean over FINAL_S (0.2 … 0.5 s)
    rise_ms: float  # the first time it reaches RISE_FRACTION (90 %) of `final`, ms; nan if never
    delay_ms: float  # the first time it reaches half of `final`, ms; nan if never


def _snr(nfft: int, dt: float) -> np.ndarray:
    """PID-Analyzer's SNR on the rfft bins of an `nfft`-sample window (wiener_deconvolution)."""
    freq = np.abs(np.fft.fftfreq(nfft, dt))
    step = (freq >= CUT_HZ).astype(np.float64)  # 0 under the cut, 1 from it up
    under = float(np.sum(1.0 - step))  # bins under the cut, both signs of frequency
    smooth = gaussian_filter1d(step, under / 6.0)
    smooth = (smooth - smooth.min()) / (smooth.max() - smooth.min())
    return (SNR * (1.0 - smooth + 1e-9))[: nfft // 2 + 1]


def _crossing(t_s: np.ndarray, response: np.ndarray, level: float) -> float:
    """The first time `response` reaches `level`, interpolated between samples; nan if never."""
    above = np.flatnonzero(response >= level)
    if len(above) == 0:
        return float("nan")
    k = int(above[0])
    if k == 0:
        return float(t_s[0])
    r0, r1 = response[k - 1], response[k]
    return float(t_s[k - 1] + (level - r0) / (r1 - r0) * (t_s[k] - t_s[k - 1]))


def _mode_average(values: np.ndarray) -> np.ndarray:
    """PID-Analyzer's weighted mode (weighted_mode_avr) of `values` (W, K) at each of the K times."""
    lo, hi = MODE_RANGE
    n_times = values.shape[1]
    index = np.floor((values - lo) / (hi - lo) * MODE_BINS)
    inside = (index >= 0) & (index < MODE_BINS)
    column = np.broadcast_to(np.arange(n_times), values.shape)
    flat = column[inside] * MODE_BINS + index[inside].astype(np.int64)
    hist = np.bincount(flat, minlength=n_times * MODE_BINS).reshape(n_times, MODE_BINS).astype(np.float64)
    hist = gaussian_filter1d(hist, MODE_SIGMA_BINS, axis=1, mode="constant")
    top = hist.max(axis=1, keepdims=True)
    weights = np.divide(hist, top, out=np.zeros_like(hist), where=top > 0) ** 2
    centres = lo + (np.arange(MODE_BINS) + 0.5) * (hi - lo) / MODE_BINS
    total = weights.sum(axis=1)
    return np.divide(weights @ centres, total, out=np.full(n_times, np.nan), where=total > 0)


def step_responses(setpoint: np.ndarray, gyro: np.ndarray, dt: float, *,
                   deg_per_unit: float = 180.0 / np.pi,
                   frame_s: float = FRAME_S) -> tuple[np.ndarray, np.ndarray]:
    """Every window's step response (W, L + K) and the largest tapered |setpoint| in each (W,), deg/s.

    The first L = round(LEAD_S/dt) samples of each response are before the step, the K =
    round(RESPONSE_S/dt) after it. `setpoint` and `gyro` are one axis (N,), in the same units
    (`deg_per_unit` deg/s each: rad/s by default), every `dt` s. W = 0 on a log shorter than a window.
    """
    setpoint = np.asarray(setpoint, dtype=np.float64)
    gyro = np.asarray(gyro, dtype=np.float64)
    if setpoint.ndim != 1 or setpoint.shape != gyro.shape:
        raise ValueError(f"setpoint {setpoint.shape} and gyro {gyro.shape} must be one axis, the same length")
    if not (np.isfinite(dt) and dt > 0.0):
        raise ValueError(f"dt must be a positive number of seconds, not {dt}")
    if not (np.isfinite(deg_per_unit) and deg_per_unit > 0.0):
        raise ValueError(f"deg_per_unit must be positive, not {deg_per_unit}")
    if not (np.isfinite(setpoint).all() and np.isfinite(gyro).all()):
        raise ValueError("setpoint and gyro must be finite (no NaN or inf)")
    if not frame_s >= 2.0 * RESPONSE_S:
        raise ValueError(f"frame_s {frame_s} s must be at least twice the response's {RESPONSE_S} s")
    frame = round(frame_s / dt)
    length = round(RESPONSE_S / dt)
    lead = round(LEAD_S / dt)
    if length < 10:
        raise ValueError(f"dt {dt} s is too coarse: {RESPONSE_S} s of response would be {length} samples")
    if len(setpoint) < frame:
        return np.zeros((0, lead + length)), np.zeros(0)
    shift = frame // OVERLAP
    taper = np.hanning(frame)
    inp = np.lib.stride_tricks.sliding_window_view(setpoint * deg_per_unit, frame)[::shift] * taper
    out = np.lib.stride_tricks.sliding_window_view(gyro * deg_per_unit, frame)[::shift] * taper
    nfft = frame + PAD_TO - frame % PAD_TO
    s = np.fft.rfft(inp, n=nfft, axis=-1)
    g = np.fft.rfft(out, n=nfft, axis=-1)
    noise = 1.0 / _snr(nfft, dt)
    impulse = np.fft.irfft(g * np.conj(s) / (s.real**2 + s.imag**2 + noise), n=nfft, axis=-1)
    impulse = np.concatenate([impulse[:, nfft - lead:], impulse[:, :length]], axis=1)  # -LEAD_S … RESPONSE_S
    return np.cumsum(impulse, axis=1), np.abs(inp).max(axis=1)


def step_response(setpoint: np.ndarray, gyro: np.ndarray, dt: float, *,
                  deg_per_unit: float = 180.0 / np.pi,
                  inputs: Literal["all", "low", "high"] = "all",
                  average: Literal["mode", "median", "mean"] = "mode",
                  min_input_deg_s: float = MIN_INPUT_DEG_S,
                  high_input_deg_s: float = HIGH_INPUT_DEG_S,
                  frame_s: float = FRAME_S) -> StepResponse | None:
    """The step response from `gyro` against `setpoint` (one axis (N,) each, same units, every `dt` s).

    `deg_per_unit`: deg/s per unit of the arrays (180/π: rad/s, fcemu's; 1.0: deg/s, a blackbox
    log's). `inputs`: which windows are averaged, by the largest |setpoint| in the tapered window:
    "all" over `min_input_deg_s`, "low" those up to `high_input_deg_s`, "high" those over it
    (none unless there are at least MIN_HIGH_WINDOWS). `average`: PID-Analyzer's histogram
    "mode", the per-time "median", or the "mean" (not robust; see the module's docstring).
    `frame_s`: the window length (PID-Analyzer's 1 s; a longer one leaks less on slow loops).

    Returns None where the log says too little: shorter than one window (`frame_s`) or no window
    with input enough. Raises ValueError on arguments that are wrong (shapes, dt, NaN).
    """
    if inputs not in ("all", "low", "high"):
        raise ValueError(f"inputs must be 'all', 'low' or 'high', not {inputs!r}")
    if average not in ("mode", "median", "mean"):
        raise ValueError(f"average must be 'mode', 'median' or 'mean', not {average!r}")
    responses, max_input = step_responses(setpoint, gyro, dt, deg_per_unit=deg_per_unit, frame_s=frame_s)
    keep = max_input > min_input_deg_s
    high = max_input > high_input_deg_s
    if inputs == "low":
        keep &= ~high
    elif inputs == "high":
        keep &= high
        if keep.sum() < MIN_HIGH_WINDOWS:
            return None
    if not keep.any():
        return None
    kept = responses[keep]
    if average == "mode":
        full = _mode_average(kept)
    elif average == "median":
        full = np.median(kept, axis=0)
    else:
        full = kept.mean(axis=0)
    lead = round(LEAD_S / dt)
    t_full = (np.arange(full.shape[0]) - lead + 0.5) * dt
    t_s, response = t_full[lead:], full[lead:]
    final = float(response[(t_s >= FINAL_S[0]) & (t_s <= FINAL_S[1])].mean())
    if final > 0.0:  # crossings from the last sample before the step (the step is midway), never before it
        rise = max(_crossing(t_full[lead - 1:], full[lead - 1:], RISE_FRACTION * final), 0.0) * 1000.0
        delay = max(_crossing(t_full[lead - 1:], full[lead - 1:], 0.5 * final), 0.0) * 1000.0
    else:
        rise = delay = float("nan")
    return StepResponse(t_s=t_s, response=response, windows=int(keep.sum()), peak=float(np.max(response)),
                        final=final, rise_ms=rise, delay_ms=delay)
