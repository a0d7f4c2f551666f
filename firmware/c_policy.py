"""A policy exported as C (`fcemu export P.onnx --target c --out DIR`) flown through ctypes.

`--controller DIR` loads DIR/libfcemu_policy.so, the host build of the exported sources,
and calls `fcemu_policy_step` each tick: the C observation, network and PWM mapping a
flight controller would run, in float32. Containment as for the ONNX policy: a
non-finite input or output raises `PolicyOutputError` and the loop flies its fallback.
"""

from __future__ import annotations

import ctypes
import json
from pathlib import Path

import numpy as np

from fcemu.firmware.airframe_spec import AirframeSpec
from fcemu.firmware.contract import PolicyContract
from fcemu.firmware.controller import RateSetpoint
from fcemu.firmware.neural import PolicyContractError, PolicyOutputError
from fcemu.firmware.sensors import SensorFrame

LIBRARY = "libfcemu_policy.so"
CONTRACT = "contract.json"
_NONFINITE_INPUT, _NONFINITE_OUTPUT = 1, 2


def is_c_policy_dir(spec: str) -> bool:
    return (Path(spec) / LIBRARY).is_file() or (Path(spec) / "fcemu_policy.h").is_file()


class CPolicyController:
    """Runs the exported C policy; one state buffer per instance, so instances are independent."""

    def __init__(self, directory: str | Path, loop_rate_hz: float | None = None,
                 airframe: AirframeSpec | None = None) -> None:
        self.path = Path(directory)
        lib_path, contract_path = self.path / LIBRARY, self.path / CONTRACT
        if not lib_path.is_file() or not contract_path.is_file():
            raise PolicyContractError(f"{self.path}: no {LIBRARY} and {CONTRACT}; write them with "
                                      f"`fcemu export POLICY.onnx --target c --out {self.path}`")
        try:
            metadata = json.loads(contract_path.read_text())["metadata"]
        except (OSError, ValueError, RecursionError, TypeError, KeyError) as exc:
            raise PolicyContractError(f"{contract_path}: not a contract written by `fcemu export` "
                                      f"({type(exc).__name__}: {str(exc)[:80]})") from None
        if not isinstance(metadata, dict) or not all(isinstance(v, str) for v in metadata.values()):
            raise PolicyContractError(f"{contract_path}: metadata is not a table of strings")
        self.metadata: dict[str, str] = metadata
        contract = PolicyContract.from_metadata(self.metadata, str(self.path), loop_rate_hz)
        if airframe is not None:
            contract.check_airframe(airframe, str(self.path))
        trained_rate = contract.loop_rate_hz
        try:
            self._lib = ctypes.CDLL(str(lib_path.resolve()))
        except OSError as exc:
            raise PolicyContractError(f"{lib_path}: cannot load ({exc})") from exc
        f32p = ctypes.POINTER(ctypes.c_float)
        self._step = self._lib.fcemu_policy_step
        self._step.argtypes = [ctypes.c_void_p, f32p, f32p, f32p, ctypes.c_float, f32p]
        self._step.restype = ctypes.c_int
        self._lib.fcemu_policy_reset.argtypes = [ctypes.c_void_p]
        self._state = ctypes.create_string_buffer(self._lib.fcemu_policy_state_bytes())
        if airframe is not None:  # as NeuralRateController reads them; none: 0 ticks, the trained top speed
            self._lib.fcemu_policy_configure.argtypes = [ctypes.c_void_p, ctypes.c_float, ctypes.c_float]
            self._lib.fcemu_policy_configure(self._state, float(airframe.loop_delay_ticks),
                                             float(airframe.max_rotor_speed))
        self._setpoint, self._gyro = (ctypes.c_float * 3)(), (ctypes.c_float * 3)()
        self._rotor, self._pwm = (ctypes.c_float * 4)(), (ctypes.c_float * 4)()
        self.trained_rate_hz = trained_rate
        self.name = f"c:{self.path.name}"
        self.reset()

    def reset(self) -> None:
        self._lib.fcemu_policy_reset(self._state)

    def update(self, setpoint: RateSetpoint, frame: SensorFrame, dt: float) -> np.ndarray:
        self._setpoint[:] = setpoint.rates.tolist()
        self._gyro[:] = frame.gyro.tolist()
        self._rotor[:] = frame.rotor_speed.tolist()
        status = self._step(self._state, self._setpoint, self._gyro, self._rotor, setpoint.throttle,
                            self._pwm)
        if status == _NONFINITE_INPUT:
            raise PolicyOutputError("non-finite sensor frame or setpoint; the policy was not run")
        if status == _NONFINITE_OUTPUT:
            raise PolicyOutputError("the C policy's output is not finite")
        return np.array(self._pwm[:], dtype=np.float64)
