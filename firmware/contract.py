"""A policy's contract: what an exported ONNX model promises in its `fcemu.*` metadata.

Pure: it reads the metadata strings and the graph's declared inputs and outputs and either
returns a `PolicyContract` whose every field is finite, in range and consistent with the
graph, or raises `PolicyContractError` with one line that says which field is wrong. A
model is refused at load time, never discovered wrong in flight.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from fcemu.firmware.action import ACTION_MAPPINGS
from fcemu.firmware.airframe_spec import AirframeSpec, Envelope
from fcemu.firmware.errors import UserError
from fcemu.firmware.observation import FIELD_DEFS, LEAKS, OBS_VERSION, ObservationSpec, observe_step

META_PREFIX = "fcemu."
REQUIRED_META = ("observation", "action_mapping", "loop_rate_hz")
LOOP_RATE_RANGE_HZ = (50.0, 20_000.0)
MAX_MEMORY = 64
# The observation is scaled to about ±1 in training; a scale that maps the physical range
# (±RATE_BOUND rad/s of rate error, 0..the top rotor speed of the envelope) outside [1/20, 20]
# is not one a policy was trained with (swapped or corrupted metadata).
RATE_BOUND = 5.24
SCALED_RANGE = (1.0 / 20.0, 20.0)
# A model without an envelope (exported before they were recorded) flies an airframe whose top
# rotor speed its observation's scale maps to 1 within this fraction.
LEGACY_SCALE_TOLERANCE = 0.01
# Actions are in [-1, 1] and clipped there; a model answering ordinary observations with
# outputs beyond this bound was not trained for this action space.
OUTPUT_LIMIT = 100.0
MAX_LOOP_DELAY_TICKS = 5  # the longest loop the randomisation ranges draw (ESC 2 + gyro 3): the probes' span
_SPEC_KEYS = {"memory", "rate_scale", "rotor_speed_scale", "fields", "version", "loop_delay_scale",
              "per_airframe_rotor_speed", "authority_scale", *LEAKS}
# The PID a policy was fitted against (`fcemu fit`: pid.json), a path relative to the policy file, so
# that the folder can be moved: what it hands over to unless --fallback names another.
FALLBACK_META = "fallback"


class PolicyContractError(UserError, ValueError):
    """The ONNX file is not a policy this firmware can fly."""


class TensorInfo(Protocol):
    """What the contract reads of a graph input or output (onnxruntime's NodeArg has it)."""

    name: str
    shape: Sequence[Any]
    type: str


@dataclass(frozen=True)
class PolicyContract:
    observation: ObservationSpec
    action_mapping: str
    loop_rate_hz: float
    throttle: float | tuple[float, float] | None  # the collective range trained on; None: hover
    airframe: str | None = None  # the airframe it was made for (None: not recorded)
    envelope: Envelope | None = None  # the airframes it was trained across (None: not recorded)

    @classmethod
    def from_metadata(cls, meta: Mapping[str, str], where: str = "policy",
                      loop_rate_hz: float | None = None) -> PolicyContract:
        """Validate every contract field; `loop_rate_hz` is the rate the loop will run at, if known."""
        missing = [k for k in REQUIRED_META if k not in meta]
        if missing:
            raise PolicyContractError(
                f"{where}: metadata lacks {', '.join(META_PREFIX + k for k in missing)}; "
                "export policies with `fcemu export`")
        envelope = _envelope(meta.get("envelope"), where)
        top = None if envelope is None or "max_rotor_speed" not in envelope.ranges \
            else envelope.ranges["max_rotor_speed"][1]
        spec = _observation(meta["observation"], where, top)  # type: ignore[arg-type]
        mapping = meta["action_mapping"]
        if mapping not in ACTION_MAPPINGS:
            raise PolicyContractError(
                f"{where}: action mapping {_short(mapping)} unknown (known: {ACTION_MAPPINGS})")
        rate = _loop_rate(meta["loop_rate_hz"], where)
        if loop_rate_hz is not None and abs(rate - loop_rate_hz) > 1e-6:
            raise PolicyContractError(f"{where}: trained for a {rate:g} Hz loop, asked to run at "
                                      f"{loop_rate_hz:g} Hz")
        throttle = _throttle(meta.get("throttle", "null"), where)
        return cls(spec, mapping, rate, throttle, meta.get("airframe"), envelope)

    def check_airframe(self, airframe: AirframeSpec, where: str = "policy") -> None:
        """Refuse, in one line, to fly an airframe outside the envelope the policy was trained across."""
        made_for = self.airframe or "an airframe it does not name"
        if self.envelope is None and not self.observation.per_airframe_rotor_speed:
            top = 1.0 / self.observation.rotor_speed_scale
            if abs(self.observation.rotor_speed_scale * airframe.max_rotor_speed - 1.0) \
                    > LEGACY_SCALE_TOLERANCE:
                raise PolicyContractError(
                    f"policy {where} records no envelope and was made for a top rotor speed of "
                    f"{top:,.0f} rad/s; "
                    f"{airframe.name}'s is {airframe.max_rotor_speed:,.0f} rad/s")
            return
        if self.envelope is None:  # scaled by the flown airframe's top speed, trained across any
            return
        outside = self.envelope.outside(airframe)
        if outside:
            raise PolicyContractError(f"policy {where} was made for {made_for} ({self.envelope.describe()}); "
                                      f"{airframe.name}'s {', '.join(outside)} "
                                      f"{'is' if len(outside) == 1 else 'are'} outside it")

    def check_graph(self, inputs: Sequence[TensorInfo], outputs: Sequence[TensorInfo],
                    where: str = "policy") -> None:
        """The graph takes (batch, observation size) float32 and gives (batch, 4) float32."""
        spec = self.observation
        if len(inputs) != 1 or len(outputs) < 1:
            raise PolicyContractError(f"{where}: expected one input and one output, found "
                                      f"{len(inputs)} and {len(outputs)}")
        in_shape, out_shape = list(inputs[0].shape), list(outputs[0].shape)
        if len(in_shape) != 2 or in_shape[1] != spec.size or not _batch_dim(in_shape[0]):
            raise PolicyContractError(f"{where}: input shape {in_shape} does not match the observation "
                                      f"spec (batch, {spec.size}) = memory {spec.memory} × {spec.step_size}")
        if len(out_shape) != 2 or out_shape[1] != 4 or not _batch_dim(out_shape[0]):
            raise PolicyContractError(f"{where}: output shape {out_shape}, expected (batch, 4) motor actions")
        if inputs[0].type != "tensor(float)" or outputs[0].type != "tensor(float)":
            raise PolicyContractError(f"{where}: input/output must be float32 tensors")

    def probe_observations(self, n: int = 64, seed: int = 0) -> np.ndarray:
        """Observations over the range the policy flies in: rate errors within ±RATE_BOUND, rotor
        speeds within 0..the top speed its observation scales to 1, each step repeated through the memory."""
        rng = np.random.default_rng(seed)
        error = rng.uniform(-RATE_BOUND, RATE_BOUND, (n, 3))
        error[0] = 0.0
        rotor = rng.uniform(0.0, 1.0 / self.observation.rotor_speed_scale, (n, 4))
        delay = rng.integers(0, MAX_LOOP_DELAY_TICKS + 1, n).astype(float)
        step = observe_step(self.observation, error, np.zeros((n, 3)), rotor, loop_delay=delay)
        return np.tile(step, (1, self.observation.memory)).astype(np.float32)

    def check_outputs(self, actions: np.ndarray, where: str = "policy") -> None:
        """Refuse finite outputs far outside the action space (non-finite ones are contained per tick)."""
        finite = actions[np.isfinite(actions)]
        if finite.size and float(np.abs(finite).max()) > OUTPUT_LIMIT:
            raise PolicyContractError(
                f"{where}: outputs up to {float(np.abs(finite).max()):.3g} on ordinary observations; "
                f"actions are in [-1, 1] (at most ±{OUTPUT_LIMIT:g} accepted before clipping)")


def named_fallback(meta: Mapping[str, str], policy: str | Path) -> Path | None:
    """The PID preset file the policy's metadata names as its fallback, beside `policy`; None if none."""
    text = meta.get(FALLBACK_META)
    if text is None:
        return None
    if not text or Path(text).is_absolute():
        raise PolicyContractError(f"{policy}: {META_PREFIX}{FALLBACK_META} {_short(text)} is not a path "
                                  "relative to the policy file")
    return Path(policy).parent / text


def _short(value: object, limit: int = 40) -> str:
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit - 1]}…"


