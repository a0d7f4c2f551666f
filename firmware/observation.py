"""The neural controller's observation: one definition for training and for flight.

The GymFC observation (Koch et al. 2018): the rate error e = Ω* − Ω (3) and the rotor
speeds (4) for the last `memory` steps, newest first. `sim_bridge.env` trains on
exactly this code and `firmware.neural` feeds it to the ONNX model; the spec travels in
the model's metadata and the firmware refuses a model whose spec differs.

Every function takes arrays with any leading batch shape, so the batched environment
and the single flight controller share the arithmetic.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass

import numpy as np

OBS_VERSION = 1
FIELDS = ("rate_error", "rotor_speed")
FIELD_SIZES = {"rate_error": 3, "rotor_speed": 4}


@dataclass(frozen=True)
class ObservationSpec:
    memory: int = 1
    rate_scale: float = 1.0 / 5.24  # rad/s -> about ±1 at the paper's command bound
    rotor_speed_scale: float = 1.0 / 1100.0  # rad/s -> 0..1 at the Iris' max rotor speed
    fields: tuple[str, ...] = FIELDS
    version: int = OBS_VERSION

    def __post_init__(self) -> None:
        if self.memory < 1:
            raise ValueError(f"memory must be >= 1, got {self.memory}")
        unknown = set(self.fields) - set(FIELD_SIZES)
        if unknown:
            raise ValueError(f"unknown observation fields {sorted(unknown)}")

    @property
    def step_size(self) -> int:
        return sum(FIELD_SIZES[f] for f in self.fields)

    @property
    def size(self) -> int:
        return self.step_size * self.memory

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> ObservationSpec:
        raw = json.loads(text)
        raw["fields"] = tuple(raw["fields"])
        return cls(**raw)


def observe_step(spec: ObservationSpec, setpoint: np.ndarray, gyro: np.ndarray,
                 rotor_speed: np.ndarray) -> np.ndarray:
    """One step's features, (..., step_size) float32, in `spec.fields` order."""
    parts = {
        "rate_error": (setpoint - gyro) * spec.rate_scale,
        "rotor_speed": rotor_speed * spec.rotor_speed_scale,
    }
    return np.concatenate([parts[f] for f in spec.fields], axis=-1).astype(np.float32)


class ObservationHistory:
    """The last `memory` steps, newest first, for one vehicle or a batch of them."""

    def __init__(self, spec: ObservationSpec, batch_shape: tuple[int, ...] = ()) -> None:
        self.spec = spec
        self._buf = np.zeros((*batch_shape, spec.memory, spec.step_size), dtype=np.float32)

    def reset(self, step: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """Fill the whole history with one step (the episode start); `mask` picks batch rows."""
        if mask is None:
            self._buf[...] = step[..., None, :]
        else:
            self._buf[mask] = step[mask][..., None, :]
        return self.observation()

    def push(self, step: np.ndarray) -> np.ndarray:
        if self.spec.memory > 1:
            self._buf[..., 1:, :] = self._buf[..., :-1, :]
        self._buf[..., 0, :] = step
        return self.observation()

    def observation(self) -> np.ndarray:
        return self._buf.reshape(*self._buf.shape[:-2], self.spec.size).copy()
