"""The paper's metrics (Koch et al. 2018, Evaluation) over traces, as defined in DESIGN.md.

Per episode and axis, with e0 = Ω*(0) − Ω(0) and c(t) = (Ω(t) − Ω(0)) / e0 the fraction
of the initial error corrected:

- Success: mean |Ω* − Ω| over t ≥ 0.5 s is ≤ 10% of |e0|; aggregated as % of episodes.
- Failure: for the episodes that do not succeed, that mean as % of |e0|. With no
  failing episode the aggregate is [0.0, 0.0] (n = 0): nothing unacceptable to measure,
  as the paper prints for its PID.
- Rise: ms from the first crossing of c = 0.1 to the first crossing of c = 0.9, each
  crossing interpolated linearly between samples; NaN (left out, counted) when 0.9 is
  never reached.
- Peak: 100 · max c over the episode; > 100 is overshoot.
- Error: Σ over the episode of |Ω* − Ω| (rad/s, the paper's unit).
- Stability: least-squares slope of Ω against t over t ≥ 0.5 s (rad/s²).
- Smoothness: mean |Δpwm| per 1 ms step, µs, over all four motors. It is not an axis
  quantity: the JSON carries the same value under roll, pitch and yaw, and
  `EvalMetrics.smoothness_per_motor` has the breakdown.

Axes with |e0| < 0.1 rad/s are left out of the e0-normalised metrics (Success, Failure,
Rise, Peak) and counted; Error, Stability and Smoothness use every episode.
Aggregates are mean ± 1.96·σ/√n, σ the sample standard deviation of the n contributing
episodes. In JSON a mean with n = 0, or a CI with n < 2, is null.

Inflight task: the metrics start at the step (t = 0); the warm-up at hover before it
(t < 0) is not scored, and e0 = Ω*(0) − Ω(0) uses the rate at the step.

Continuous task: `segment_traces` cuts each episode wherever the setpoint changes and
every hold becomes an episode of its own (time from the hold's start, e0 at that start).
The final hold of an episode is dropped when shorter than the task's minimum hold
(0.1 s): it was cut by the episode's end. Holds shorter than 0.5 s have no settling
window, so they count as "unassessed" for Success/Failure and are left out of Stability.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np

from fcemu.sitl.traces import Traces

AXES = ("roll", "pitch", "yaw")
METRIC_KEYS = ("success_pct", "failure_pct", "rise_ms", "peak_pct", "error", "stability", "smoothness")
SETTLE_S = 0.5
MIN_E0 = 0.1  # rad/s
SUCCESS_BAND = 0.1  # fraction of |e0|
RISE_LEVELS = (0.1, 0.9)
MIN_HOLD_S = 0.1  # continuous task: shortest command hold
Z95 = 1.96
_T_EPS = 1e-9  # s; t = k·dt in floating point may sit just below 0.5


@dataclass(frozen=True)
class Stat:
    """One aggregate: mean ± ci95 over n contributing episodes (NaN when undefined)."""

    mean: float
    ci95: float
    n: int

    def to_json(self) -> list[float | None]:
        return [_json_float(self.mean), _json_float(self.ci95)]


def _json_float(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def mean_ci95(values: np.ndarray, mask: np.ndarray | None = None,
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Column-wise mean, 1.96·σ/√n (σ with ddof = 1) and n over axis 0; NaN values never count."""
    v = np.asarray(values, dtype=float)
    m = np.isfinite(v) if mask is None else (np.asarray(mask, dtype=bool) & np.isfinite(v))
    n = m.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(m, v, 0.0).sum(axis=0) / n
        dev = np.where(m, v - mean, 0.0)
        var = (dev**2).sum(axis=0) / (n - 1)
        ci = Z95 * np.sqrt(var / n)
    mean = np.where(n > 0, mean, np.nan)
    ci = np.where(n > 1, ci, np.nan)
    return mean, ci, n


