"""The paper's metrics on synthetic responses whose answers are known by hand."""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest

from fcemu.evaluation.metrics import (
    AXES,
    METRIC_KEYS,
    aggregate,
    compute_metrics,
    episode_metrics,
    mean_ci95,
    segment_traces,
)
from fcemu.sitl.traces import Traces

DT = 0.001
T = 1000
t = np.arange(T) * DT


def _const_setpoint(values: np.ndarray) -> np.ndarray:
    """(N,3) setpoints -> (N,T,3) held for the whole episode."""
    return np.repeat(np.asarray(values, dtype=float)[:, None, :], T, axis=1)


def _flat_pwm(n: int) -> np.ndarray:
    return np.full((n, T, 4), 1500.0)


def _first_order(target: np.ndarray, tau: float) -> np.ndarray:
    return np.asarray(target)[:, None, :] * (1.0 - np.exp(-t[None, :, None] / tau))


def _metrics(sp: np.ndarray, rate: np.ndarray, pwm: np.ndarray | None = None):
    pwm = _flat_pwm(sp.shape[0]) if pwm is None else pwm
    ep = episode_metrics(t, sp, rate, pwm)
    return ep, aggregate(ep)


def test_first_order_rise_time_is_tau_ln9() -> None:
    tau = 0.05
    targets = np.array([[2.0, -3.0, 4.5], [-1.0, 0.5, -5.2]])
    ep, m = _metrics(_const_setpoint(targets), _first_order(targets, tau))
    expected_ms = tau * math.log(9) * 1000  # 109.86 ms
    np.testing.assert_allclose(ep.rise_ms, expected_ms, atol=1.0)
    np.testing.assert_allclose(ep.rise_ms, expected_ms, atol=0.05)  # interpolation beats the 1 ms grid
    assert m.roll.rise_ms.mean == pytest.approx(expected_ms, abs=0.05)
    assert m.roll.rise_ms.n == 2
    # No overshoot: peak just under 100%, and every episode succeeds.
    assert np.all(ep.peak_pct <= 100.0) and np.all(ep.peak_pct > 99.99)
    assert m.yaw.success_pct.mean == 100.0


def test_rise_time_scales_with_tau() -> None:
    targets = np.array([[3.0, 3.0, 3.0]])
    fast, _ = _metrics(_const_setpoint(targets), _first_order(targets, 0.02))
    slow, _ = _metrics(_const_setpoint(targets), _first_order(targets, 0.08))
    np.testing.assert_allclose(slow.rise_ms / fast.rise_ms, 4.0, rtol=1e-3)


def test_ramp_stability_slope_is_a() -> None:
    slopes = np.array([[0.7, -2.0, 0.0], [3.0, 0.01, -0.25]])
    targets = np.array([[1.0, 1.0, 1.0], [2.0, -2.0, 2.0]])
    rate = slopes[:, None, :] * t[None, :, None]
    ep, m = _metrics(_const_setpoint(targets), rate)
    np.testing.assert_allclose(ep.stability, slopes, atol=1e-9)
    assert m.roll.stability.mean == pytest.approx(1.85)


def test_stability_ignores_the_first_half() -> None:
    # Wild transient before 0.5 s, flat afterwards: slope 0.
    target = np.array([[2.0, 2.0, 2.0]])
    rate = np.repeat(target[:, None, :], T, axis=1).copy()
    rate[:, :500, :] = np.sin(t[:500] * 50)[None, :, None] * 10
    ep, _ = _metrics(_const_setpoint(target), rate)
    np.testing.assert_allclose(ep.stability, 0.0, atol=1e-12)


@pytest.mark.parametrize("zeta", [0.2, 0.4, 0.6])
def test_second_order_peak_overshoot(zeta: float) -> None:
    wn = 40.0
    wd = wn * math.sqrt(1 - zeta**2)
    phi = math.acos(zeta)
    targets = np.array([[3.0, -4.0, 1.5]])
    shape = 1 - np.exp(-zeta * wn * t) / math.sqrt(1 - zeta**2) * np.sin(wd * t + phi)
    rate = targets[:, None, :] * shape[None, :, None]
    ep, m = _metrics(_const_setpoint(targets), rate)
    expected = 100 * (1 + math.exp(-zeta * math.pi / math.sqrt(1 - zeta**2)))
    np.testing.assert_allclose(ep.peak_pct, expected, atol=0.05)
    assert m.pitch.peak_pct.mean == pytest.approx(expected, abs=0.05)


