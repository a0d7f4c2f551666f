"""The step response from a log (PID-Analyzer's Wiener deconvolution) of systems whose response is known."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from fcemu.evaluation.step_response import _snr, step_response

pytestmark = pytest.mark.no_wall_clock


def sticks(dt: float, seconds: float = 30.0, seed: int = 0) -> np.ndarray:
    """A pilot's setpoint, rad/s: levels held 0.1-0.5 s at random amplitudes, some chirps, some noise."""
    rng = np.random.default_rng(seed)
    n = round(seconds / dt)
    sp = np.zeros(n)
    k = 0
    while k < n:
        hold = round(rng.uniform(0.1, 0.5) / dt)
        amp = rng.choice([0.5, 2.0, 6.0, 12.0])  # 12 rad/s ≈ 690 deg/s: some windows are "high input"
        if rng.random() < 0.15:
            t = np.arange(min(2 * hold, n - k)) * dt
            sp[k:k + len(t)] = 0.5 * amp * signal.chirp(t, 1.0, max(t[-1], dt), 15.0)
            k += len(t)
        else:
            sp[k:k + hold] = rng.uniform(-amp, amp)
            k += hold
    return sp + rng.normal(0.0, 0.02, n)


def fly(system: tuple[np.ndarray, np.ndarray], setpoint: np.ndarray) -> np.ndarray:
    return signal.lfilter(*system, setpoint)