@dataclass(frozen=True, eq=False)
class EpisodeMetrics:
    """Per-episode values, shape (N, 3) unless noted; NaN where an episode does not count."""

    e0: np.ndarray
    included: np.ndarray  # bool: |e0| >= MIN_E0
    assessed: np.ndarray  # bool: included and a settling window exists
    success: np.ndarray  # bool
    settle_err_pct: np.ndarray  # mean |Ω* − Ω| over the settling window, % of |e0|
    rise_ms: np.ndarray
    peak_pct: np.ndarray
    error: np.ndarray
    stability: np.ndarray
    smoothness_per_motor: np.ndarray  # (N, 4) µs per step

    @property
    def n_episodes(self) -> int:
        return int(self.e0.shape[0])


@dataclass(frozen=True)
class AxisMetrics:
    """Every metric on one axis, with the counts that say what was left out."""

    success_pct: Stat
    failure_pct: Stat
    rise_ms: Stat
    peak_pct: Stat
    error: Stat
    stability: Stat
    smoothness: Stat
    failure_all_pct: Stat  # the paper's tabulation: over all assessed episodes, successes as 0
    n_episodes: int
    n_excluded: int  # |e0| < MIN_E0
    n_unassessed: int  # included but no settling window (continuous task, short holds)
    n_failures: int
    n_rise_not_reached: int

    def counts(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name.startswith("n_")}


@dataclass(frozen=True)
class EvalMetrics:
    roll: AxisMetrics
    pitch: AxisMetrics
    yaw: AxisMetrics
    smoothness_per_motor: tuple[Stat, Stat, Stat, Stat]
    n_episodes: int  # evaluation units: episodes, or holds for the continuous task
    unit: str = "episode"

    def axis(self, name: str) -> AxisMetrics:
        if name not in AXES:
            raise KeyError(f"unknown axis {name!r}; expected one of {AXES}")
        return getattr(self, name)

    def stat(self, metric: str, axis: str) -> Stat:
        return getattr(self.axis(axis), metric)

    def to_json(self) -> dict[str, dict[str, list[float | None]]]:
        """DESIGN.md's `"metrics"` object: {metric: {axis: [mean, ci95]}}, null for undefined."""
        return {k: {a: self.stat(k, a).to_json() for a in AXES} for k in METRIC_KEYS}

    def details_json(self) -> dict[str, object]:
        """What `to_json` leaves out: counts, per-motor smoothness, the paper's failure averaging."""
        return {
            "unit": self.unit,
            "n": self.n_episodes,
            "counts": {a: self.axis(a).counts() for a in AXES},
            "failure_all_pct": {a: self.axis(a).failure_all_pct.to_json() for a in AXES},
            "smoothness_per_motor": [s.to_json() for s in self.smoothness_per_motor],
        }


