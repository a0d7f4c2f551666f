"""From a neural policy's action a ∈ [-1, 1]^4 to motor PWM: one definition for training and flight.

Two mappings, named in the ONNX metadata:

- ``gymfc``: PWM = 1000 + 500·(a + 1), as in GymFC. The policy owns the collective,
  so it can only fly the ball-joint rig.
- ``throttle``: the outer loop's collective thrust t ∈ [0, 1] plus the policy's
  differential, u = t + gain·(a − mean(a)), with Betaflight's airmode handling (a mix
  wider than the output range is scaled down, then shifted inside it) so no axis
  authority is clipped away. This is what lets a trained policy take off and land.

Both take actions of shape (..., 4) with any leading batch shape.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import reduce
from typing import TypeVar

import numpy as np

ACTION_MAPPINGS = ("gymfc", "throttle")
DEFAULT_ACTION_MAPPING = "throttle"  # what `fcemu train`, RateControlEnv and the shipped policies use
PWM_MIN, PWM_SPAN = 1000.0, 1000.0
DIFFERENTIAL_GAIN = 0.5

V = TypeVar("V", float, np.ndarray)


def _clip(x: np.ndarray, lo: float | np.ndarray, hi: float | np.ndarray) -> np.ndarray:
    return np.minimum(np.maximum(x, lo), hi)


def _clip_float(x: float, lo: float, hi: float) -> float:
    x = lo if x < lo else x  # min(max(x, lo), hi), also when lo > hi
    return hi if hi < x else x


def _lowest(values: Sequence[np.ndarray]) -> np.ndarray:
    return reduce(np.minimum, values)


def _highest(values: Sequence[np.ndarray]) -> np.ndarray:
    return reduce(np.maximum, values)


def gymfc_pwm(action: np.ndarray) -> np.ndarray:
    return PWM_MIN + 0.5 * PWM_SPAN * (_clip(action, -1.0, 1.0) + 1.0)


def _throttle_mix(a: Sequence[V], t: V, gain: float, clip: Callable[[V, V | float, V | float], V],
                 lowest: Callable[[Sequence[V]], V], highest: Callable[[Sequence[V]], V]) -> list[V]:
    """The ``throttle`` mapping on four motor actions and a collective, each a float (one
    vehicle) or an array over a batch, with the matching `clip`, `lowest` and `highest`.

    One sequence of IEEE operations either way, so one vehicle and a batch get the same
    bits; plain floats spare one vehicle's tick numpy's per-call overhead.
    """
    a = [clip(x, -1.0, 1.0) for x in a]
    mean = (((a[0] + a[1]) + a[2]) + a[3]) * 0.25
    mix = [gain * (x - mean) for x in a]
    lo, hi = lowest(mix), highest(mix)
    # A mix wider than the output range is scaled to fit (scaling keeps which motor is min/max).
    scale = 1.0 / highest([hi - lo, 1.0])
    # Airmode: shift the collective so the mix fits.
    t = clip(clip(t, 0.0, 1.0), -lo * scale, 1.0 - hi * scale)
    return [PWM_MIN + PWM_SPAN * clip(t + m * scale, 0.0, 1.0) for m in mix]


def throttle_pwm(action: np.ndarray, throttle: np.ndarray | float,
                 gain: float = DIFFERENTIAL_GAIN) -> np.ndarray:
    a = np.asarray(action)
    if a.ndim == 1 and not isinstance(throttle, np.ndarray):
        return np.array(_throttle_mix(a.tolist(), float(throttle), gain, _clip_float, min, max))
    a = a.astype(np.float64, copy=False)
    t = np.asarray(throttle, dtype=np.float64)
    pwm = _throttle_mix([a[..., i] for i in range(4)], t, gain, _clip, _lowest, _highest)
    return np.stack(pwm, axis=-1)


def motor_output(pwm: np.ndarray) -> np.ndarray:
    """u = (PWM − 1000) / 1000 ∈ [0, 1] in float64: the motor output the reward's |Δu| and the
    `motor_output` observation field read, one definition for training and flight."""
    return (np.asarray(pwm, dtype=np.float64) - PWM_MIN) / PWM_SPAN


def pwm_to_action(mapping: str, pwm: np.ndarray) -> np.ndarray:
    """The action whose mapping gives `pwm` (..., 4) where one does, else the nearest in
    [-1, 1]: for a controller's output as a policy's label. ``throttle``: a = (u − ū)/gain
    shifted so its range is centred on zero. The mapping ignores a's mean (the collective comes
    from the outer loop), and centred so, every output spread the range can hold (at most 1 = gain·2)
    has its exact action; a zero-mean a would clip a motor more than 0.5 from the others' mean
    (one motor up, three down), which cost the racer's model-based teacher 7 % of its Error.
    ``gymfc``: a = 2u − 1."""
    u = motor_output(pwm)
    if mapping == "gymfc":
        return np.clip(2.0 * u - 1.0, -1.0, 1.0)
    if mapping == "throttle":
        a = (u - u.mean(axis=-1, keepdims=True)) / DIFFERENTIAL_GAIN
        a = a - 0.5 * (a.max(axis=-1, keepdims=True) + a.min(axis=-1, keepdims=True))
        return np.clip(a, -1.0, 1.0)
    raise ValueError(f"unknown action mapping {mapping!r}; known: {ACTION_MAPPINGS}")


def action_to_pwm(mapping: str, action: np.ndarray, throttle: np.ndarray | float = 0.0) -> np.ndarray:
    if mapping == "gymfc":
        return gymfc_pwm(action)
    if mapping == "throttle":
        return throttle_pwm(action, throttle)
    raise ValueError(f"unknown action mapping {mapping!r}; known: {ACTION_MAPPINGS}")
