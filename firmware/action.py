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


def gymfc_pwm(action: np.ndarray) -> np.ndarray:
    return PWM_MIN + 0.5 * PWM_SPAN * (np.clip(action, -1.0, 1.0) + 1.0)


def throttle_pwm(action: np.ndarray, throttle: np.ndarray | float,
                 gain: float = DIFFERENTIAL_GAIN) -> np.ndarray:
    a = np.clip(action, -1.0, 1.0)
    mix = gain * (a - a.mean(axis=-1, keepdims=True))
    lo, hi = mix.min(axis=-1, keepdims=True), mix.max(axis=-1, keepdims=True)
    span = hi - lo
    mix = np.where(span > 1.0, mix / np.maximum(span, 1e-12), mix)
    lo, hi = mix.min(axis=-1, keepdims=True), mix.max(axis=-1, keepdims=True)
    t = np.clip(np.asarray(throttle, dtype=float), 0.0, 1.0)
    if t.ndim:
        t = t[..., None]
    t = np.clip(t, -lo, 1.0 - hi)  # airmode: shift the collective so the mix fits in [0, 1]
    return PWM_MIN + PWM_SPAN * np.clip(t + mix, 0.0, 1.0)


def action_to_pwm(mapping: str, action: np.ndarray, throttle: np.ndarray | float = 0.0) -> np.ndarray:
    if mapping == "gymfc":
        return gymfc_pwm(action)
    if mapping == "throttle":
        return throttle_pwm(action, throttle)
    raise ValueError(f"unknown action mapping {mapping!r}; known: {ACTION_MAPPINGS}")
