"""From a neural policy's action a ∈ [-1, 1]^4 to motor PWM: one definition for training and flight.

Two mappings, named in the ONNX metadata:

- ``gymfc``: PWM = 1000 + 500·(a + 1), as in GymFC. The policy owns the collective,
  so it can only fly the ball-joint rig.
- ``throttle``: the outer loop's collective thrust t ∈ [0, 1] plus the policy's
  differential, u = t + gain·(a − mean(a)), with Betaflight's airmode handling (a mix
  wider than the output range is scaled down, then shifted inside it) so no axis
  authority is clipped away. This is what lets a trained policy take off and land.

All functions take arrays with any leading batch shape.
"""

from __future__ import annotations

import numpy as np

ACTION_MAPPINGS = ("gymfc", "throttle")
PWM_MIN, PWM_SPAN = 1000.0, 1000.0
DIFFERENTIAL_GAIN = 0.5


def _clip(x: np.ndarray, lo: float | np.ndarray, hi: float | np.ndarray) -> np.ndarray:
    # np.clip's Python-level dispatch costs several µs on a 4-vector; this runs every tick.
    return np.minimum(np.maximum(x, lo), hi)


def gymfc_pwm(action: np.ndarray) -> np.ndarray:
    return PWM_MIN + 0.5 * PWM_SPAN * (_clip(action, -1.0, 1.0) + 1.0)


def throttle_pwm(action: np.ndarray, throttle: np.ndarray | float,
                 gain: float = DIFFERENTIAL_GAIN) -> np.ndarray:
    a = _clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
    mix = gain * (a - a.sum(axis=-1, keepdims=True) * 0.25)
    lo, hi = mix.min(axis=-1, keepdims=True), mix.max(axis=-1, keepdims=True)
    # A mix wider than the output range is scaled to fit (scaling keeps which motor is min/max).
    scale = 1.0 / np.maximum(hi - lo, 1.0)
    t = _clip(np.asarray(throttle, dtype=np.float64), 0.0, 1.0)
    if t.ndim:
        t = t[..., None]
    t = _clip(t, -lo * scale, 1.0 - hi * scale)  # airmode: shift the collective so the mix fits
    return PWM_MIN + PWM_SPAN * _clip(t + mix * scale, 0.0, 1.0)


def throttle_pwm_one(action: np.ndarray | list[float], throttle: float,
                     gain: float = DIFFERENTIAL_GAIN) -> np.ndarray:
    """`throttle_pwm` for one vehicle in plain floats (a few µs instead of ~15 per tick).

    The same IEEE operations in the same order, so the result is bit-identical to the
    batched version the environment trains with (tests/firmware/test_action.py checks it).
    """
    values = action.tolist() if isinstance(action, np.ndarray) else [float(x) for x in action]
    a = [-1.0 if x < -1.0 else 1.0 if x > 1.0 else x for x in values]
    mean = (((a[0] + a[1]) + a[2]) + a[3]) * 0.25
    mix = [gain * (x - mean) for x in a]
    lo, hi = min(mix), max(mix)
    scale = 1.0 / max(hi - lo, 1.0)
    t = min(max(float(throttle), 0.0), 1.0)
    t = min(max(t, -lo * scale), 1.0 - hi * scale)
    return np.array([PWM_MIN + PWM_SPAN * min(max(t + m * scale, 0.0), 1.0) for m in mix])


def action_to_pwm(mapping: str, action: np.ndarray, throttle: np.ndarray | float = 0.0) -> np.ndarray:
    if mapping == "gymfc":
        return gymfc_pwm(action)
    if mapping == "throttle":
        return throttle_pwm(action, throttle)
    raise ValueError(f"unknown action mapping {mapping!r}; known: {ACTION_MAPPINGS}")
