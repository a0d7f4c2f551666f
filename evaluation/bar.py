"""The deployable bar: what a rate controller must show, against the tuned PID, to deserve to fly.

Defined once here and used by `fcemu train --select bar`, `fcemu bench train --target bar`,
`fcemu sweep`'s verdicts and the tests. Against the best PID preset on the same commands
(`fcemu eval --episodes 1000 --seed 7`, tasks `episodic` and `inflight`):

- Error sum ≤ 0.95 × the PID's;
- Rise ≤ the PID's on every axis; Peak ≤ the PID's + 3 points on every axis;
- Success ≥ 99.8 % on every axis;
- smoothness (mean |Δpwm| per step) ≤ 1.5 × the PID's.

On perturbed airframes (`--perturb 20`), from rest and in flight: Error ≤ the PID's and Success
≥ 99 % on every axis.
And it fits a flight controller: inference ≤ 25 % of the 1 kHz period on an STM32F405 at
168 MHz (`fcemu bench mcu`) and a host median ≤ 10 µs (`fcemu bench inference`).
"""

from __future__ import annotations

from fcemu.evaluation.metrics import AXES, EvalMetrics

ERROR_RATIO_BAR = 0.95  # Error sum ≤ this × the PID's
PEAK_MARGIN_PCT = 3.0  # Peak ≤ the PID's + this, every axis
SUCCESS_BAR_PCT = 99.8  # Success ≥ this, every axis
SMOOTHNESS_BAR = 1.5  # smoothness (mean |Δpwm| per step) ≤ this × the PID's
PERTURBED_SUCCESS_BAR_PCT = 99.0  # on perturbed airframes: Success ≥ this, every axis (Error ≤ the PID's)
MCU_BUDGET_PCT = 25.0  # inference ≤ this % of the 1 kHz period on an STM32F405 at 168 MHz
HOST_MEDIAN_US = 10.0  # inference median on the host, onnxruntime
TIMES_BOUND_BAR = 1.2  # per airframe: Error sum ≤ this × `fcemu bound`'s on the same commands


def bar_verdict(policy: EvalMetrics, pids: dict[str, EvalMetrics], error_ratio: float = ERROR_RATIO_BAR,
                min_success: float = SUCCESS_BAR_PCT, peak_margin: float = PEAK_MARGIN_PCT,
                smoothness_ratio: float = SMOOTHNESS_BAR) -> dict:
    """The bar against the best PID preset (lowest Error sum); every criterion, its figures and its check.

    Error sum ≤ `error_ratio` × the PID's; Rise ≤ the PID's, Peak ≤ the PID's + `peak_margin`
    points and Success ≥ `min_success` % on every axis; smoothness ≤ `smoothness_ratio` × the
    PID's. A figure that is missing (NaN: e.g. no episode rose) fails its check.
    """
    best = min(pids, key=lambda k: error_sum(pids[k]))
    ref = pids[best]
    pol_sum, ref_sum = error_sum(policy), error_sum(ref)
    rise = {a: [policy.stat("rise_ms", a).mean, ref.stat("rise_ms", a).mean] for a in AXES}
    peak = {a: [policy.stat("peak_pct", a).mean, ref.stat("peak_pct", a).mean] for a in AXES}
    success = {a: policy.stat("success_pct", a).mean for a in AXES}
    # smoothness is one figure over the motors, the same on every axis
    smooth, smooth_pid = policy.stat("smoothness", "roll").mean, ref.stat("smoothness", "roll").mean
    checks = {
        "error_ratio": pol_sum / ref_sum <= error_ratio,
        "rise": all(p <= r for p, r in rise.values()),
        "peak": all(p <= r + peak_margin for p, r in peak.values()),
        "success": all(success[a] >= min_success for a in AXES),
        "smoothness": smooth <= smoothness_ratio * smooth_pid,
    }
    return {"best_pid": best, "policy_error_sum": pol_sum, "pid_error_sum": ref_sum,
            "error_ratio": pol_sum / ref_sum, "error_ratio_bar": error_ratio,
            "success_pct": success, "success_bar": min_success,
            "rise_ms_policy_vs_pid": rise, "peak_pct_policy_vs_pid": peak, "peak_margin": peak_margin,
            "smoothness": smooth, "pid_smoothness": smooth_pid, "smoothness_ratio": smooth / smooth_pid,
            "smoothness_bar": smoothness_ratio,
            "checks": checks, "meets_bar": all(checks.values())}


def error_sum(metrics: EvalMetrics) -> float:
    """The bar's figure: mean Error per episode, summed over roll, pitch and yaw."""
    return float(sum(metrics.stat("error", a).mean for a in AXES))