def _batch_dim(dim: object) -> bool:
    return isinstance(dim, str) or dim is None or dim == 1


def _number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _finite(value: object) -> bool:
    try:
        return _number(value) and math.isfinite(value)  # type: ignore[arg-type]
    except OverflowError:
        return False


def _envelope(text: str | None, where: str) -> Envelope | None:
    if text is None:
        return None
    try:
        return Envelope.from_json(text)
    except ValueError as exc:
        raise PolicyContractError(f"{where}: envelope not understood ({exc})") from None


_DEFAULTS = {f.name: f.default for f in fields(ObservationSpec)}


def _observation(text: str, where: str, top_rotor_speed: float | None) -> ObservationSpec:
    """The spec; `top_rotor_speed` (the envelope's, if any) is what rotor_speed_scale must map near 1."""
    try:
        raw = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise PolicyContractError(f"{where}: observation spec not understood ({exc})") from None
    if not isinstance(raw, dict):
        raise PolicyContractError(f"{where}: observation spec not understood (not a JSON object)")
    unknown = set(raw) - _SPEC_KEYS
    if unknown or "fields" not in raw:
        raise PolicyContractError(f"{where}: observation spec not understood (keys {sorted(raw)[:8]})")
    version = raw.get("version", OBS_VERSION)
    if not isinstance(version, int) or isinstance(version, bool) or version != OBS_VERSION:
        raise PolicyContractError(f"{where}: observation version {_short(version)}, this firmware "
                                  f"builds version {OBS_VERSION}")
    memory = raw.get("memory", 1)
    if not isinstance(memory, int) or isinstance(memory, bool) or not 1 <= memory <= MAX_MEMORY:
        raise PolicyContractError(f"{where}: observation memory {_short(memory)} is not an integer "
                                  f"in 1..{MAX_MEMORY}")
    fields = raw["fields"]
    if (not isinstance(fields, list) or not fields or not all(isinstance(f, str) for f in fields)
            or set(fields) - set(FIELD_DEFS) or len(set(fields)) != len(fields)):
        raise PolicyContractError(f"{where}: observation spec not understood (fields {_short(fields)}; "
                                  f"known: {sorted(FIELD_DEFS)}, each at most once)")
    if "rotor_speed_scale" not in raw:
        raise PolicyContractError(f"{where}: observation spec lacks rotor_speed_scale")
    if raw.get("per_airframe_rotor_speed") is True:  # the scale is the flown airframe's, not the envelope's
        top_rotor_speed = None
    for key, physical in (("rate_scale", RATE_BOUND), ("rotor_speed_scale", top_rotor_speed)):
        value = raw.get(key, _DEFAULTS[key])
        lo, hi = SCALED_RANGE
        if not _finite(value) or not value > 0:
            raise PolicyContractError(f"{where}: observation {key} {_short(value)} is not a finite "
                                      "number > 0")
        if physical is not None and not lo <= value * physical <= hi:
            raise PolicyContractError(f"{where}: observation {key} {value:.3g} maps {physical:g} rad/s to "
                                      f"{value * physical:.3g}, outside [{lo:g}, {hi:g}] as trained")
    leaks = {}
    for key in sorted(LEAKS):
        leak = raw.get(key, _DEFAULTS[key])
        if not _finite(leak) or not 0.0 <= leak < 1.0:
            raise PolicyContractError(f"{where}: observation {key} {_short(leak)} is not in [0, 1)")
        leaks[key] = float(leak)
    delay_scale = raw.get("loop_delay_scale", _DEFAULTS["loop_delay_scale"])
    if not _finite(delay_scale) or not 0.0 < delay_scale <= 1.0:
        raise PolicyContractError(f"{where}: observation loop_delay_scale {_short(delay_scale)} "
                                  "is not in (0, 1]")
    authority_scale = raw.get("authority_scale", _DEFAULTS["authority_scale"])
    if not _finite(authority_scale) or not authority_scale > 0.0:
        raise PolicyContractError(f"{where}: observation authority_scale {_short(authority_scale)} "
                                  "is not a finite number > 0")
    per_airframe = raw.get("per_airframe_rotor_speed", False)
    if not isinstance(per_airframe, bool):
        raise PolicyContractError(f"{where}: observation per_airframe_rotor_speed {_short(per_airframe)} "
                                  "is not true or false")
    return ObservationSpec(memory=memory, rate_scale=float(raw.get("rate_scale", _DEFAULTS["rate_scale"])),
                           rotor_speed_scale=float(raw["rotor_speed_scale"]), fields=tuple(fields),
                           version=version, loop_delay_scale=float(delay_scale),
                           authority_scale=float(authority_scale),
                           per_airframe_rotor_speed=per_airframe, **leaks)


def _loop_rate(text: str, where: str) -> float:
    try:
        rate = float(text)
    except (TypeError, ValueError):
        raise PolicyContractError(f"{where}: loop_rate_hz {_short(text)} is not a number") from None
    lo, hi = LOOP_RATE_RANGE_HZ
    if not math.isfinite(rate) or not lo <= rate <= hi:
        raise PolicyContractError(f"{where}: loop_rate_hz {_short(text)} is not a rate in "
                                  f"[{lo:g}, {hi:g}] Hz")
    return rate


def _throttle(text: str, where: str) -> float | tuple[float, float] | None:
    try:
        raw = json.loads(text)
    except (ValueError, RecursionError):
        raw = text
    if raw is None:
        return None
    if _finite(raw) and 0.0 <= raw <= 1.0:
        return float(raw)
    if (isinstance(raw, list) and len(raw) == 2 and all(_finite(v) for v in raw)
            and 0.0 <= raw[0] <= raw[1] <= 1.0):
        return (float(raw[0]), float(raw[1]))
    raise PolicyContractError(f"{where}: throttle {_short(text)} is not null, a number in [0, 1] or "
                              "[low, high] with 0 <= low <= high <= 1")
