"""The neural controller's contract: what it flies, what it refuses, what it contains."""

from __future__ import annotations

from functools import partial

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from fcemu.firmware.action import action_to_pwm, gymfc_pwm, throttle_pwm
from fcemu.firmware.controller import RateSetpoint
from fcemu.firmware.loop import FlightLoop, ScriptedCommander
from fcemu.firmware.neural import META_PREFIX, NeuralRateController, PolicyContractError, PolicyOutputError
from fcemu.firmware.observation import (
    FIELDS,
    INTEGRAL,
    MOTOR_OUTPUT,
    ObservationHistory,
    ObservationSpec,
    observe_step,
)
from fcemu.firmware.sensors import SensorFrame
from fcemu.firmware.timing import LockstepClock
from fcemu.sim_bridge.env import EnvConfig, RateTask
from fcemu.sim_bridge.twin import Twin

TOP = 1100.0  # rad/s: the top rotor speed the tests' observations are scaled for
Spec = partial(ObservationSpec, max_rotor_speed=TOP)


def linear_policy(path, weight: np.ndarray, bias: np.ndarray, meta: dict[str, str] | None,
                  nan: bool = False) -> str:
    """action = obs @ weight + bias (optionally ·0/0 to poison it), with fcemu metadata."""
    n_in, n_out = weight.shape
    nodes = [helper.make_node("MatMul", ["observation", "W"], ["xw"]),
             helper.make_node("Add", ["xw", "b"], ["action" if not nan else "raw"])]
    inits = [numpy_helper.from_array(weight.astype(np.float32), "W"),
             numpy_helper.from_array(bias.astype(np.float32), "b")]
    if nan:
        nodes.append(helper.make_node("Div", ["raw", "zero"], ["ratio"]))
        nodes.append(helper.make_node("Mul", ["ratio", "zero"], ["action"]))
        inits.append(numpy_helper.from_array(np.zeros(1, np.float32), "zero"))
    graph = helper.make_graph(
        nodes, "policy",
        [helper.make_tensor_value_info("observation", TensorProto.FLOAT, ["batch", n_in])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", n_out])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=9)
    for k, v in (meta or {}).items():
        model.metadata_props.add(key=META_PREFIX + k, value=v)
    onnx.save(model, str(path))
    return str(path)


def meta(memory: int = 1, mapping: str = "gymfc", rate: float = 1000.0,
         spec: ObservationSpec | None = None) -> dict[str, str]:
    spec = spec or Spec(memory=memory)
    return {"observation": spec.to_json(), "action_mapping": mapping,
            "loop_rate_hz": str(rate), "algorithm": "ppo", "training_steps": "0", "seed": "0"}


def frame(gyro=(0.1, -0.2, 0.3), rotor=(500.0, 510.0, 520.0, 530.0)) -> SensorFrame:
    return SensorFrame(0, np.array(gyro, float), np.array([0, 0, -9.81]), np.array(rotor, float))


@pytest.fixture
def weight() -> np.ndarray:
    return np.random.default_rng(0).uniform(-0.5, 0.5, (7, 4))


def test_flies_the_shared_observation_and_action_mapping(tmp_path, weight):
    bias = np.array([0.1, -0.2, 0.3, 0.0])
    ctl = NeuralRateController(linear_policy(tmp_path / "p.onnx", weight, bias, meta()))
    sp = RateSetpoint(np.array([1.0, 2.0, -3.0]), 0.6)
    f = frame()
    obs = observe_step(ctl.spec, sp.rates, f.gyro, f.rotor_speed)
    expected = gymfc_pwm(obs.astype(np.float64) @ weight + bias)
    np.testing.assert_allclose(ctl.update(sp, f, 0.001), expected, rtol=0, atol=1e-3)


def test_throttle_mapping_uses_the_setpoint_collective(tmp_path, weight):
    path = linear_policy(tmp_path / "p.onnx", weight, np.zeros(4), meta(mapping="throttle"))
    ctl = NeuralRateController(path)
    sp = RateSetpoint(np.array([1.0, 0.0, 0.0]), 0.7)
    f = frame()
    action = observe_step(ctl.spec, sp.rates, f.gyro, f.rotor_speed).astype(np.float64) @ weight
    np.testing.assert_allclose(ctl.update(sp, f, 0.001), throttle_pwm(action, 0.7), atol=1e-3)


def test_memory_keeps_the_last_steps_newest_first(tmp_path):
    spec = Spec(memory=3)
    weight = np.zeros((spec.size, 4))
    weight[7, 0] = 1.0  # action[0] = the previous step's roll error (scaled)
    ctl = NeuralRateController(linear_policy(tmp_path / "p.onnx", weight, np.zeros(4), meta(memory=3)))
    sp = RateSetpoint(np.zeros(3), 0.5)
    first = ctl.update(sp, frame(gyro=(-1.0, 0, 0)), 0.001)
    second = ctl.update(sp, frame(gyro=(-2.0, 0, 0)), 0.001)
    assert first[0] == pytest.approx(gymfc_pwm(np.array(1.0 * spec.rate_scale)), abs=1e-3)  # history filled
    assert second[0] == pytest.approx(gymfc_pwm(np.array(1.0 * spec.rate_scale)), abs=1e-3)


def test_integral_field_integrates_the_error_across_ticks_and_restarts_on_reset(tmp_path):
    spec = Spec(fields=("rate_error", "rotor_speed", "rate_error_integral"), integral_leak=0.9)
    weight = np.zeros((spec.size, 4))
    weight[7, 0] = 1.0  # action[0] = the roll error's leaky integral
    ctl = NeuralRateController(linear_policy(tmp_path / "p.onnx", weight, np.zeros(4), meta(spec=spec)))
    sp = RateSetpoint(np.zeros(3), 0.5)
    e = 1.0 * spec.rate_scale
    outs = [ctl.update(sp, frame(gyro=(-1.0, 0, 0)), 0.001)[0] for _ in range(3)]
    expected = [0.1 * e, 0.19 * e, 0.271 * e]  # I_k = 0.9·I_{k-1} + 0.1·e, I_0 = 0.1·e
    np.testing.assert_allclose(outs, [gymfc_pwm(np.array(x)) for x in expected], atol=1e-3)
    ctl.reset()
    assert ctl.update(sp, frame(gyro=(-1.0, 0, 0)), 0.001)[0] == pytest.approx(outs[0], abs=1e-3)


@pytest.mark.parametrize(("shape", "metadata", "message"), [
    ((8, 4), meta(), "input shape"),
    ((7, 3), meta(), "output shape"),
    ((7, 4), {k: v for k, v in meta().items() if k != "observation"}, "metadata lacks"),
    ((7, 4), meta(mapping="rpm"), "action mapping"),
    ((7, 4), {**meta(), "observation": '{"memory": 1, "fields": ["attitude"], "version": 1}'},
     "observation spec"),
    ((7, 4), {**meta(), "observation": Spec().to_json().replace('"version": 1', '"version": 9')},
     "observation version"),
])
def test_refuses_a_model_it_cannot_fly(tmp_path, shape, metadata, message):
    path = linear_policy(tmp_path / "bad.onnx", np.zeros(shape), np.zeros(shape[1]), metadata)
    with pytest.raises(PolicyContractError, match=message):
        NeuralRateController(path)


def test_refuses_another_loop_rate_and_garbage(tmp_path, weight):
    path = linear_policy(tmp_path / "p.onnx", weight, np.zeros(4), meta(rate=1000.0))
    with pytest.raises(PolicyContractError, match="1000 Hz loop"):
        NeuralRateController(path, loop_rate_hz=4000.0)
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    with pytest.raises(PolicyContractError, match="not a loadable"):
        NeuralRateController(junk)


def test_nan_output_never_reaches_the_motors(tmp_path, weight):
    path = linear_policy(tmp_path / "nan.onnx", weight, np.zeros(4), meta(), nan=True)
    ctl = NeuralRateController(path)
    with pytest.raises(PolicyOutputError):
        ctl.update(RateSetpoint(np.zeros(3), 0.5), frame(), 0.001)

    class Hover:
        name = "pid"

        def reset(self) -> None: ...

        def update(self, setpoint, frame, dt):
            return np.full(4, 1500.0)

    twin = Twin(rig="rig")
    writes = []

    class Plant:
        def pwm_write(self, pwm):
            writes.append(np.array(pwm))
            return twin.step(pwm)

    loop = FlightLoop(Plant(), twin.reset(), {"main": ctl, "pid": Hover()},
                      ScriptedCommander([(0.0, (1, 0, 0), 0.5)], controller="main"), LockstepClock(),
                      fallback="pid")
    loop.run(0.05)
    assert all((w == 1500).all() for w in writes)
    assert sum(loop.faults.values()) == 50


def test_non_finite_sensor_input_is_not_fed_to_the_model(tmp_path, weight):
    ctl = NeuralRateController(linear_policy(tmp_path / "p.onnx", weight, np.zeros(4), meta()))
    with pytest.raises(PolicyOutputError, match="sensor"):
        ctl.update(RateSetpoint(np.zeros(3), 0.5), frame(gyro=(np.nan, 0, 0)), 0.001)
    with pytest.raises(PolicyOutputError):
        ctl.update(RateSetpoint(np.array([np.inf, 0, 0]), 0.5), frame(), 0.001)


@pytest.mark.parametrize("mapping", ["throttle", "gymfc"])
@pytest.mark.parametrize("spec", [Spec(), Spec(memory=3),
                                  Spec(fields=(*FIELDS, INTEGRAL), integral_leak=0.9)])
def test_flight_feeds_the_model_bit_for_bit_what_training_builds(tmp_path, mapping, spec):
    """One vehicle goes through the batched environment's observation and action code."""
    weight = np.random.default_rng(1).uniform(-0.5, 0.5, (spec.size, 4))
    path = linear_policy(tmp_path / "p.onnx", weight, np.array([0.3, -0.1, 0.05, 0.2]),
                         meta(mapping=mapping, spec=spec))
    ctl = NeuralRateController(path)
    training = ObservationHistory(spec, (2,))  # as BatchedRateEnv keeps it, for two copies
    rng = np.random.default_rng(4)
    for i in range(300):
        sp = RateSetpoint(rng.uniform(-6, 6, 3), float(rng.uniform(-0.1, 1.1)))
        f = frame(rng.uniform(-8, 8, 3), rng.uniform(0, 1100, 4))
        pwm = ctl.update(sp, f, 0.001)
        step = observe_step(spec, *(np.stack([x] * 2) for x in (sp.rates, f.gyro, f.rotor_speed)))
        obs = training.reset(step) if i == 0 else training.push(step)
        assert np.array_equal(ctl._history.view[0], obs[0])
        action = np.stack([ctl.infer(obs[0]).copy()] * 2)
        np.testing.assert_array_equal(pwm, action_to_pwm(mapping, action, np.full(2, sp.throttle))[0])


@pytest.mark.parametrize("mapping", ["throttle", "gymfc"])
def test_motor_output_in_flight_is_what_training_observes_after_the_same_outputs(tmp_path, mapping):
    """The controller's own previous PWM, as training's RateTask sees the PWM it applied; a
    reset starts again from the rotors' steady-state command."""
    spec = Spec(memory=2, fields=(*FIELDS, MOTOR_OUTPUT))
    weight = np.random.default_rng(2).uniform(-0.5, 0.5, (spec.size, 4))
    ctl = NeuralRateController(linear_policy(tmp_path / "p.onnx", weight, np.array([0.3, -0.1, 0.05, 0.2]),
                                             meta(mapping=mapping, spec=spec)))
    task = RateTask(EnvConfig(memory=2, action_mapping=mapping, obs_fields=spec.fields))
    assert task.spec == spec
    rng = np.random.default_rng(6)
    pwm = None
    for i in range(300):
        if i == 150:
            ctl.reset()
        sp = RateSetpoint(rng.uniform(-6, 6, 3), float(rng.uniform(0.1, 0.9)))
        f = frame(rng.uniform(-8, 8, 3), rng.uniform(0, 1100, 4))
        if i in (0, 150):
            obs = task.reset(sp.rates, f.gyro, f.rotor_speed)
        else:
            obs = task.step(sp.rates, f.gyro, f.gyro, f.rotor_speed, pwm)[0]
        new = ctl.update(sp, f, 0.001)
        assert np.array_equal(ctl._history.view[0], obs)
        if i not in (0, 150):
            np.testing.assert_allclose(obs[7:11], (pwm - 1000.0) / 1000.0, atol=1e-7)
        pwm = new
