"""The neural rate controller: an ONNX policy run by onnxruntime every tick.

The model carries its contract in metadata (written by `fcemu export`): the observation
spec, the action mapping and the loop rate it was trained at. The firmware builds the
observation with `firmware.observation` from that spec and refuses a model whose
contract (`firmware.contract`) it cannot honour, with a message that says what differs.

Containment, as documented for users: actions are clipped to [-1, 1] as in training; a
non-finite action raises `PolicyOutputError`, and the flight loop hands that tick to
its fallback controller (the PID) and counts the fault. Non-finite sensor input never
reaches the model.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import onnxruntime as ort

from fcemu.firmware.action import action_to_pwm, motor_output
from fcemu.firmware.airframe_spec import AirframeSpec
from fcemu.firmware.contract import META_PREFIX, PolicyContract, PolicyContractError
from fcemu.firmware.controller import RateSetpoint
from fcemu.firmware.observation import ObservationHistory, observe_step
from fcemu.firmware.sensors import SensorFrame

__all__ = ["META_PREFIX", "NeuralRateController", "PolicyContractError", "PolicyOutputError", "read_metadata"]


class PolicyOutputError(RuntimeError):
    """The policy produced something that must not reach the motors."""


def read_metadata(path: str | Path) -> dict[str, str]:
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return _fcemu_metadata(session)


def _fcemu_metadata(session: ort.InferenceSession) -> dict[str, str]:
    raw = session.get_modelmeta().custom_metadata_map
    return {k[len(META_PREFIX):]: v for k, v in raw.items() if k.startswith(META_PREFIX)}


def _first_line(exc: BaseException, limit: int = 200) -> str:
    text = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
    return text if len(text) <= limit else f"{text[:limit - 1]}…"


def _session(path: Path) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1  # one thread: a tiny MLP loses more to thread hand-off than it gains
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


class NeuralRateController:
    """Runs an exported policy; see the module docstring for what it refuses and contains."""

    def __init__(self, path: str | Path, loop_rate_hz: float | None = None,
                 airframe: AirframeSpec | None = None) -> None:
        """`airframe`: the one it will fly; refused outside the policy's envelope (None: not checked)."""
        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"no policy file {self.path}")
        try:
            self._session = _session(self.path)
        except Exception as exc:  # onnxruntime raises several unrelated types for a bad file
            raise PolicyContractError(f"{self.path}: not a loadable ONNX model ({_first_line(exc)})") from exc
        self.metadata = _fcemu_metadata(self._session)
        self.contract = PolicyContract.from_metadata(self.metadata, str(self.path), loop_rate_hz)
        self.contract.check_graph(self._session.get_inputs(), self._session.get_outputs(), str(self.path))
        if airframe is not None:
            self.contract.check_airframe(airframe, str(self.path))
        self.spec, self.action_mapping = self.contract.observation, self.contract.action_mapping
        if airframe is not None:
            self.spec = self.spec.for_airframe(airframe.max_rotor_speed)
        # a `loop_delay` field's ticks: the airframe's configured delays (none given: 0, a nominal twin's)
        self.loop_delay = float(airframe.loop_delay_ticks) if airframe is not None else 0.0
        self.trained_rate_hz = self.contract.loop_rate_hz
        self._input_name = self._session.get_inputs()[0].name
        self._output_name = self._session.get_outputs()[0].name
        self.name = f"neural:{self.path.stem}"
        # One vehicle is a batch of one: the step and the history are preallocated and the
        # history's buffer is bound as the model's input, so a tick allocates next to nothing.
        self._history = ObservationHistory(self.spec, (1,))
        self._fresh = True
        self._motor_output: np.ndarray | None = None  # u of the previous tick, for a spec that reads it
        self._step = self._history.staging
        self._step_values = self._step.reshape(-1)  # a view of the same memory
        self._output = np.zeros((1, 4), dtype=np.float32)
        self._binding = self._bind(self._history.view)
        self._infer_input = np.zeros((1, self.spec.size), dtype=np.float32)
        self._infer_binding = self._bind(self._infer_input)
        self._probe()

    def _bind(self, observation: np.ndarray) -> ort.IOBinding:
        binding = self._session.io_binding()
        binding.bind_cpu_input(self._input_name, observation)
        binding.bind_output(self._output_name, "cpu", element_type=np.float32, shape=(1, 4),
                            buffer_ptr=self._output.ctypes.data)
        return binding

    def _probe(self) -> None:
        """Run the model once on observations from its flight range: it must run and answer in range."""
        probe = self.contract.probe_observations()
        actions = np.empty((len(probe), 4))
        try:
            for i, obs in enumerate(probe):  # one at a time, through the binding the loop uses
                actions[i] = self.infer(obs)
        except Exception as exc:  # onnxruntime raises several unrelated types for a graph that cannot run
            raise PolicyContractError(f"{self.path}: the model does not run ({_first_line(exc)})") from exc
        self.contract.check_outputs(actions, str(self.path))

    def reset(self) -> None:
        self._fresh = True
        self._motor_output = None

    def infer(self, observation: np.ndarray) -> np.ndarray:
        """Raw policy output for one observation (no clipping, no checks); the history is kept."""
        self._infer_input[0] = observation
        self._session.run_with_iobinding(self._infer_binding)
        return self._output[0]

    def update(self, setpoint: RateSetpoint, frame: SensorFrame, dt: float) -> np.ndarray:
        observe_step(self.spec, setpoint.rates, frame.gyro, frame.rotor_speed, out=self._step_values,
                     motor_output=self._motor_output, loop_delay=self.loop_delay)
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
        pwm = action_to_pwm(self.action_mapping, action, setpoint.throttle)
        if self.spec.reads_motor_output:
            self._motor_output = motor_output(pwm)
        return pwm
