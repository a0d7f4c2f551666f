"""The generated contract C against `firmware.observation` and `firmware.action`, compiled
for the host: a spec with memory 3, the leaky integral and the leaky RMS, both action mappings;
one with the previous tick's motor outputs, flown against the ONNX policy."""

from __future__ import annotations

import ctypes
import shutil
from functools import partial
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from fcemu.export.c.build import compile_host, export_c
from fcemu.export.c.contract import Contract, contract_sources
from fcemu.firmware.action import action_to_pwm
from fcemu.firmware.c_policy import CPolicyController
from fcemu.firmware.controller import RateSetpoint
from fcemu.firmware.neural import NeuralRateController
from fcemu.firmware.observation import (
    FIELDS,
    INTEGRAL,
    LOOP_DELAY,
    MOTOR_OUTPUT,
    RMS,
    ObservationHistory,
    ObservationSpec,
    observe_step,
)
from fcemu.firmware.sensors import SensorFrame
from tests.export.mcu_tools import require_codegen

pytestmark = pytest.mark.no_wall_clock

TOP = 1100.0  # rad/s: the top rotor speed the tests' observations are scaled for
Spec = partial(ObservationSpec, max_rotor_speed=TOP)

SPEC = Spec(memory=3, fields=("rate_error", "rotor_speed", INTEGRAL, RMS), integral_leak=0.99,
                       rms_leak=0.95)
F32P = ctypes.POINTER(ctypes.c_float)


def _policy(path: Path, spec: ObservationSpec, mapping: str) -> None:
    rng = np.random.default_rng(3)
    w = numpy_helper.from_array(rng.standard_normal((4, spec.size)).astype(np.float32) * 0.3, "w")
    b = numpy_helper.from_array(np.zeros(4, np.float32), "b")
    nodes = [helper.make_node("Gemm", ["observation", "w", "b"], ["pre"], transB=1),
             helper.make_node("Tanh", ["pre"], ["action"])]
    graph = helper.make_graph(
        nodes, "g", [helper.make_tensor_value_info("observation", TensorProto.FLOAT, ["batch", spec.size])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", 4])], [w, b])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    onnx.helper.set_model_props(model, {"fcemu.observation": spec.to_json(), "fcemu.action_mapping": mapping,
                                        "fcemu.loop_rate_hz": "1000.0"})
    onnx.save(model, path)


def _load(lib_path: Path) -> ctypes.CDLL:
    lib = ctypes.CDLL(str(lib_path))
    lib.fcemu_observe.argtypes = [ctypes.c_void_p, F32P, F32P, F32P, F32P]
    lib.fcemu_action_to_pwm.argtypes = [F32P, ctypes.c_float, F32P]
    lib.fcemu_policy_reset.argtypes = [ctypes.c_void_p]
    return lib


@pytest.fixture(scope="module")
def libraries(tmp_path_factory) -> dict[str, ctypes.CDLL]:
    require_codegen()
    root = tmp_path_factory.mktemp("contract")
    _policy(root / "p.onnx", SPEC, "throttle")
    export_c(root / "p.onnx", root / "throttle", parity_samples=1000)
    gymfc = root / "gymfc"  # the same network and golden vectors, the other mapping's contract code
    gymfc.mkdir()
    for name in ("fcemu_net.c", "fcemu_tanh.h", "fcemu_golden.c"):
        shutil.copy(root / "throttle" / name, gymfc / name)
    for name, text in contract_sources(Contract(SPEC, "gymfc", 1000.0)).items():
        (gymfc / name).write_text(text)
    compile_host(gymfc)
    return {m: _load(root / m / "libfcemu_policy.so") for m in ("throttle", "gymfc")}


def _ptr(a: np.ndarray):
    return a.ctypes.data_as(F32P)


def test_observation_history_integral_and_rms_match_python(libraries) -> None:
    lib = libraries["throttle"]
    state = ctypes.create_string_buffer(lib.fcemu_policy_state_bytes())
    rng = np.random.default_rng(0)
    history = ObservationHistory(SPEC)
    obs_c = np.zeros(SPEC.size, np.float32)
    for _ in range(3):
        lib.fcemu_policy_reset(state)
        for k in range(50):
            sp, gyro = (rng.uniform(-6, 6, 3).astype(np.float32) for _ in range(2))
            rotor = rng.uniform(0, 1100, 4).astype(np.float32)
            step = observe_step(SPEC, *(x.astype(np.float64) for x in (sp, gyro, rotor)))
            expected = history.reset(step) if k == 0 else history.push(step)
            lib.fcemu_observe(state, _ptr(sp), _ptr(gyro), _ptr(rotor), _ptr(obs_c))
            np.testing.assert_allclose(obs_c, expected, rtol=1e-6, atol=1e-6)  # float32 vs float64


@pytest.mark.parametrize("mapping", ["throttle", "gymfc"])
def test_action_to_pwm_matches_python(libraries, mapping: str) -> None:
    lib = libraries[mapping]
    rng = np.random.default_rng(1)
    actions = rng.uniform(-1.5, 1.5, (2000, 4)).astype(np.float32)
    throttles = rng.uniform(-0.2, 1.2, 2000).astype(np.float32)
    pwm = np.zeros(4, np.float32)
    ours = np.zeros((2000, 4))
    for n in range(2000):
        lib.fcemu_action_to_pwm(_ptr(actions[n]), float(throttles[n]), _ptr(pwm))
        ours[n] = pwm
    expected = action_to_pwm(mapping, actions.astype(np.float64), throttles.astype(np.float64))
    np.testing.assert_allclose(ours, expected, atol=1e-3)  # µs; float32 against float64
    assert ours.min() >= 1000.0 and ours.max() <= 2000.0


