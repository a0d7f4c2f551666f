"""The neural rate controller: an ONNX policy run by onnxruntime every tick.

The model carries its contract in metadata (written by `fcemu export`): the observation
spec, the action mapping and the loop rate it was trained at. The firmware builds the
observation with `firmware.observation` from that spec and refuses a model whose
contract it cannot honour, with a message that says what differs.

Containment, as documented for users: actions are clipped to [-1, 1] as in training; a
non-finite action raises `PolicyOutputError`, and the flight loop hands that tick to
its fallback controller (the PID) and counts the fault. Non-finite sensor input never
reaches the model.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import onnxruntime as ort

from firmware.action import ACTION_MAPPINGS, action_to_pwm
from firmware.controller import RateSetpoint
from firmware.observation import OBS_VERSION, ObservationHistory, ObservationSpec, observe_step
from firmware.sensors import SensorFrame

META_PREFIX = "fcemu."
REQUIRED_META = ("observation", "action_mapping", "loop_rate_hz")


class PolicyContractError(ValueError):
    """The ONNX file is not a policy this firmware can fly."""


class PolicyOutputError(RuntimeError):
    """The policy produced something that must not reach the motors."""


def read_metadata(path: str | Path) -> dict[str, str]:
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return _fcemu_metadata(session)


def _fcemu_metadata(session: ort.InferenceSession) -> dict[str, str]:
    raw = session.get_modelmeta().custom_metadata_map
    return {k[len(META_PREFIX):]: v for k, v in raw.items() if k.startswith(META_PREFIX)}


def _session(path: Path) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1  # one thread: a tiny MLP loses more to thread hand-off than it gains
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


class NeuralRateController:
    """Runs an exported policy; see the module docstring for what it refuses and contains."""

    def __init__(self, path: str | Path, loop_rate_hz: float | None = None) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"no policy file {self.path}")
        try:
            self._session = _session(self.path)
        except Exception as exc:  # onnxruntime raises several unrelated types for a bad file
            raise PolicyContractError(f"{self.path}: not a loadable ONNX model ({exc})") from exc
        self.metadata = _fcemu_metadata(self._session)
        self.spec, self.action_mapping, self.trained_rate_hz = self._check_contract(loop_rate_hz)
        self.name = f"neural:{self.path.stem}"
        # One vehicle is a batch of one: the step and the history are preallocated and the
        # history's buffer is bound as the model's input, so a tick allocates next to nothing.
        self._history = ObservationHistory(self.spec, (1,))
        self._fresh = True
        self._step = self._history.staging
        self._step_values = self._step.reshape(-1)  # a view of the same memory
        self._output = np.zeros((1, 4), dtype=np.float32)
        self._binding = self._bind(self._history.view)
        self._infer_input = np.zeros((1, self.spec.size), dtype=np.float32)
        self._infer_binding = self._bind(self._infer_input)

    def _bind(self, observation: np.ndarray) -> ort.IOBinding:
        binding = self._session.io_binding()
        binding.bind_cpu_input(self._input_name, observation)
        binding.bind_output(self._output_name, "cpu", element_type=np.float32, shape=(1, 4),
                            buffer_ptr=self._output.ctypes.data)
        return binding

    def _check_contract(self, loop_rate_hz: float | None) -> tuple[ObservationSpec, str, float]:
        where = str(self.path)
        missing = [k for k in REQUIRED_META if k not in self.metadata]
        if missing:
            raise PolicyContractError(
                f"{where}: metadata lacks {', '.join(META_PREFIX + k for k in missing)}; "
                "export policies with `fcemu export`")
        try:
            spec = ObservationSpec.from_json(self.metadata["observation"])
        except (ValueError, TypeError, KeyError) as exc:
            raise PolicyContractError(f"{where}: observation spec not understood ({exc})") from exc
        if spec.version != OBS_VERSION:
            raise PolicyContractError(f"{where}: observation version {spec.version}, this firmware "
                                      f"builds version {OBS_VERSION}")
        mapping = self.metadata["action_mapping"]
        if mapping not in ACTION_MAPPINGS:
            raise PolicyContractError(
                f"{where}: action mapping {mapping!r} unknown (known: {ACTION_MAPPINGS})")
        inputs, outputs = self._session.get_inputs(), self._session.get_outputs()
        if len(inputs) != 1 or len(outputs) < 1:
            raise PolicyContractError(f"{where}: expected one input and one output, found "
                                      f"{len(inputs)} and {len(outputs)}")
        in_shape, out_shape = inputs[0].shape, outputs[0].shape
        if len(in_shape) != 2 or in_shape[1] != spec.size:
            raise PolicyContractError(f"{where}: input shape {in_shape} does not match the observation "
                                      f"spec (batch, {spec.size}) = memory {spec.memory} × {spec.step_size}")
        if len(out_shape) != 2 or out_shape[1] != 4:
            raise PolicyContractError(f"{where}: output shape {out_shape}, expected (batch, 4) motor actions")
        if inputs[0].type != "tensor(float)" or outputs[0].type != "tensor(float)":
            raise PolicyContractError(f"{where}: input/output must be float32 tensors")
        trained_rate = float(self.metadata["loop_rate_hz"])
        if loop_rate_hz is not None and abs(trained_rate - loop_rate_hz) > 1e-6:
            raise PolicyContractError(f"{where}: trained for a {trained_rate:.0f} Hz loop, asked to run at "
                                      f"{loop_rate_hz:.0f} Hz")
        self._input_name, self._output_name = inputs[0].name, outputs[0].name
        return spec, mapping, trained_rate

    def describe(self) -> dict[str, object]:
        meta = {k: v for k, v in self.metadata.items() if k != "observation"}
        return {"path": str(self.path), "observation": json.loads(self.metadata["observation"]), **meta}

    def reset(self) -> None:
        self._fresh = True

    def infer(self, observation: np.ndarray) -> np.ndarray:
        """Raw policy output for one observation (no clipping, no checks); the history is kept."""
        self._infer_input[0] = observation
        self._session.run_with_iobinding(self._infer_binding)
        return self._output[0]

    def update(self, setpoint: RateSetpoint, frame: SensorFrame, dt: float) -> np.ndarray:
        observe_step(self.spec, setpoint.rates, frame.gyro, frame.rotor_speed, out=self._step_values)
        if not all(map(math.isfinite, self._step_values.tolist())):  # the step holds every input read
            raise PolicyOutputError("non-finite sensor frame or setpoint; the policy was not run")
        if self._fresh:
            self._history.start(self._step)
            self._fresh = False
        else:
            self._history.record(self._step)
        self._session.run_with_iobinding(self._binding)
        action = self._output[0]
        if not all(map(math.isfinite, action.tolist())):
            raise PolicyOutputError(f"policy output {action} is not finite")
        return action_to_pwm(self.action_mapping, action, setpoint.throttle)
