"""The neural controller's observation: one definition for training and for flight.

The GymFC observation (Koch et al. 2018): the rate error e = Ω* − Ω (3) and the rotor
speeds (4) for the last `memory` steps, newest first. Optional field
`rate_error_integral` (3): a leaky integral of the scaled rate error,
I_k = λ·I_{k−1} + (1 − λ)·e_k with I = (1 − λ)·e_0 at the episode start; a policy with
m = 1 has no other memory, so it cannot remove a steady offset the way a PID's I term
does. `observe_step` puts e_k in those columns and `ObservationHistory` integrates them,
so it is the one owner of the integrator state. `sim_bridge.env` trains on
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
FIELDS = ("rate_error", "rotor_speed")  # the default; the shipped policy's spec
FIELD_SIZES = {"rate_error": 3, "rotor_speed": 4, "rate_error_integral": 3}
INTEGRAL = "rate_error_integral"


@dataclass(frozen=True)
class ObservationSpec:
    memory: int = 1
    rate_scale: float = 1.0 / 5.24  # rad/s -> about ±1 at the paper's command bound
    rotor_speed_scale: float = 1.0 / 1100.0  # rad/s -> 0..1 at the Iris' max rotor speed
    fields: tuple[str, ...] = FIELDS
    version: int = OBS_VERSION
    integral_leak: float = 0.995  # λ per step: τ = 200 steps (0.2 s at 1 kHz); only with INTEGRAL

    def __post_init__(self) -> None:
        if self.memory < 1:
            raise ValueError(f"memory must be >= 1, got {self.memory}")
        unknown = set(self.fields) - set(FIELD_SIZES)
        if unknown:
            raise ValueError(f"unknown observation fields {sorted(unknown)}")
        if len(set(self.fields)) != len(self.fields):
            raise ValueError(f"repeated observation fields {self.fields}")
        if not 0.0 <= self.integral_leak < 1.0:
            raise ValueError(f"integral_leak must be in [0, 1), got {self.integral_leak}")

    @property
    def step_size(self) -> int:
        return sum(FIELD_SIZES[f] for f in self.fields)

    @property
    def size(self) -> int:
        return self.step_size * self.memory

    def integral_slice(self) -> slice | None:
        """The integral's columns within one step, or None without the field."""
        if INTEGRAL not in self.fields:
            return None
        start = sum(FIELD_SIZES[f] for f in self.fields[:self.fields.index(INTEGRAL)])
        return slice(start, start + FIELD_SIZES[INTEGRAL])

    def to_json(self) -> str:
        raw = asdict(self)
        if INTEGRAL not in self.fields:  # specs without the integral serialise as before it existed
            del raw["integral_leak"]
        return json.dumps(raw, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> ObservationSpec:
        raw = json.loads(text)
        raw["fields"] = tuple(raw["fields"])
        return cls(**raw)


def observe_step(spec: ObservationSpec, setpoint: np.ndarray, gyro: np.ndarray,
                 rotor_speed: np.ndarray) -> np.ndarray:
    """One step's features, (..., step_size) float32, in `spec.fields` order."""
    error = (setpoint - gyro) * spec.rate_scale
    parts = {
        "rate_error": error,
        "rotor_speed": rotor_speed * spec.rotor_speed_scale,
        INTEGRAL: error,  # the integrator's input; `ObservationHistory` integrates it
    }
    return np.concatenate([parts[f] for f in spec.fields], axis=-1).astype(np.float32)


class ObservationHistory:
    """The last `memory` steps, newest first, for one vehicle or a batch of them.

    With `rate_error_integral` in the spec it also keeps the integrator state, one per
    batch row, and writes it into each step it stores.
    """

    def __init__(self, spec: ObservationSpec, batch_shape: tuple[int, ...] = ()) -> None:
        self.spec = spec
        self._buf = np.zeros((*batch_shape, spec.memory, spec.step_size), dtype=np.float32)
        self._cols = spec.integral_slice()
        self._integral = np.zeros((*batch_shape, FIELD_SIZES[INTEGRAL]), dtype=np.float32)

    def _integrate(self, step: np.ndarray, restart: bool) -> np.ndarray:
        """`step` with its integral columns replaced by the updated state (a copy)."""
        if self._cols is None:
            return step
        lam = np.float32(self.spec.integral_leak)
        carried = np.float32(0.0) if restart else lam * self._integral
        self._integral[...] = carried + (np.float32(1.0) - lam) * step[..., self._cols]
        out = np.array(step, dtype=np.float32, copy=True)
        out[..., self._cols] = self._integral
        return out

    def reset(self, step: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """Fill the whole history with one step (the episode start); `mask` picks batch rows."""
        if mask is None:
            step = self._integrate(step, True)
            self._buf[...] = step[..., None, :]
        else:
            kept = self._integral.copy()
            step = self._integrate(step, True)
            self._integral[~mask] = kept[~mask]
            self._buf[mask] = step[mask][..., None, :]
        return self.observation()

    def push(self, step: np.ndarray) -> np.ndarray:
        step = self._integrate(step, False)
        if self.spec.memory > 1:
            self._buf[..., 1:, :] = self._buf[..., :-1, :]
        self._buf[..., 0, :] = step
        return self.observation()

    def observation(self) -> np.ndarray:
        return self._buf.reshape(*self._buf.shape[:-2], self.spec.size).copy()
