"""Evaluation traces: what a controller did over a set of episodes, saved as npz.

Arrays (DESIGN.md, `--save-traces`): `t` (T,) seconds, `setpoint` (N,T,3) and `rate`
(N,T,3) FRD rad/s, `pwm` (N,T,4) µs in Betaflight Quad X motor order. Index k of
every array is the same instant: the command in force and the rate measured at t[k].
Metadata (controller, seed, task, anything else JSON-serialisable) is stored as one
JSON string, so loading never needs pickle. Inflight-task traces start with the warm-up
at hover (t < 0); the step is at t = 0 (`Traces.step_window`).
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fcemu.sim_bridge.tasks import EVAL_TASKS

TASKS = EVAL_TASKS
_T_EPS = 1e-9  # s
_ARRAYS = ("t", "setpoint", "rate", "pwm")


class TracesError(ValueError):
    """A traces object or file that does not have the documented layout."""


@dataclass(frozen=True, eq=False)
class Traces:
    t: np.ndarray  # (T,) s
    setpoint: np.ndarray  # (N,T,3) rad/s
    rate: np.ndarray  # (N,T,3) rad/s
    pwm: np.ndarray  # (N,T,4) µs
    controller: str = ""
    seed: int | None = None
    task: str = "episodic"
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in _ARRAYS:
            value = np.asarray(getattr(self, name))
            if not np.issubdtype(value.dtype, np.number) or np.iscomplexobj(value):
                raise TracesError(f"traces: {name} must be a real numeric array, got dtype {value.dtype}")
            object.__setattr__(self, name, value)
        t = self.t
        if t.ndim != 1 or t.shape[0] < 2:
            raise TracesError(f"traces: t must have shape (T,) with T >= 2, got {t.shape}")
        n_steps = t.shape[0]
        n_ep = None
        for name, width in (("setpoint", 3), ("rate", 3), ("pwm", 4)):
            arr = getattr(self, name)
            if arr.ndim != 3 or arr.shape[1:] != (n_steps, width) or arr.shape[0] < 1:
                raise TracesError(f"traces: {name} must have shape (N, {n_steps}, {width}), got {arr.shape}")
            if n_ep is not None and arr.shape[0] != n_ep:
                raise TracesError(f"traces: {name} has {arr.shape[0]} episodes, setpoint has {n_ep}")
            n_ep = arr.shape[0]
        for name in _ARRAYS:
            if not np.all(np.isfinite(getattr(self, name))):
                raise TracesError(f"traces: {name} contains NaN or infinite values")
        if not np.all(np.diff(t) > 0):
            raise TracesError("traces: t must be strictly increasing")
        if self.task not in TASKS:
            raise TracesError(f"traces: task must be one of {TASKS}, got {self.task!r}")

    @property
    def n_episodes(self) -> int:
        return int(self.setpoint.shape[0])

    @property
    def dt(self) -> float:
        return float(self.t[1] - self.t[0])

    def episode(self, i: int) -> Traces:
        """Episode i alone, as an N = 1 traces object."""
        sl = slice(i, i + 1) if i >= 0 else slice(i, i + 1 or None)
        return Traces(self.t, self.setpoint[sl], self.rate[sl], self.pwm[sl],
                      self.controller, self.seed, self.task, dict(self.extra))

    def step_window(self) -> Traces:
        """The samples from t = 0 on: the inflight task without its warm-up (others unchanged)."""
        k0 = int(np.searchsorted(self.t, -_T_EPS))
        if k0 == 0:
            return self
        return Traces(self.t[k0:], self.setpoint[:, k0:], self.rate[:, k0:], self.pwm[:, k0:],
                      self.controller, self.seed, self.task, dict(self.extra))

    def metadata(self) -> dict[str, Any]:
        return {"controller": self.controller, "seed": self.seed, "task": self.task, **self.extra}


def save_traces(path: str | os.PathLike[str], traces: Traces) -> Path:
    """Write `traces` as a compressed npz at `path` (".npz" appended if missing)."""
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    meta = json.dumps(traces.metadata(), allow_nan=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, t=traces.t, setpoint=traces.setpoint, rate=traces.rate, pwm=traces.pwm,
                        meta=np.array(meta))
    return path


def load_traces(path: str | os.PathLike[str]) -> Traces:
    """Read an npz written by `save_traces`; raises TracesError naming what is wrong."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in _ARRAYS if k not in data.files]
            if missing:
                raise TracesError(f"{path}: not a traces file, missing arrays {missing} (has {data.files})")
            arrays = {k: data[k] for k in _ARRAYS}
            meta_raw = str(data["meta"][()]) if "meta" in data.files else "{}"
    except (OSError, zipfile.BadZipFile, EOFError) as exc:
        raise TracesError(f"{path}: cannot read as npz: {exc}") from exc
    except ValueError as exc:
        if isinstance(exc, TracesError):
            raise
        raise TracesError(f"{path}: cannot read as npz: {exc}") from exc
    try:
        meta = json.loads(meta_raw)
    except json.JSONDecodeError as exc:
        raise TracesError(f"{path}: metadata is not valid JSON: {exc}") from exc
    if not isinstance(meta, dict):
        raise TracesError(f"{path}: metadata must be a JSON object")
    controller = meta.pop("controller", "") or ""
    seed = meta.pop("seed", None)
    task = meta.pop("task", "episodic")
    try:
        return Traces(**arrays, controller=str(controller), seed=None if seed is None else int(seed),
                      task=str(task), extra=meta)
    except TracesError as exc:
        raise TracesError(f"{path}: {exc}") from None
