"""The in-training verdict: the deployable bar against the best PID, and the checkpoint ranking."""

from __future__ import annotations

import math

import pytest

from fcemu.evaluation import bar
from fcemu.evaluation.metrics import compute_metrics
from fcemu.evaluation.runner import EvalConfig, run_controller
from fcemu.training import quick_eval


@pytest.fixture(scope="module")
def pids():
    return {spec: compute_metrics(run_controller(spec, EvalConfig(episodes=4, seed=2), progress=False))
            for spec in ("pid", "pid:paper")}


def test_the_verdict_checks_every_criterion_against_the_best_pid(pids):
    best = min(pids, key=lambda k: bar.error_sum(pids[k]))
    other = next(k for k in pids if k != best)
    v = bar.bar_verdict(pids[other], pids)
    assert v["best_pid"] == best and v["error_ratio"] > 1.0 and not v["meets_bar"]
    assert set(v["checks"]) == {"error_ratio", "rise", "peak", "success", "smoothness"}
    ref = pids[best]
    assert v["smoothness_ratio"] == pytest.approx(v["smoothness"] / ref.stat("smoothness", "roll").mean)
    peaks = v["peak_pct_policy_vs_pid"]
    assert v["checks"]["peak"] == all(p <= r + 3.0 for p, r in peaks.values())
    assert v["checks"]["success"] == all(x >= 99.8 for x in v["success_pct"].values())
    line = bar.format_verdict(v)
    for word in ("error", "rise ms", "peak %", "success %", "smoothness", "not met: error_ratio"):
        assert word in line
    # against itself with the bars opened: every criterion holds
    same = bar.bar_verdict(ref, {best: ref}, error_ratio=1.0, min_success=0.0)
    assert same["meets_bar"] and bar.format_verdict(same).endswith("→ MET")


def _verdict(ratio: float, smooth_ratio: float, meets: bool) -> dict:
    return {"error_ratio": ratio, "smoothness_ratio": smooth_ratio, "smoothness_bar": 1.5, "meets_bar": meets}


def test_the_exported_checkpoint_meets_the_bar_first_then_has_the_lowest_penalised_error():
    key = quick_eval.selection_key
    meets_worse_error = _verdict(0.94, 1.4, True)
    fails_better_error = _verdict(0.80, 1.0, False)
    assert key(meets_worse_error) < key(fails_better_error)
    assert key(_verdict(0.90, 1.2, True)) < key(meets_worse_error)  # among those meeting: lowest Error
    smooth = _verdict(0.99, 1.5, False)  # at the smoothness bar: no penalty
    rough = _verdict(0.90, 3.0, False)  # twice the bar: its ratio counts double, 1.8
    assert key(smooth) == (1, 0.99) and key(rough) == (1, pytest.approx(1.8))
    assert key(smooth) < key(rough)
    assert not math.isnan(key(_verdict(0.9, float("nan"), False))[1])
    assert key(rough, "error") < key(smooth, "error")  # --select error: the lowest Error, however rough
    assert key(fails_better_error, "error") < key(meets_worse_error, "error")
    with pytest.raises(ValueError, match="unknown selection"):
        key(smooth, "smoothest")