def _first_crossing(c: np.ndarray, level: float, tr: np.ndarray) -> np.ndarray:
    """Time where c (N,3,T) first reaches `level`, interpolated between samples; NaN if never."""
    above = c >= level
    reached = above.any(axis=-1)
    k = above.argmax(axis=-1)
    km1 = np.maximum(k - 1, 0)
    c_k = np.take_along_axis(c, k[..., None], axis=-1)[..., 0]
    c_km1 = np.take_along_axis(c, km1[..., None], axis=-1)[..., 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where((k > 0) & (c_k > c_km1), (level - c_km1) / (c_k - c_km1), 1.0)
    t_cross = tr[km1] + frac * (tr[k] - tr[km1])
    return np.where(reached, t_cross, np.nan)


def _time_last(x: np.ndarray) -> np.ndarray:
    """(N,T,k) -> contiguous (N,k,T): reductions over time then run over contiguous memory."""
    return np.ascontiguousarray(np.moveaxis(np.asarray(x, dtype=float), 1, 2))


def episode_metrics(
    t: np.ndarray,
    setpoint: np.ndarray,
    rate: np.ndarray,
    pwm: np.ndarray,
    lengths: np.ndarray | None = None,
    *,
    settle_s: float = SETTLE_S,
    min_e0: float = MIN_E0,
) -> EpisodeMetrics:
    """Per-episode metrics. t (T,) s; setpoint, rate (N,T,3); pwm (N,T,4).

    `lengths` (N,) makes episode i use only its first lengths[i] steps (padded segments);
    padding must be finite.
    """
    sp, om, u = _time_last(setpoint), _time_last(rate), _time_last(pwm)
    tr = np.asarray(t, dtype=float) - float(t[0])
    n_ep, _, n_t = sp.shape
    steps = np.arange(n_t)
    n_valid = np.full(n_ep, n_t) if lengths is None else np.asarray(lengths, dtype=int)
    valid = (steps[None, :] < n_valid[:, None])[:, None, :]  # (N,1,T)
    window = valid & (tr >= settle_s - _T_EPS)[None, None, :]
    n_win = window.sum(axis=-1)  # (N,1)

    err = np.abs(sp - om)
    if lengths is not None:
        err *= valid
    error = err.sum(axis=-1)

    om0 = om[..., 0]
    e0 = sp[..., 0] - om0
    abs_e0 = np.abs(e0)
    included = abs_e0 >= min_e0

    with np.errstate(invalid="ignore", divide="ignore"):
        mean_err = (err * window).sum(axis=-1) / n_win
        settle_err_pct = np.where(included & (n_win > 0), 100.0 * mean_err / abs_e0, np.nan)
    assessed = included & (n_win > 0)
    success = assessed & (mean_err <= SUCCESS_BAND * abs_e0)

    e0_safe = np.where(included, e0, 1.0)
    c = (om - om0[..., None]) / e0_safe[..., None]
    if lengths is not None:
        c[~np.broadcast_to(valid, c.shape)] = -np.inf
    peak_pct = np.where(included, 100.0 * c.max(axis=-1), np.nan)
    t_lo = _first_crossing(c, RISE_LEVELS[0], tr)
    t_hi = _first_crossing(c, RISE_LEVELS[1], tr)
    rise_ms = np.where(included, 1000.0 * (t_hi - t_lo), np.nan)

    # Least-squares slope over the window; x is centred per episode, so sxy needs no y mean.
    with np.errstate(invalid="ignore", divide="ignore"):
        x_mean = (window * tr).sum(axis=-1) / n_win
        dx = np.where(window, tr - x_mean[..., None], 0.0)  # (N,1,T)
        sxy = (dx * om).sum(axis=-1)
        sxx = (dx**2).sum(axis=-1)
        stability = np.where(n_win >= 2, sxy / sxx, np.nan)

    du = np.abs(np.diff(u, axis=-1))
    dvalid = valid[..., 1:]
    if lengths is not None:
        du *= dvalid
    with np.errstate(invalid="ignore", divide="ignore"):
        smooth = du.sum(axis=-1) / dvalid.sum(axis=-1)

    return EpisodeMetrics(e0=e0, included=included, assessed=assessed, success=success,
                          settle_err_pct=settle_err_pct, rise_ms=rise_ms, peak_pct=peak_pct, error=error,
                          stability=stability, smoothness_per_motor=smooth)


def _stats(values: np.ndarray, mask: np.ndarray | None = None) -> list[Stat]:
    mean, ci, n = mean_ci95(values, mask)
    return [Stat(float(a), float(b), int(k)) for a, b, k in zip(mean, ci, n, strict=True)]


def aggregate(ep: EpisodeMetrics, unit: str = "episode") -> EvalMetrics:
    """Mean and 95% CI per axis over the episodes that count for each metric."""
    failed = ep.assessed & ~ep.success
    success = _stats(np.where(ep.success, 100.0, 0.0), ep.assessed)
    n_assessed = ep.assessed.sum(axis=0)
    failure = [s if s.n > 0 or n_assessed[i] == 0 else Stat(0.0, 0.0, 0)
               for i, s in enumerate(_stats(ep.settle_err_pct, failed))]
    failure_all = _stats(np.where(ep.success, 0.0, ep.settle_err_pct), ep.assessed)
    rise = _stats(ep.rise_ms, ep.included)
    peak = _stats(ep.peak_pct, ep.included)
    error = _stats(ep.error)
    stability = _stats(ep.stability)
    per_motor = _stats(ep.smoothness_per_motor)
    smooth = _stats(ep.smoothness_per_motor.mean(axis=1)[:, None])[0]
    not_reached = ep.included & ~np.isfinite(ep.rise_ms)
    axes = [
        AxisMetrics(success_pct=success[i], failure_pct=failure[i], rise_ms=rise[i], peak_pct=peak[i],
                    error=error[i], stability=stability[i], smoothness=smooth,
                    failure_all_pct=failure_all[i], n_episodes=ep.n_episodes,
                    n_excluded=int((~ep.included[:, i]).sum()),
                    n_unassessed=int((ep.included[:, i] & ~ep.assessed[:, i]).sum()),
                    n_failures=int(failed[:, i].sum()), n_rise_not_reached=int(not_reached[:, i].sum()))
        for i in range(3)
    ]
    return EvalMetrics(*axes, smoothness_per_motor=tuple(per_motor), n_episodes=ep.n_episodes, unit=unit)


@dataclass(frozen=True, eq=False)
class Segments:
    """Continuous-task holds, padded to a common length (padding repeats the last sample)."""

    t: np.ndarray  # (L,) s from each hold's start
    setpoint: np.ndarray  # (S, L, 3)
    rate: np.ndarray  # (S, L, 3)
    pwm: np.ndarray  # (S, L, 4)
    lengths: np.ndarray  # (S,) valid steps
    episode: np.ndarray  # (S,) source episode
    start: np.ndarray  # (S,) start index in the source episode


def segment_traces(
    t: np.ndarray, setpoint: np.ndarray, rate: np.ndarray, pwm: np.ndarray, *, min_hold_s: float = MIN_HOLD_S
) -> Segments:
    """Cut each episode where any axis of the setpoint changes; each hold becomes a segment."""
    sp = np.asarray(setpoint)
    n_ep, n_t = sp.shape[:2]
    dt = float(np.median(np.diff(t)))
    ep_chg, k_chg = np.nonzero(np.any(sp[:, 1:] != sp[:, :-1], axis=2))
    ep = np.concatenate([np.arange(n_ep), ep_chg])
    start = np.concatenate([np.zeros(n_ep, dtype=int), k_chg + 1])
    order = np.lexsort((start, ep))
    ep, start = ep[order], start[order]
    last = np.append(ep[1:] != ep[:-1], True)
    end = np.where(last, n_t, np.append(start[1:], n_t))
    length = end - start
    keep = ~(last & (length < round(min_hold_s / dt)))
    ep, start, end, length = ep[keep], start[keep], end[keep], length[keep]
    if ep.size == 0:
        raise ValueError("segment_traces: no hold is long enough to evaluate")
    n_l = int(length.max())
    idx = np.minimum(start[:, None] + np.arange(n_l)[None, :], end[:, None] - 1)
    rows = ep[:, None]
    return Segments(t=np.arange(n_l) * dt, setpoint=sp[rows, idx], rate=np.asarray(rate)[rows, idx],
                    pwm=np.asarray(pwm)[rows, idx], lengths=length, episode=ep, start=start)


def traces_episode_metrics(traces: Traces, *, settle_s: float = SETTLE_S, min_e0: float = MIN_E0,
                           min_hold_s: float = MIN_HOLD_S) -> tuple[EpisodeMetrics, str]:
    """Per-unit metrics and the unit: holds for the continuous task; inflight from its step on."""
    if traces.task == "continuous":
        seg = segment_traces(traces.t, traces.setpoint, traces.rate, traces.pwm, min_hold_s=min_hold_s)
        ep = episode_metrics(seg.t, seg.setpoint, seg.rate, seg.pwm, seg.lengths,
                             settle_s=settle_s, min_e0=min_e0)
        return ep, "hold"
    tr = traces.step_window()
    return episode_metrics(tr.t, tr.setpoint, tr.rate, tr.pwm, settle_s=settle_s, min_e0=min_e0), "episode"


def pool_episode_metrics(parts: Sequence[EpisodeMetrics]) -> EpisodeMetrics:
    """Several evaluations' units as one set (e.g. the same commands on several airframes)."""
    if not parts:
        raise ValueError("pool_episode_metrics: nothing to pool")
    return EpisodeMetrics(**{f.name: np.concatenate([getattr(p, f.name) for p in parts])
                             for f in fields(EpisodeMetrics)})


def compute_metrics(traces: Traces, *, settle_s: float = SETTLE_S, min_e0: float = MIN_E0,
                    min_hold_s: float = MIN_HOLD_S) -> EvalMetrics:
    """The paper's metrics for a traces object; the continuous task is evaluated per hold."""
    ep, unit = traces_episode_metrics(traces, settle_s=settle_s, min_e0=min_e0, min_hold_s=min_hold_s)
    return aggregate(ep, unit=unit)
