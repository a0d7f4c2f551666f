"""The exported C policy as a controller (`--controller DIR`): same PWM as the ONNX policy,
same containment, and it flies the evaluation loop with the ONNX policy's traces."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from fcemu.evaluation.runner import EvalConfig, run_controller
from fcemu.firmware.c_policy import CPolicyController
from fcemu.firmware.controller import RateSetpoint
from fcemu.firmware.controllers import DEFAULT_POLICY, load_controller
from fcemu.firmware.neural import NeuralRateController, PolicyContractError, PolicyOutputError
from fcemu.firmware.sensors import SensorFrame

pytestmark = pytest.mark.no_wall_clock

SHIPPED = DEFAULT_POLICY


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> Path:
    from tests.export.mcu_tools import require_codegen

    require_codegen()
    from fcemu.export.c.build import export_c

    out = tmp_path_factory.mktemp("c_policy")
    export_c(SHIPPED, out, parity_samples=1000)
    return out


def _frame(rng: np.random.Generator, k: int) -> tuple[RateSetpoint, SensorFrame]:
    setpoint = RateSetpoint(rng.uniform(-5, 5, 3), float(rng.uniform(0.3, 0.9)))
    gyro, rotor = rng.uniform(-5, 5, 3), rng.uniform(300, 1000, 4)
    frame = SensorFrame(k * 1000, gyro, np.array([0.0, 0.0, -9.81]), rotor)
    return setpoint, frame


def test_same_pwm_as_the_onnx_policy(exported: Path) -> None:
    c_policy, onnx_policy = load_controller(str(exported)), NeuralRateController(SHIPPED)
    assert isinstance(c_policy, CPolicyController)
    rng = np.random.default_rng(0)
    worst = 0.0
    for k in range(2000):
        setpoint, frame = _frame(rng, k)
        ours, theirs = c_policy.update(setpoint, frame, 1e-3), onnx_policy.update(setpoint, frame, 1e-3)
        assert ((ours >= 1000.0) & (ours <= 2000.0)).all()
        worst = max(worst, float(np.max(np.abs(ours - theirs))))
    assert worst < 0.05  # µs: float32 contract code and network against onnxruntime's


def test_non_finite_input_is_contained(exported: Path) -> None:
    policy = CPolicyController(exported)
    setpoint, frame = _frame(np.random.default_rng(1), 0)
    bad = frame._replace(gyro=np.array([0.0, math.nan, 0.0]))
    with pytest.raises(PolicyOutputError, match="non-finite sensor"):
        policy.update(setpoint, bad, 1e-3)
    with pytest.raises(PolicyOutputError, match="non-finite sensor"):
        policy.update(RateSetpoint(setpoint.rates, math.inf), frame, 1e-3)
    assert np.isfinite(policy.update(setpoint, frame, 1e-3)).all()  # and it keeps flying


def test_refuses_a_directory_without_the_build(tmp_path: Path, exported: Path) -> None:
    (tmp_path / "fcemu_policy.h").write_text((exported / "fcemu_policy.h").read_text())
    with pytest.raises(PolicyContractError, match=r"fcemu export POLICY\.onnx --target c"):
        load_controller(str(tmp_path))
    with pytest.raises(PolicyContractError, match="trained for a 1000 Hz loop"):
        CPolicyController(exported, loop_rate_hz=500.0)
    with pytest.raises(ValueError, match="unknown controller"):
        load_controller(str(tmp_path / "nothing_here"))


@pytest.mark.parametrize("contract", ["{not json", "[]", '{"other": 1}', '{"metadata": {"observation": 3}}'])
def test_refuses_a_contract_that_is_not_one(tmp_path: Path, exported: Path, contract: str) -> None:
    for name in ("fcemu_policy.h", "libfcemu_policy.so"):
        (tmp_path / name).write_bytes((exported / name).read_bytes())
    (tmp_path / "contract.json").write_text(contract)
    with pytest.raises(PolicyContractError, match=r"contract\.json"):
        load_controller(str(tmp_path))


def test_flies_the_evaluation_like_the_onnx_policy(exported: Path) -> None:
    cfg = EvalConfig(episodes=3, seed=7)
    ours = run_controller(str(exported), cfg, progress=False)
    theirs = run_controller(str(SHIPPED), cfg, progress=False)
    assert ours.extra["controller_faults"] == 0
    assert np.max(np.abs(ours.rate - theirs.rate)) < 1e-3  # rad/s over 3 s of closed-loop flight
    assert np.max(np.abs(ours.pwm - theirs.pwm)) < 1.0  # µs
