"""The policies shipped in policies/: each passes the firmware's contract and flies as documented."""

from __future__ import annotations

from pathlib import Path

import pytest

from fcemu.evaluation.metrics import AXES, compute_metrics
from fcemu.evaluation.runner import EvalConfig, run_controller
from fcemu.firmware.controllers import load_controller

POLICY_DIR = Path(__file__).parents[1] / "policies"
POLICIES = sorted(POLICY_DIR.glob("*.onnx"))


def test_there_are_shipped_policies():
    assert {p.name for p in POLICIES} >= {"iris_rate_ppo.onnx", "iris_rate_ppo_smooth.onnx",
                                          "iris_rate_ppo_robust.onnx", "iris_rate_ppo_quiet.onnx",
                                          "iris_rate_ppo_quiet64.onnx", "iris_rate_ppo_quiet64_roll.onnx",
                                          "iris_rate_ppo_rms64.onnx", "iris_rate_ppo_rms64_ft.onnx",
                                          "iris_rate_ppo_rms64_mo.onnx"}


@pytest.mark.parametrize("path", POLICIES, ids=lambda p: p.name)
def test_a_shipped_policy_loads_and_tracks(path: Path):
    load_controller(str(path), 1000.0)  # the contract check: metadata, shapes, a trial run
    metrics = compute_metrics(run_controller(str(path), EvalConfig(episodes=8, seed=7), progress=False))
    assert all(metrics.stat("success_pct", a).mean >= 75.0 for a in AXES)


def test_the_smooth_policy_is_about_as_smooth_as_the_pid_and_the_old_one_is_not():
    """policies/README.md: 1.77 vs the PID's 1.42 µs/step on 1000 commands (the older policy: 5.32)."""
    cfg = EvalConfig(episodes=8, seed=7)
    specs = {"pid": "pid", "smooth": str(POLICY_DIR / "iris_rate_ppo_smooth.onnx"),
             "old": str(POLICY_DIR / "iris_rate_ppo.onnx")}
    smooth = {name: compute_metrics(run_controller(spec, cfg, progress=False)).stat("smoothness", "roll").mean
              for name, spec in specs.items()}
    assert smooth["smooth"] <= 1.5 * smooth["pid"]
    assert smooth["old"] > 2.5 * smooth["pid"]


def test_the_64_wide_policies_have_the_actor_their_inference_budget_rests_on():
    """policies/README.md: 9.1–9.4 µs median against 11.5–11.9 µs for the 128 × 128 quiet policy."""
    import onnx
    from onnx import numpy_helper

    def widths(name: str) -> list[int]:
        graph = onnx.load(str(POLICY_DIR / name)).graph
        weights = {w.name: numpy_helper.to_array(w) for w in graph.initializer}
        gemms = [n for n in graph.node if n.op_type == "Gemm"]
        transposed = [any(a.name == "transB" and a.i for a in g.attribute) for g in gemms]
        return [int(weights[g.input[1]].shape[0 if t else 1]) for g, t in zip(gemms, transposed, strict=True)]

    assert widths("iris_rate_ppo_quiet64.onnx") == [64, 64, 4]
    assert widths("iris_rate_ppo_quiet64_roll.onnx") == [64, 64, 4]  # its 256-wide critic is not exported
    assert widths("iris_rate_ppo_rms64.onnx") == [64, 64, 4]
    assert widths("iris_rate_ppo_rms64_ft.onnx") == [64, 64, 4]  # its normalisation unfolded: Sub, Mul first
    assert widths("iris_rate_ppo_rms64_mo.onnx") == [64, 64, 4]  # 1/σ folded, μ a Sub; 272 inputs
    assert widths("iris_rate_ppo_quiet.onnx") == [128, 128, 4]


@pytest.mark.parametrize("path", sorted((POLICY_DIR / "sweeps").glob("*.yaml")), ids=lambda p: p.name)
def test_a_committed_sweep_config_is_a_valid_sweep(path: Path):
    """The reliability runs in policies/README.md come from these files: they must still parse."""
    from fcemu.cli import build_parser
    from fcemu.training.cli import SWEEP_DEFAULTS
    from fcemu.training.sweep import spec_from_args

    spec = spec_from_args(build_parser().parse_args(["sweep", "--config", str(path)]), SWEEP_DEFAULTS)
    assert len(spec.seeds) >= 4 and spec.train["algo"] == "ppo"


def test_the_motor_output_policy_observes_its_own_commands():
    """rms64_mo is rms64_ft's start fine-tuned with its previous motor outputs added to what it sees."""
    import onnx

    from fcemu.firmware.contract import META_PREFIX, PolicyContract

    model = onnx.load(str(POLICY_DIR / "iris_rate_ppo_rms64_mo.onnx"))
    meta = {p.key.removeprefix(META_PREFIX): p.value
            for p in model.metadata_props if p.key.startswith(META_PREFIX)}
    spec = PolicyContract.from_metadata(meta).observation
    assert spec.fields == ("rate_error", "rotor_speed", "rate_error_integral", "rate_error_rms",
                           "motor_output")
    assert spec.memory == 16 and spec.size == 272
    assert [n.op_type for n in model.graph.node][:2] == ["Sub", "Gemm"]  # the export's centred fold
