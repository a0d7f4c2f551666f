import numpy as np

from benchmarks.pid_noise_pareto import error_cost, wider
from fcemu.training.pid_search import AxisGains, Knob, Score


def _score(error: float, success: float = 100.0, smoothness: float = 1.0) -> Score:
    three = np.full(3, 1.0)
    return Score(error=three * error, rise_ms=three * 40.0, peak_pct=three * 110.0,
                 success_pct=three * success, not_risen=np.zeros(3), smoothness=smoothness,
                 worst_settle_pct=three)


def test_the_cost_is_the_error_with_success_and_the_noise_wall():
    start = _score(100.0)
    assert error_cost(_score(50.0), start, None) == 1.5
    assert error_cost(_score(50.0, success=98.8), start, None) == 1.5 + 3.0  # a point per % per axis
    assert error_cost(_score(50.0, smoothness=3.0), start, None) == 1.5  # noise-free: no wall
    assert error_cost(_score(50.0, smoothness=1.2), start, 1.2) == 1.5
    assert error_cost(_score(50.0, smoothness=1.7), start, 1.2) == 1.5 + 50.0
    assert error_cost(_score(float("nan")), start, None) == float("inf")


def test_the_filters_bounds_are_wider_than_the_tunes_and_the_rest_is_the_tunes():
    knobs = [Knob("kp_roll", "kp", 0, 1.3, 0.5, 40.0),
             Knob("gyro_lowpass_hz", "gyro_lowpass_hz", None, 1.4, 50, 450),
             Knob("pidsum_roll", "pidsum_limit", 0, 1.25, 0.2, 1.0)]
    gains = AxisGains("gains_roll", (knobs[0],), 2.0)
    out = {k.name: k for k in wider([gains, *knobs])}
    assert (out["gyro_lowpass_hz"].lowest, out["gyro_lowpass_hz"].highest) == (5.0, 1000.0)
    assert out["kp_roll"] is knobs[0] and out["pidsum_roll"] is knobs[2] and out["gains_roll"] is gains
