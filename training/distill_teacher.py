"""`fcemu distill`'s teacher, and the one observation it and its student both read (columns of it)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

from fcemu.firmware.neural import META_PREFIX
from fcemu.firmware.observation import FIELD_DEFS, ObservationSpec
from fcemu.sim_bridge.env_config import DEFAULT_AIRFRAME


class DistillError(ValueError):
    """A teacher or a student that cannot be distilled, with the reason."""


class Teacher:
    """An exported policy in onnxruntime, and the contract its metadata carries."""

    def __init__(self, path: str | Path) -> None:
        try:
            self.session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own types for a missing or foreign file
            raise DistillError(f"{path}: cannot load as an ONNX policy ({exc})") from None
        meta = self.session.get_modelmeta().custom_metadata_map
        if META_PREFIX + "observation" not in meta:
            raise DistillError(f"{path}: no fcemu metadata; give a policy made by `fcemu export`")
        self.spec = ObservationSpec.from_json(meta[META_PREFIX + "observation"])
        self.action_mapping = meta[META_PREFIX + "action_mapping"]
        self.throttle = json.loads(meta.get(META_PREFIX + "throttle", "null"))
        # the airframe it was made for (exports before it was recorded: the Iris, the only one then)
        self.airframe = meta.get(META_PREFIX + "airframe", DEFAULT_AIRFRAME)
        self.input = self.session.get_inputs()[0].name

    def act(self, obs: np.ndarray) -> np.ndarray:
        return self.session.run(None, {self.input: obs})[0]


INVERSION = "inversion"  # the teacher that inverts the airframe's model (`training.inversion_teacher`)


def is_model_based(name: str) -> bool:
    """Whether the teacher reads the state rather than sensors it was trained on: privileged, it reads
    the truth, where a trained teacher reads its sensors as sampled (`fcemu distill --privileged`)."""
    return name == INVERSION or name.startswith(INVERSION + ":")


def make_teacher(name: str, airframe: str, privileged: bool = False, per_twin: bool = False) -> Any:
    """`inversion` (or `inversion:K`, its time constant in motor lags, `inversion:K:Z`, and its
    damping ratio, `inversion:K:Z:Y`, and the share of yaw it serves first, `inversion:K:Z:Y:J`, and
    its braking share; an empty field takes the default) for the model-based teacher of `airframe`
    (`privileged`: reading the truth; `per_twin`: of each twin's drawn airframe, `DrawnInversionTeacher`),
    else an exported policy's path."""
    if is_model_based(name):
        from fcemu.sim_bridge.airframe import load_airframe
        from fcemu.training.inversion_teacher import (
            BRAKING_SHARE,
            DAMPING,
            LAG_MULTIPLE,
            DrawnInversionTeacher,
            InversionTeacher,
        )

        fields = name.split(":")[1:]
        multiple, damping, yaw_first, braking = (*fields, "", "", "", "")[:4]
        try:
            if len(fields) > 4:
                raise ValueError("at most four fields follow `inversion`: K:Z:Y:J")
            if damping and not float(damping) > 0.0:
                raise ValueError(f"the damping ratio must be > 0, got {damping}")
            options = {"damping": float(damping) if damping else DAMPING, "reads_truth": privileged,
                       "yaw_first": float(yaw_first) if yaw_first else 0.0,
                       "braking": float(braking) if braking else BRAKING_SHARE}
            lag_multiple = float(multiple) if multiple else LAG_MULTIPLE

            def teacher_of(airframe: Any) -> InversionTeacher:
                return InversionTeacher(airframe, lag_multiple, **options)

            if per_twin:
                return DrawnInversionTeacher(teacher_of, load_airframe(airframe))
            return teacher_of(airframe)
        except ValueError as exc:
            raise DistillError(f"teacher {name!r}: {exc}") from None
    if per_twin:
        raise DistillError("a teacher per twin is the model-based one's (`inversion`); "
                           "a policy is one teacher")
    return Teacher(name)


def union_spec(teacher: ObservationSpec, student: ObservationSpec) -> ObservationSpec:
    """One observation holding both: the teacher's fields then the student's others, the longer history."""
    for leak in ("integral_leak", "rms_leak"):
        if getattr(teacher, leak) != getattr(student, leak):
            raise DistillError(f"the student's {leak} differs from the teacher's")
    return ObservationSpec(memory=max(teacher.memory, student.memory), rate_scale=teacher.rate_scale,
                           rotor_speed_scale=teacher.rotor_speed_scale,
                           fields=(*teacher.fields, *(f for f in student.fields if f not in teacher.fields)),
                           integral_leak=teacher.integral_leak, rms_leak=teacher.rms_leak)


def columns(spec: ObservationSpec, union: ObservationSpec) -> np.ndarray:
    """For each column of `spec`'s observation, its column in `union`'s (newest step first)."""
    offsets, start = {}, 0
    for name in union.fields:
        offsets[name] = start
        start += FIELD_DEFS[name].size
    return np.array([k * union.step_size + offsets[name] + j for k in range(spec.memory)
                     for name in spec.fields for j in range(FIELD_DEFS[name].size)])
