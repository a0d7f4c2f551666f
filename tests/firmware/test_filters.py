"""Filters against hand-computed coefficients and their textbook responses (Betaflight's filter tests)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from fcemu.firmware.filters import BiquadLowpass, BiquadNotch, PT1Filter, make_lowpass, notch_q, pt1_gain


def _sine_gain(filt, freq_hz: float, dt: float, seconds: float = 2.0) -> float:
    """Steady-state gain for a unit sine: its projection on sin and cos over the last second
    (a whole number of periods for the frequencies used here)."""
    t = np.arange(round(seconds / dt)) * dt
    w = 2 * math.pi * freq_hz * t
    y = np.array([filt.apply(float(v)) for v in np.sin(w)])
    tail = slice(len(t) - round(1.0 / dt), None)
    a, b = 2 * np.mean(y[tail] * np.sin(w[tail])), 2 * np.mean(y[tail] * np.cos(w[tail]))
    return float(math.hypot(a, b))


def test_pt1_gain_matches_hand_computed_values():
    # k = dt / (RC + dt), RC = 1 / (2π fc)
    assert pt1_gain(100.0, 0.001) == pytest.approx(0.3858695450950375, rel=1e-12)
    assert pt1_gain(10.0, 0.001) == pytest.approx(0.05911739744174893, rel=1e-12)
    w = 2 * math.pi * 80 * 0.000125
    assert pt1_gain(80.0, 0.000125) == pytest.approx(w / (w + 1), rel=1e-12)  # Betaflight 4.3 form


def test_pt1_difference_equation_exact():
    f = PT1Filter(100.0, 0.001)
    k = 0.3858695450950375
    assert f.apply(1.0) == pytest.approx(k)
    assert f.apply(1.0) == pytest.approx(k + k * (1 - k))
    assert f.apply(0.0) == pytest.approx((k + k * (1 - k)) * (1 - k))


@pytest.mark.parametrize("rate_hz", [1000, 8000])
def test_pt1_step_reaches_63_percent_at_tau(rate_hz):
    tau = 0.016  # a whole number of samples at both rates
    cutoff = 1.0 / (2 * math.pi * tau)
    dt = 1.0 / rate_hz
    f = PT1Filter(cutoff, dt)
    y = [f.apply(1.0) for _ in range(round(tau / dt))]
    # the discrete PT1 lags its continuous model by less than a sample
    assert y[-1] == pytest.approx(1 - math.exp(-1), abs=0.012 if rate_hz == 1000 else 0.002)
    assert all(b > a for a, b in itertools.pairwise(y))  # monotone, no overshoot


def test_biquad_lowpass_coefficients_match_hand_computed_butterworth():
    # ω = 2π·100·0.001, α = sin ω / (2Q), Q = 1/√2; the classic 2nd-order Butterworth at fs/10
    f = BiquadLowpass(100.0, 0.001)
    expected = (0.0674552738890719, 0.1349105477781438, 0.0674552738890719,
                -1.142980502539901, 0.4128015980961886)
    assert f.coefficients == pytest.approx(expected, rel=1e-9)


def test_biquad_lowpass_dc_gain_one_and_minus_3db_at_cutoff():
    dt = 0.001
    f = BiquadLowpass(100.0, dt)
    y = [f.apply(1.0) for _ in range(500)]
    assert y[-1] == pytest.approx(1.0, abs=1e-9)
    assert max(y) > 1.0  # Butterworth step overshoot (~4%)
    assert max(y) < 1.05
    assert _sine_gain(BiquadLowpass(100.0, dt), 100.0, dt) == pytest.approx(1 / math.sqrt(2), abs=0.01)
    assert _sine_gain(BiquadLowpass(100.0, dt), 20.0, dt) == pytest.approx(1.0, abs=0.01)
    assert _sine_gain(BiquadLowpass(100.0, dt), 400.0, dt) < 0.05


def test_biquad_difference_equation_is_transposed_direct_form_2():
    f = BiquadLowpass(50.0, 0.001)
    b0, b1, b2, a1, a2 = f.coefficients
    rng = np.random.default_rng(1)
    x = rng.standard_normal(50)
    y_ref = np.zeros_like(x)
    for n in range(len(x)):  # direct form 1, the textbook equation
        y_ref[n] = (b0 * x[n] + b1 * (x[n - 1] if n >= 1 else 0) + b2 * (x[n - 2] if n >= 2 else 0)
                    - a1 * (y_ref[n - 1] if n >= 1 else 0) - a2 * (y_ref[n - 2] if n >= 2 else 0))
    y = [f.apply(float(v)) for v in x]
    np.testing.assert_allclose(y, y_ref, rtol=1e-12, atol=1e-12)


def test_notch_coefficients_and_zero_at_centre():
    dt = 0.001
    assert notch_q(200.0, 150.0) == pytest.approx(30000 / 17500)
    f = BiquadNotch(200.0, 150.0, dt)
    expected = (0.7828453630610566, -0.4838250423069844, 0.7828453630610566,
                -0.4838250423069844, 0.5656907261221131)
    assert f.coefficients == pytest.approx(expected, rel=1e-9)
    assert _sine_gain(BiquadNotch(200.0, 150.0, dt), 200.0, dt, seconds=4.0) < 1e-3
    # Betaflight's Q is the analog one: the -3 dB edge is exact where the bilinear warp is small
    fast = 1.0 / 8000
    edge = _sine_gain(BiquadNotch(200.0, 150.0, fast), 150.0, fast)
    assert edge == pytest.approx(1 / math.sqrt(2), abs=0.01)
    g = BiquadNotch(200.0, 150.0, dt)
    assert [g.apply(1.0) for _ in range(400)][-1] == pytest.approx(1.0, abs=1e-9)  # DC passes


def test_notch_rejects_a_cutoff_above_the_centre():
    with pytest.raises(ValueError):
        BiquadNotch(100.0, 120.0, 0.001)


def test_biquad_rejects_cutoff_at_nyquist():
    with pytest.raises(ValueError, match="Nyquist"):
        BiquadLowpass(500.0, 0.001)


@pytest.mark.parametrize("filt", [PT1Filter(0.0, 0.001), BiquadLowpass(-1.0, 0.001),
                                  BiquadNotch(0.0, 0.0, 0.001)])
def test_cutoff_zero_or_negative_passes_through(filt):
    assert not filt.enabled
    assert filt.apply(3.25) == 3.25
    x = np.array([1.0, -2.0, 3.0])
    assert filt.apply(x) is x


@pytest.mark.parametrize("kind", ["pt1", "biquad"])
def test_vectorised_over_axes_matches_scalar_filters(kind):
    dt = 0.001
    vec = make_lowpass(kind, 60.0, dt)
    scalars = [make_lowpass(kind, 60.0, dt) for _ in range(3)]
    rng = np.random.default_rng(2)
    for _ in range(100):
        x = rng.standard_normal(3)
        y = vec.apply(x)
        assert y.shape == (3,)
        expected = [s.apply(float(v)) for s, v in zip(scalars, x, strict=True)]
        np.testing.assert_allclose(y, expected, rtol=1e-12)
    grid = make_lowpass(kind, 60.0, dt)
    assert grid.apply(np.ones((2, 4))).shape == (2, 4)


@pytest.mark.parametrize("filt", [PT1Filter(30.0, 0.001), BiquadLowpass(30.0, 0.001),
                                  BiquadNotch(100.0, 70.0, 0.001)])
def test_reset_starts_in_steady_state(filt):
    for _ in range(20):
        filt.apply(5.0)
    filt.reset()
    assert filt.apply(0.0) == pytest.approx(0.0)
    filt.reset(2.5)
    assert [filt.apply(2.5) for _ in range(10)] == pytest.approx([2.5] * 10, abs=1e-12)
    filt.reset(np.array([1.0, -1.0, 0.5]))
    np.testing.assert_allclose(filt.apply(np.array([1.0, -1.0, 0.5])), [1.0, -1.0, 0.5], atol=1e-12)


def test_configure_keeps_state():
    f = PT1Filter(10.0, 0.001)
    for _ in range(50):
        f.apply(1.0)
    before = f.state
    f.configure(20.0, 0.0005)
    assert f.state == before
    assert f.k == pytest.approx(pt1_gain(20.0, 0.0005))


def test_unknown_lowpass_type():
    with pytest.raises(ValueError, match="unknown lowpass"):
        make_lowpass("pt7", 10.0, 0.001)