@pytest.mark.parametrize("mapping", ["throttle", "gymfc"])
def test_motor_output_field_feeds_back_the_last_pwm_as_the_onnx_policy_does(tmp_path, mapping: str) -> None:
    """`fcemu_policy_step` keeps the tick's PWM for the next observation; at a reset the rotors'
    steady-state command. Fed back through the network, any difference grows: 400 ticks agree."""
    require_codegen()
    spec = Spec(memory=3, fields=(*FIELDS, MOTOR_OUTPUT))
    _policy(tmp_path / "p.onnx", spec, mapping)
    export_c(tmp_path / "p.onnx", tmp_path / "c", parity_samples=200)
    ours, theirs = CPolicyController(tmp_path / "c"), NeuralRateController(tmp_path / "p.onnx")
    _, worst = _side_by_side(ours, theirs, 400)
    assert worst < 0.05  # µs


def _side_by_side(ours, theirs, ticks: int) -> tuple[np.ndarray, float]:
    """Both controllers on the same random frames, both reset halfway: our PWM and the largest gap."""
    rng = np.random.default_rng(7)
    flown, worst = [], 0.0
    for k in range(ticks):
        if k == ticks // 2:
            ours.reset()
            theirs.reset()
        setpoint = RateSetpoint(rng.uniform(-3, 3, 3), float(rng.uniform(0.2, 0.8)))
        frame = SensorFrame(k * 1000, rng.uniform(-3, 3, 3), np.array([0.0, 0.0, -9.81]),
                            rng.uniform(0, 1100, 4))
        flown.append(ours.update(setpoint, frame, 1e-3))
        worst = max(worst, float(np.abs(flown[-1] - theirs.update(setpoint, frame, 1e-3)).max()))
    return np.array(flown), worst


def test_a_loop_delay_policy_reads_the_delay_its_airframe_is_configured_with(tmp_path) -> None:
    """The C state holds the configured delay across resets, as the ONNX policy's controller does;
    airframes of different delays fly the same frames differently, each alike in C and ONNX (none
    given: 0 ticks in both)."""
    from dataclasses import replace

    from fcemu.sim_bridge.airframe_spec import airframe_spec

    require_codegen()
    spec = Spec(memory=3, fields=(*FIELDS, LOOP_DELAY, MOTOR_OUTPUT))
    _policy(tmp_path / "p.onnx", spec, "throttle")
    export_c(tmp_path / "p.onnx", tmp_path / "c", parity_samples=200)
    iris = airframe_spec("iris_realistic")
    assert iris.loop_delay_ticks == 3  # ESC 1 + gyro 2
    outputs = []
    for airframe in (iris, replace(iris, loop_delay_ticks=0), None):
        flown, worst = _side_by_side(CPolicyController(tmp_path / "c", airframe=airframe),
                                     NeuralRateController(tmp_path / "p.onnx", airframe=airframe), 100)
        assert worst < 0.05  # µs
        outputs.append(flown)
    assert np.abs(outputs[0] - outputs[1]).max() > 1.0
    np.testing.assert_array_equal(outputs[1], outputs[2])


def test_a_policy_of_shares_of_the_top_rotor_speed_reads_the_top_speed_configured(tmp_path) -> None:
    """A policy trained across quads scales rotor speeds by the flown airframe's top speed, set once at
    boot in C as the ONNX policy's controller takes it from the airframe; quads of different top speeds
    fly the same frames differently, each alike in C and ONNX (none given: the trained airframe's)."""
    from dataclasses import replace

    from fcemu.sim_bridge.airframe_spec import airframe_spec

    require_codegen()
    spec = Spec(memory=2, fields=(*FIELDS, MOTOR_OUTPUT), per_airframe_rotor_speed=True)
    _policy(tmp_path / "p.onnx", spec, "throttle")
    export_c(tmp_path / "p.onnx", tmp_path / "c", parity_samples=200)
    iris = airframe_spec("iris")
    outputs = []
    for airframe in (replace(iris, max_rotor_speed=TOP / 2), replace(iris, max_rotor_speed=TOP), None):
        flown, worst = _side_by_side(CPolicyController(tmp_path / "c", airframe=airframe),
                                     NeuralRateController(tmp_path / "p.onnx", airframe=airframe), 100)
        assert worst < 0.05  # µs
        outputs.append(flown)
    assert np.abs(outputs[0] - outputs[1]).max() > 1.0
    np.testing.assert_allclose(outputs[1], outputs[2], atol=0.05)


def test_the_authority_estimate_in_c_is_the_python_one_across_a_reset(tmp_path) -> None:
    """The in-flight slope in C keeps its state per tick and starts over on reset, as the ONNX policy's
    controller does, on a quad whose top speed is configured (the rotor shares it reads)."""
    from dataclasses import replace

    from fcemu.firmware.observation import AUTHORITY, RATE
    from fcemu.sim_bridge.airframe_spec import airframe_spec

    require_codegen()
    spec = Spec(memory=2, fields=(*FIELDS, RATE, AUTHORITY), per_airframe_rotor_speed=True)
    _policy(tmp_path / "p.onnx", spec, "throttle")
    export_c(tmp_path / "p.onnx", tmp_path / "c", parity_samples=200)
    quad = replace(airframe_spec("iris"), max_rotor_speed=2 * TOP)
    ours, theirs = CPolicyController(tmp_path / "c", airframe=quad), NeuralRateController(tmp_path / "p.onnx",
                                                                                        airframe=quad)
    _, worst = _side_by_side(ours, theirs, 400)
    assert worst < 0.05  # µs
