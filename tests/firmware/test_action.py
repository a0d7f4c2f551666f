"""The action mappings shared by training and flight."""

from __future__ import annotations

import numpy as np
import pytest

from fcemu.firmware.action import action_to_pwm, gymfc_pwm, pwm_to_action, throttle_pwm


def test_gymfc_mapping_is_the_papers():
    np.testing.assert_array_equal(gymfc_pwm(np.array([-1.0, 0.0, 1.0, 3.0])), [1000, 1500, 2000, 2000])


def test_throttle_mapping_centres_the_differential_on_the_collective():
    pwm = throttle_pwm(np.array([0.2, -0.2, 0.2, -0.2]), 0.5)
    np.testing.assert_allclose(pwm, [1600, 1400, 1600, 1400])
    assert throttle_pwm(np.zeros(4), 0.3).tolist() == [1300.0] * 4


def test_airmode_shifts_the_collective_instead_of_clipping_an_axis():
    pwm = throttle_pwm(np.array([1.0, -1.0, 1.0, -1.0]), 0.95)  # differential ±0.5 at 95%
    assert pwm.max() == 2000 and pwm.min() == 1000  # full differential kept, collective moved down
    # mix [0.75, -0.25, -0.25, -0.25] at 50% would clip motor 1; the collective drops to 25% instead
    squeezed = throttle_pwm(np.array([1.0, -1.0, -1.0, -1.0]), 0.5)
    np.testing.assert_allclose(squeezed, [2000, 1000, 1000, 1000])


def test_a_mix_wider_than_the_range_is_scaled_to_fit():
    pwm = throttle_pwm(np.array([1.0, -1.0, 1.0, -1.0]), 0.5, gain=1.0)  # ±1: twice the range
    np.testing.assert_allclose(pwm, [2000, 1000, 2000, 1000])


def reference_throttle_pwm(action: np.ndarray, throttle: np.ndarray, gain: float = 0.5) -> np.ndarray:
    """The mapping the shipped policy was trained with, written as whole-array numpy."""
    a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
    mix = gain * (a - a.sum(axis=-1, keepdims=True) * 0.25)
    lo, hi = mix.min(axis=-1, keepdims=True), mix.max(axis=-1, keepdims=True)
    scale = 1.0 / np.maximum(hi - lo, 1.0)
    t = np.clip(np.asarray(throttle, dtype=np.float64), 0.0, 1.0)[..., None]
    t = np.minimum(np.maximum(t, -lo * scale), 1.0 - hi * scale)
    return 1000.0 + 1000.0 * np.clip(t + mix * scale, 0.0, 1.0)


def test_single_vehicle_path_is_bit_identical_to_the_batched_one():
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1.6, 1.6, (20_000, 4)).astype(np.float32)
    actions[:50] = np.round(actions[:50])  # ties between motors, exact ±1 and zeros
    throttles = rng.uniform(-0.1, 1.1, 20_000)
    throttles[:10] = [0.0, 1.0, -0.0, 0.5, 0.0, 1.0, 0.25, 0.75, 0.0, 1.0]
    batched = throttle_pwm(actions, throttles)
    single = np.array([throttle_pwm(a, float(t)) for a, t in zip(actions, throttles, strict=True)])
    assert np.array_equal(batched, single)
    assert np.array_equal(batched, reference_throttle_pwm(actions, throttles))
    assert np.array_equal(throttle_pwm(actions.reshape(100, 200, 4), throttles.reshape(100, 200)),
                          batched.reshape(100, 200, 4))
    assert np.array_equal(throttle_pwm(actions, 0.6), reference_throttle_pwm(actions, np.full(20_000, 0.6)))


def test_unknown_mapping_is_refused():
    with pytest.raises(ValueError, match="unknown action mapping"):
        action_to_pwm("rpm", np.zeros(4))


def test_pwm_to_action_inverts_each_mapping():
    rng = np.random.default_rng(0)
    t = rng.uniform(0.4, 0.8, 50)
    diff = rng.uniform(-0.15, 0.15, (50, 4))
    diff -= diff.mean(axis=1, keepdims=True)
    pwm = 1000.0 + 1000.0 * (t[:, None] + diff)  # a mix that fits the output range
    np.testing.assert_allclose(throttle_pwm(pwm_to_action("throttle", pwm), t), pwm, atol=1e-9)
    np.testing.assert_allclose(gymfc_pwm(pwm_to_action("gymfc", pwm)), pwm, atol=1e-9)
    beyond = np.array([900.0, 2100.0, 1000.0, 2000.0])  # no action gives it: the nearest one in range
    np.testing.assert_array_equal(pwm_to_action("gymfc", beyond), [-1.0, 1.0, -1.0, 1.0])


def test_every_throttle_mix_in_the_output_range_has_its_exact_action():
    """One motor far from the other three (roll, pitch and yaw all large) is 0.75 of the range from
    their mean, past the 0.5 a zero-mean action reaches: the action's range is centred instead."""
    rng = np.random.default_rng(1)
    u = rng.uniform(0.0, 1.0, (500, 4))
    u[:100] = [1.0, 0.0, 0.0, 0.0]
    u[100:200, 1:] *= 0.1
    pwm = 1000.0 + 1000.0 * u
    action = pwm_to_action("throttle", pwm)
    assert np.abs(action).max() <= 1.0
    np.testing.assert_allclose(throttle_pwm(action, u.mean(axis=1)), pwm, atol=1e-9)
    zero_mean = (u - u.mean(axis=1, keepdims=True)) / 0.5
    assert np.abs(zero_mean).max() > 1.4  # what the old label clipped
    with pytest.raises(ValueError, match="unknown action mapping"):
        pwm_to_action("bogus", pwm)
