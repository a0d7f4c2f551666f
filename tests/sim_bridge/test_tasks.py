import itertools

import numpy as np
import pytest

from fcemu.sim_bridge.tasks import (
    OMEGA_MAX,
    continuous_schedule,
    draw_throttle,
    episodic_commands,
    episodic_setpoint,
    pulse_schedule,
    rate_reward,
)


def _runs(x: np.ndarray) -> list[tuple[np.ndarray, int]]:
    """Constant segments of a (T, 3) trace as (value, length)."""
    change = np.flatnonzero(np.any(np.diff(x, axis=0) != 0, axis=1)) + 1
    edges = [0, *change.tolist(), len(x)]
    return [(x[a], b - a) for a, b in itertools.pairwise(edges)]


def test_episodic_commands_are_seeded_bounded_and_spread():
    a = episodic_commands(7, 500)
    assert a.shape == (500, 3)
    np.testing.assert_array_equal(a, episodic_commands(7, 500))
    assert not np.array_equal(a, episodic_commands(8, 500))
    assert np.abs(a).max() <= OMEGA_MAX
    assert a.min() < -0.9 * OMEGA_MAX and a.max() > 0.9 * OMEGA_MAX
    assert np.abs(a.mean(axis=0)).max() < 0.5


def test_episodic_setpoint_batch_shape():
    rng = np.random.default_rng(0)
    assert episodic_setpoint(rng, batch_shape=(4, 2)).shape == (4, 2, 3)


def test_continuous_schedule_pulses_return_to_zero_with_paper_widths():
    dt = 0.001
    x = continuous_schedule(3, 60.0, dt)
    assert x.shape == (60_000, 3)
    np.testing.assert_array_equal(x, continuous_schedule(3, 60.0, dt))
    assert np.abs(x).max() <= OMEGA_MAX
    runs = _runs(x)[:-1]  # the last one is cut off by the end of the trace
    zero = [n for v, n in runs if not v.any()]
    held = [n for v, n in runs if v.any()]
    assert len(held) > 40 and len(zero) >= len(held) - 1
    for n in zero + held:
        assert 100 <= n <= 1000
    assert not x[0].any()  # it starts at rest, as the paper's appendix describes
    # commands alternate with rests: no two commands back to back
    kinds = [bool(v.any()) for v, _ in _runs(x)]
    assert all(not (a and b) for a, b in itertools.pairwise(kinds))


def test_continuous_schedule_without_rests_is_back_to_back():
    x = pulse_schedule(np.random.default_rng(1), 20_000, rest_s=None)
    runs = _runs(x)[:-1]
    assert all(v.any() for v, _ in runs)
    assert all(100 <= n <= 1000 for _, n in runs)


def test_draw_throttle_fixed_or_range():
    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    assert draw_throttle(rng, 0.6) == 0.6
    assert rng.bit_generator.state == state  # a fixed throttle draws nothing
    draws = [draw_throttle(rng, (0.3, 0.7)) for _ in range(200)]
    assert 0.3 <= min(draws) < 0.35 and 0.65 < max(draws) <= 0.7


def test_rate_reward_formula():
    sp = np.array([1.0, -2.0, 0.5])
    rate = np.array([0.5, 0.0, 1.0])
    assert rate_reward(sp, rate) == pytest.approx(-(0.5 + 2.0 + 0.5) / (3 * 5.24))
    assert rate_reward(sp, sp) == 0.0
    assert rate_reward(np.full(3, 5.24), np.full(3, -5.24)) == -1.0  # clipped
    batch = rate_reward(np.stack([sp, sp]), np.stack([rate, sp]))
    assert batch.shape == (2,) and batch[1] == 0.0 and batch[0] == rate_reward(sp, rate)