def lag(tau: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """1/(τs + 1), discretised with a first-order hold: the input ramps between samples, so a step
    between two samples happens midway, as step_response takes it."""
    b, a, _ = signal.cont2discrete(([1.0], [tau, 1.0]), dt, method="foh")
    return np.ravel(b), np.ravel(a)


def second_order(zeta: float, hz: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    w = 2.0 * np.pi * hz
    b, a, _ = signal.cont2discrete(([w * w], [1.0, 2.0 * zeta * w, w * w]), dt, method="foh")
    return np.ravel(b), np.ravel(a)


def delay(samples: int) -> tuple[np.ndarray, np.ndarray]:
    return np.r_[np.zeros(samples), 1.0], np.array([1.0])


def test_snr_is_pid_analyzers():
    dt = 0.002
    nfft = 1024
    snr = _snr(nfft, dt)
    freq = np.fft.rfftfreq(nfft, dt)
    assert snr[0] == pytest.approx(10.0)
    assert snr[freq < 5.0].min() > 9.9  # trusted well under the 25 Hz cut
    assert 3.0 < np.interp(25.0, freq, snr) < 7.0  # about half-way at the cut
    assert snr[freq > 60.0].max() < 1e-7  # 10·1e-9 past the Gaussian's 4σ: nothing trusted


@pytest.mark.parametrize(("dt", "samples"), [(0.002, 5), (0.001, 10), (0.0005, 30)])
def test_pure_delay(dt, samples):
    sp = sticks(dt)
    r = step_response(sp, fly(delay(samples), sp), dt)
    assert r is not None
    assert r.windows > 300
    assert r.t_s[0] == pytest.approx(dt / 2) and r.t_s[-1] == pytest.approx(0.5, abs=dt)
    assert r.final == pytest.approx(1.0, abs=0.01)
    assert r.delay_ms == pytest.approx(samples * dt * 1000.0, abs=0.3)  # half-way: exactly the delay
    # the Wiener filter's band limit (~25-58 Hz) spreads the jump over ~8 ms (10-90 %), ~10 % ringing
    assert 1.0 < r.peak < 1.13
    assert samples * dt * 1000.0 + 2.5 < r.rise_ms < samples * dt * 1000.0 + 4.5
    assert abs(r.response[r.t_s < samples * dt - 0.006]).max() < 0.1  # nothing well before the delay


@pytest.mark.parametrize("dt", [0.002, 0.0005])
def test_first_order_lag(dt):
    tau = 0.01
    sp = sticks(dt, seed=1)
    r = step_response(sp, fly(lag(tau, dt), sp), dt)
    assert r is not None
    assert r.rise_ms == pytest.approx(tau * np.log(10.0) * 1000.0, rel=0.1)
    assert r.delay_ms == pytest.approx(tau * np.log(2.0) * 1000.0, rel=0.1)
    assert 0.98 < r.peak <= 1.03
    assert r.final == pytest.approx(1.0, abs=0.02)
    truth = 1.0 - np.exp(-r.t_s / tau)
    assert abs(r.response - truth)[r.t_s > 0.01].max() < 0.05


def test_a_longer_window_leaks_less_on_a_slow_loop():
    dt, tau = 0.002, 0.02
    sp = sticks(dt, seed=2)
    gyro = fly(lag(tau, dt), sp)
    short = step_response(sp, gyro, dt)
    long = step_response(sp, gyro, dt, frame_s=2.0)
    expected = tau * np.log(10.0) * 1000.0
    assert short is not None and long is not None
    assert short.rise_ms == pytest.approx(expected, rel=0.15)  # PID-Analyzer's 1 s reads it early
    assert long.rise_ms == pytest.approx(expected, rel=0.05)
    assert abs(long.rise_ms - expected) < abs(short.rise_ms - expected)


def test_underdamped_second_order_overshoot():
    zeta, dt = 0.4, 0.001
    sp = sticks(dt, seed=3)
    r = step_response(sp, fly(second_order(zeta, 10.0, dt), sp), dt)
    assert r is not None
    assert r.peak == pytest.approx(1.0 + np.exp(-np.pi * zeta / np.sqrt(1.0 - zeta**2)), abs=0.03)
    t_peak = np.pi / (2.0 * np.pi * 10.0 * np.sqrt(1.0 - zeta**2))
    assert r.t_s[np.argmax(r.response)] == pytest.approx(t_peak, abs=0.003)
    assert r.final == pytest.approx(1.0, abs=0.02)


def test_the_log_rate_does_not_change_the_answer():
    rises = []
    for dt in (0.002, 0.0005):
        sp = sticks(dt, seed=4)
        r = step_response(sp, fly(second_order(0.4, 10.0, dt), sp), dt)
        assert r is not None
        rises.append(r.rise_ms)
    assert rises[0] == pytest.approx(rises[1], rel=0.1)
    assert abs(rises[0] - rises[1]) < 1.5  # ms: within a sample at 2 ms


def test_rise_is_resolved_below_a_sample():
    dt = 0.002  # a 500 Hz log
    sp = sticks(dt, seed=5)
    taus = np.linspace(0.010, 0.011, 5)
    rises = [step_response(sp, fly(lag(tau, dt), sp), dt).rise_ms for tau in taus]
    steps = np.diff(rises)  # the truth: 0.25 ms·ln 10 = 0.58 ms each, a quarter of a sample
    # whole samples would step by 0 or 2 ms; the windows' leakage reads the lags a little early,
    # more so the slower (the steps come out ~25 % short)
    assert ((steps > 0.3) & (steps < 0.8)).all(), steps
    assert rises[-1] - rises[0] == pytest.approx(1000.0 * (taus[-1] - taus[0]) * np.log(10.0), rel=0.35)


def test_gyro_noise_changes_little():
    dt = 0.001
    sp = sticks(dt, seed=6)
    gyro = fly(second_order(0.5, 12.0, dt), sp)
    rng = np.random.default_rng(7)
    t = np.arange(len(sp)) * dt
    noisy = gyro + rng.normal(0.0, 0.3, len(sp)) + 0.5 * np.sin(2.0 * np.pi * 180.0 * t)  # + motor hum
    clean, dirty = step_response(sp, gyro, dt), step_response(sp, noisy, dt)
    assert clean is not None and dirty is not None
    assert dirty.rise_ms == pytest.approx(clean.rise_ms, rel=0.05)
    assert dirty.peak == pytest.approx(clean.peak, abs=0.03)
    assert abs(dirty.response - clean.response).max() < 0.05


def test_averages_and_input_split_agree_on_a_linear_loop():
    dt = 0.002
    sp = sticks(dt, seed=8)
    gyro = fly(second_order(0.4, 10.0, dt), sp)
    mode = step_response(sp, gyro, dt)
    median = step_response(sp, gyro, dt, average="median")
    low = step_response(sp, gyro, dt, inputs="low")
    high = step_response(sp, gyro, dt, inputs="high")
    assert mode is not None and median is not None and low is not None and high is not None
    assert low.windows + high.windows == mode.windows and high.windows >= 10
    for other in (median, low, high):
        assert abs(other.response - mode.response).max() < 0.05
        assert other.rise_ms == pytest.approx(mode.rise_ms, rel=0.05)


def test_units():
    dt = 0.002
    sp = sticks(dt, seed=9)
    gyro = fly(lag(0.015, dt), sp)
    rad = step_response(sp, gyro, dt)
    deg = step_response(np.rad2deg(sp), np.rad2deg(gyro), dt, deg_per_unit=1.0)
    assert rad is not None and deg is not None
    np.testing.assert_allclose(deg.response, rad.response, atol=1e-9)


def test_too_little_input_says_none():
    dt = 0.002
    n = round(20.0 / dt)
    rng = np.random.default_rng(10)
    noise = rng.normal(0.0, 0.05, n)
    assert step_response(np.zeros(n), noise, dt) is None  # no setpoint at all
    assert step_response(np.full(n, 0.1), noise, dt) is None  # 0.1 rad/s ≈ 6 deg/s: under 20 deg/s
    sp = sticks(dt, seconds=0.9)
    assert step_response(sp, sp, dt) is None  # shorter than one window
    sp = sticks(dt, seed=11) * 0.1  # never over 500 deg/s: no high-input response
    assert step_response(sp, sp, dt, inputs="high") is None
    assert step_response(sp, sp, dt, inputs="low") is not None


def test_bad_arguments_raise():
    sp = np.zeros(1000)
    with pytest.raises(ValueError, match="same length"):
        step_response(sp, np.zeros(999), 0.002)
    with pytest.raises(ValueError, match="dt"):
        step_response(sp, sp, 0.0)
    bad = sp.copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match="finite"):
        step_response(bad, sp, 0.002)
    with pytest.raises(ValueError, match="average"):
        step_response(sp, sp, 0.002, average="max")  # type: ignore[arg-type]