def meets_perturbed(error: float, success_pct: list[float], pid_error: float) -> bool:
    """The perturbed lines: Error ≤ the PID's on the same airframes, Success ≥ the bar on every axis."""
    return bool(error <= pid_error and min(success_pct) >= PERTURBED_SUCCESS_BAR_PCT)


def format_verdict(verdict: dict) -> str:
    """The verdict on one line: each criterion's figures (roll/pitch/yaw) vs the PID's, and which fail."""
    def pair(key: str, fmt: str) -> str:
        pol, ref = zip(*verdict[key].values(), strict=True)
        return f"{'/'.join(f'{x:{fmt}}' for x in pol)} vs {'/'.join(f'{x:{fmt}}' for x in ref)}"

    v = verdict
    failed = [k for k, ok in v["checks"].items() if not ok]
    success = "/".join(f"{x:.1f}" for x in v["success_pct"].values())
    return (f"error {v['policy_error_sum']:.1f} vs {v['best_pid']} {v['pid_error_sum']:.1f} "
            f"(×{v['error_ratio']:.3f} ≤ {v['error_ratio_bar']}), "
            f"rise ms {pair('rise_ms_policy_vs_pid', '.0f')}, "
            f"peak % {pair('peak_pct_policy_vs_pid', '.1f')} (+{v['peak_margin']:g}), "
            f"success % {success} (≥ {v['success_bar']}), "
            f"smoothness {v['smoothness']:.2f} vs {v['pid_smoothness']:.2f} "
            f"(×{v['smoothness_ratio']:.2f} ≤ {v['smoothness_bar']}) "
            f"→ {'MET' if v['meets_bar'] else 'not met: ' + ', '.join(failed)}")


def airframe_bar_verdict(policy: EvalMetrics, pid: EvalMetrics, bound_sum: float | None,
                         mcu_us: float | None = None) -> dict:
    """The bar for an airframe of one's own, against its tuned PID on the same commands (`fcemu fit`):
    Error ≤ 0.95 × the PID's and ≤ 1.2 × the bound; Success ≥ 99.8 % on every axis, or the PID's
    own where it is lower (an axis physics keeps from settling: `fcemu tune`'s settle limits);
    Peak ≤ the PID's + 3 points; motors ≤ 1.5 × as rough; Rise no slower than the PID's beyond
    the 95 % interval of the difference (yaw Rise is saturation-limited, so both tie there); and,
    when measured, inference ≤ 25 % of the period on an F405. A line that cannot be judged (no
    bound, no MCU figure) is None and does not fail the verdict; it is reported as such."""
    pol_sum, pid_sum = error_sum(policy), error_sum(pid)
    success = {a: [policy.stat("success_pct", a).mean, pid.stat("success_pct", a).mean] for a in AXES}
    peak = {a: [policy.stat("peak_pct", a).mean, pid.stat("peak_pct", a).mean] for a in AXES}
    rise = {}
    for a in AXES:
        p, r = policy.stat("rise_ms", a), pid.stat("rise_ms", a)
        rise[a] = [p.mean, r.mean, float((p.ci95**2 + r.ci95**2) ** 0.5)]
    smooth, smooth_pid = policy.stat("smoothness", "roll").mean, pid.stat("smoothness", "roll").mean
    times_bound = pol_sum / bound_sum if bound_sum else None
    checks: dict[str, bool | None] = {
        "error_ratio": pol_sum / pid_sum <= ERROR_RATIO_BAR,
        "times_bound": None if times_bound is None else times_bound <= TIMES_BOUND_BAR,
        "success": all(p >= min(SUCCESS_BAR_PCT, r) for p, r in success.values()),
        "peak": all(p <= r + PEAK_MARGIN_PCT for p, r in peak.values()),
        "smoothness": smooth <= SMOOTHNESS_BAR * smooth_pid,
        "rise": all(p <= r + ci for p, r, ci in rise.values()),
        "mcu": None if mcu_us is None else mcu_us <= MCU_BUDGET_PCT / 100.0 * 1000.0,  # of 1000 µs
    }
    return {"policy_error_sum": pol_sum, "pid_error_sum": pid_sum, "error_ratio": pol_sum / pid_sum,
            "error_ratio_bar": ERROR_RATIO_BAR, "bound_sum": bound_sum, "times_bound": times_bound,
            "times_bound_bar": TIMES_BOUND_BAR, "success_pct_policy_vs_pid": success,
            "peak_pct_policy_vs_pid": peak, "rise_ms_policy_pid_ci95": rise, "smoothness": smooth,
            "pid_smoothness": smooth_pid, "smoothness_ratio": smooth / smooth_pid, "mcu_us": mcu_us,
            "checks": checks, "meets_bar": all(v is not False for v in checks.values()),
            "unjudged": [k for k, v in checks.items() if v is None]}