def test_error_of_constant_offset() -> None:
    targets = np.array([[2.0, -1.0, 3.0]])
    offset = np.array([0.3, -0.2, 0.05])
    rate = _const_setpoint(targets) - offset
    ep, m = _metrics(_const_setpoint(targets), rate)
    np.testing.assert_allclose(ep.error, np.abs(offset)[None, :] * T)  # 300, 200, 50 rad/s
    assert m.roll.error.mean == pytest.approx(300.0)
    # The constant offset is the whole initial error: not one bit corrected.
    assert m.roll.failure_pct.mean == pytest.approx(100.0)
    assert m.roll.success_pct.mean == 0.0


def _settling_at(fractions: list[float], e0: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """Episodes that reach `fraction` of e0 by 0.2 s and stay there."""
    frac = np.asarray(fractions)[:, None] * np.clip(t / 0.2, 0, 1)[None, :]
    rate = np.repeat((e0 * frac)[..., None], 3, axis=2)
    return _const_setpoint(np.full((len(fractions), 3), e0)), rate


def test_success_and_failure_classification() -> None:
    # Settling errors of 0%, 50%, 15%, 5% and exactly 10% (boundary counts as success).
    sp, rate = _settling_at([1.0, 0.5, 0.85, 0.95, 0.9])
    ep, m = _metrics(sp, rate)
    np.testing.assert_array_equal(ep.success[:, 0], [True, False, False, True, True])
    np.testing.assert_allclose(ep.settle_err_pct[:, 0], [0, 50, 15, 5, 10], atol=1e-9)
    a = m.roll
    assert a.success_pct.mean == pytest.approx(60.0)
    assert a.n_failures == 2
    assert a.failure_pct.mean == pytest.approx(32.5)
    assert a.failure_pct.ci95 == pytest.approx(1.96 * np.std([50, 15], ddof=1) / math.sqrt(2))
    assert a.failure_all_pct.mean == pytest.approx(13.0)  # (0 + 50 + 15 + 0 + 0) / 5


def test_settling_window_starts_at_half_a_second() -> None:
    # On the setpoint until 0.75 s, then 1 rad/s off: the window [0.5, 1) s sees the offset half the time.
    sp = _const_setpoint(np.array([[2.0, 2.0, 2.0]]))
    rate = sp.copy()
    rate[:, 0] = 0.0
    rate[:, 750:] -= 1.0
    ep, _ = _metrics(sp, rate)
    np.testing.assert_allclose(ep.settle_err_pct, 25.0, rtol=1e-12)  # 500 samples, 250 of them off by 1
    # Least squares through a −1 step at the window's middle: Σdx·y / Σdx² = −(250·125) / (500³/12) per step.
    np.testing.assert_allclose(ep.stability[0], -(250 * 125) / (500**3 / 12) * 1e3, rtol=1e-4)


def test_failure_with_no_failures_is_zero() -> None:
    sp, rate = _settling_at([1.0, 0.97])
    _, m = _metrics(sp, rate)
    assert m.roll.failure_pct.mean == 0.0 and m.roll.failure_pct.ci95 == 0.0
    assert m.roll.failure_pct.n == 0
    assert m.to_json()["failure_pct"]["roll"] == [0.0, 0.0]


def test_rise_never_reached_is_left_out_and_counted() -> None:
    sp, rate = _settling_at([1.0, 0.5, 0.8])
    ep, m = _metrics(sp, rate)
    assert np.isnan(ep.rise_ms[1:, 0]).all() and np.isfinite(ep.rise_ms[0, 0])
    assert m.roll.n_rise_not_reached == 2
    assert m.roll.rise_ms.n == 1
    assert m.roll.rise_ms.mean == pytest.approx(160.0, abs=1e-6)  # linear ramp over 0.2 s: 0.1 → 0.9
    assert math.isnan(m.roll.rise_ms.ci95)
    assert m.to_json()["rise_ms"]["roll"] == [pytest.approx(160.0), None]


def test_small_initial_error_axes_are_excluded_and_counted() -> None:
    targets = np.array([[2.0, 0.05, 3.0], [2.5, -0.09, 0.0], [1.0, 4.0, -2.0]])
    rate = _first_order(targets, 0.04)
    ep, m = _metrics(_const_setpoint(targets), rate)
    assert m.roll.n_excluded == 0
    assert m.pitch.n_excluded == 2
    assert m.yaw.n_excluded == 1
    assert m.pitch.success_pct.n == 1 and m.pitch.rise_ms.n == 1 and m.pitch.peak_pct.n == 1
    assert m.yaw.rise_ms.n == 2
    # Error still counts every episode.
    assert m.pitch.error.n == 3
    assert np.isnan(ep.peak_pct[0, 1]) and np.isnan(ep.rise_ms[1, 2])


def test_all_excluded_axis_gives_null_not_nan() -> None:
    targets = np.array([[2.0, 0.0, 3.0], [1.0, 0.02, -2.0]])
    _, m = _metrics(_const_setpoint(targets), _first_order(targets, 0.04))
    j = m.to_json()
    for key in ("success_pct", "failure_pct", "rise_ms", "peak_pct"):
        assert j[key]["pitch"] == [None, None]
    json.dumps(j, allow_nan=False)


def test_ci_formula() -> None:
    mean, ci, n = mean_ci95(np.array([[1.0], [2.0], [3.0], [4.0]]))
    assert mean[0] == 2.5 and n[0] == 4
    assert ci[0] == pytest.approx(1.96 * math.sqrt(5 / 3) / 2)
    # Masked and NaN values do not contribute.
    mean, ci, n = mean_ci95(np.array([[1.0, np.nan], [3.0, 5.0], [100.0, 7.0]]),
                            mask=np.array([[True, True], [True, True], [False, True]]))
    assert list(n) == [2, 2]
    np.testing.assert_allclose(mean, [2.0, 6.0])
    np.testing.assert_allclose(ci, 1.96 * math.sqrt(2) / math.sqrt(2))


def test_ci_through_aggregate() -> None:
    offsets = np.array([0.1, 0.2, 0.3, 0.6])
    targets = np.full((4, 3), 2.0)
    rate = _const_setpoint(targets) - offsets[:, None, None]
    _, m = _metrics(_const_setpoint(targets), rate)
    errors = offsets * T
    assert m.yaw.error.mean == pytest.approx(errors.mean())
    assert m.yaw.error.ci95 == pytest.approx(1.96 * errors.std(ddof=1) / 2)


def test_smoothness_of_known_pwm() -> None:
    targets = np.array([[1.0, 1.0, 1.0]])
    pwm = np.empty((1, T, 4))
    pwm[0, :, 0] = np.where(np.arange(T) % 2 == 0, 1000.0, 1100.0)  # |Δ| = 100 every step
    pwm[0, :, 1] = 1500.0  # 0
    pwm[0, :, 2] = 1200.0 + 0.5 * np.arange(T)  # 0.5 per step
    pwm[0, :, 3] = 1300.0  # 0
    ep, m = _metrics(_const_setpoint(targets), _first_order(targets, 0.03), pwm)
    np.testing.assert_allclose(ep.smoothness_per_motor[0], [100.0, 0.0, 0.5, 0.0])
    assert [s.mean for s in m.smoothness_per_motor] == pytest.approx([100.0, 0.0, 0.5, 0.0])
    for axis in AXES:  # not an axis quantity: the same value under every axis
        assert m.axis(axis).smoothness.mean == pytest.approx(25.125)


def test_json_has_exactly_the_design_keys_and_no_nan() -> None:
    targets = np.array([[2.0, 0.0, -3.0], [1.0, 2.0, 4.0]])
    sp = _const_setpoint(targets)
    rate = _first_order(targets * 0.5, 0.05)  # never reaches 90%: NaN rise everywhere
    _, m = _metrics(sp, rate)
    j = m.to_json()
    assert list(j) == list(METRIC_KEYS)
    assert list(j) == ["success_pct", "failure_pct", "rise_ms", "peak_pct", "error", "stability",
                       "smoothness"]
    for key in METRIC_KEYS:
        assert list(j[key]) == ["roll", "pitch", "yaw"]
        for value in j[key].values():
            assert isinstance(value, list) and len(value) == 2
    text = json.dumps(j, allow_nan=False)
    assert j["rise_ms"]["roll"] == [None, None]
    assert json.loads(text) == j
    json.dumps(m.details_json(), allow_nan=False)


def _continuous(holds: list[int], levels: np.ndarray, tau: float,
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Piecewise-constant setpoint; the rate follows each hold as an exact first-order response."""
    n_t = sum(holds)
    tt = np.arange(n_t) * DT
    sp = np.empty((1, n_t, 3))
    rate = np.empty((1, n_t, 3))
    k, start_rate = 0, np.zeros(3)
    for h, level in zip(holds, levels, strict=True):
        s = np.arange(h) * DT
        sp[0, k:k + h] = level
        rate[0, k:k + h] = level + (start_rate - level) * np.exp(-s / tau)[:, None]
        start_rate = level + (start_rate - level) * math.exp(-h * DT / tau)
        k += h
    return tt, sp, rate


def test_segment_traces_cuts_holds_and_drops_truncated_tail() -> None:
    holds = [300, 700, 250, 40]
    levels = np.array([[2.0, -1.0, 0.5], [0.0, 3.0, 0.5], [-4.0, 1.0, 2.0], [1.0, 1.0, 1.0]])
    tt, sp, rate = _continuous(holds, levels, tau=0.03)
    seg = segment_traces(tt, sp, rate, np.full((1, tt.size, 4), 1500.0))
    assert list(seg.lengths) == [300, 700, 250]  # the 40-step tail was cut by the episode's end
    assert list(seg.start) == [0, 300, 1000]
    assert seg.setpoint.shape == (3, 700, 3)
    np.testing.assert_allclose(seg.setpoint[:, 0, :], levels[:3])
    np.testing.assert_allclose(seg.rate[1, 0], rate[0, 300])


def test_continuous_task_metrics_per_hold() -> None:
    tau = 0.03
    holds = [300, 700, 250, 40]
    levels = np.array([[2.0, -1.0, 0.5], [0.0, 3.0, 0.5], [-4.0, 1.0, 2.0], [1.0, 1.0, 1.0]])
    tt, sp, rate = _continuous(holds, levels, tau)
    traces = Traces(tt, sp, rate, np.full((1, tt.size, 4), 1500.0), controller="x", task="continuous")
    m = compute_metrics(traces)
    assert m.unit == "hold" and m.n_episodes == 3
    # Yaw holds at 0.5 in the second hold: e0 there is the residual ≈ 0, left out.
    assert m.yaw.n_excluded == 1
    # Rise is τ·ln 9 from each hold's own start and e0.
    assert m.roll.rise_ms.mean == pytest.approx(tau * math.log(9) * 1000, abs=0.05)
    assert m.roll.rise_ms.n == 3
    # Only the 0.7 s hold has a settling window; the others are counted as unassessed.
    assert m.roll.success_pct.n == 1 and m.roll.n_unassessed == 2
    assert m.roll.stability.n == 3 - 2


def test_padding_does_not_change_metrics() -> None:
    targets = np.array([[2.0, -3.0, 1.0], [1.0, 1.0, -1.0]])
    sp, rate = _const_setpoint(targets), _first_order(targets, 0.05)
    pwm = 1500 + np.random.default_rng(1).normal(0, 3, (2, T, 4))
    short = episode_metrics(t[:800], sp[:, :800], rate[:, :800], pwm[:, :800])
    padded = episode_metrics(t, sp, rate, pwm, lengths=np.array([800, 800]))
    for name in ("rise_ms", "peak_pct", "error", "stability", "settle_err_pct", "smoothness_per_motor"):
        np.testing.assert_allclose(getattr(padded, name), getattr(short, name), rtol=1e-12, atol=1e-12)


def test_thousand_episodes_under_a_second() -> None:
    rng = np.random.default_rng(0)
    n = 1000
    targets = rng.uniform(-5.24, 5.24, (n, 3))
    sp, rate = _const_setpoint(targets), _first_order(targets, 0.04)
    pwm = 1500 + rng.normal(0, 5, (n, T, 4))
    best = math.inf
    for _ in range(3):
        start = time.perf_counter()
        aggregate(episode_metrics(t, sp, rate, pwm))
        best = min(best, time.perf_counter() - start)
    assert best < 1.0, f"{best:.3f} s"
