"""`fcemu export` on real SB3 runs: parity, metadata round trip, and the checkpoints it refuses."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

from fcemu import __version__
from fcemu.export.cli import export_command
from fcemu.export.onnx_export import (
    ExportError,
    build_actor,
    export_policy,
    find_checkpoint,
    load_model,
    record_envelope,
)
from fcemu.firmware.airframe_spec import Envelope
from fcemu.firmware.controllers import DEFAULT_POLICY
from fcemu.firmware.neural import NeuralRateController, read_metadata
from fcemu.firmware.observation import ObservationSpec
from fcemu.sim_bridge.airframe_spec import airframe_spec, envelope
from fcemu.training.train import TrainConfig, train

pytestmark = [pytest.mark.slow, pytest.mark.no_wall_clock]


def _tiny_run(root: Path, algo: str, memory: int, steps: int, hp: dict | None = None,
              integral: bool = False, **options) -> Path:
    out = root / (algo + ("_integral" if integral else ""))
    cfg = TrainConfig(algo=algo, steps=steps, seed=7, out=str(out), memory=memory, envs=4, integral=integral,
                      **options, checkpoint_every=steps // 2, eval_episodes=0, progress=False, hp=hp or {})
    train(cfg)
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("runs")
    off_policy = {"learning_starts": 64, "buffer_size": 10_000, "batch_size": 32}
    return {
        "ppo": _tiny_run(root, "ppo", 2, 1024, {"n_steps": 64, "batch_size": 64}),
        "ppo_unclipped": _tiny_run(root / "unclipped", "ppo", 2, 1024, {"n_steps": 64, "batch_size": 64},
                                   obs_clip=0.0),
        "ppo_squashed": _tiny_run(root / "squashed", "ppo", 1, 1024, {
            "n_steps": 64, "batch_size": 64,
            "policy_kwargs": {"net_arch": {"pi": [64, 64], "vf": [64, 64]}, "squash_output": True}}),
        "sac": _tiny_run(root, "sac", 1, 256, off_policy),
        "td3": _tiny_run(root, "td3", 3, 256, off_policy),
    }


def test_integral_and_rms_observation_exports_and_flies(tmp_path):
    run = _tiny_run(tmp_path, "ppo", 1, 1024, {"n_steps": 64, "batch_size": 64}, integral=True,
                    integral_leak=0.9995, error_rms=True, rms_leak=0.99)
    info = export_policy(run, tmp_path / "p.onnx", parity_samples=10_000)
    assert info["parity_max_abs_diff"] <= 1e-5
    spec = ObservationSpec.from_json(read_metadata(tmp_path / "p.onnx")["observation"])
    assert spec.fields[-2:] == ("rate_error_integral", "rate_error_rms") and spec.size == 13
    assert (spec.integral_leak, spec.rms_leak) == (0.9995, 0.99)  # the leaks trained with are the ones flown
    env = json.loads((run / "config.json").read_text())["env"]
    assert (env["integral_leak"], env["rms_leak"]) == (0.9995, 0.99)
    ctrl = NeuralRateController(tmp_path / "p.onnx")
    assert ctrl.spec == spec


def test_a_loop_delay_run_trains_exports_and_flies_each_airframe_with_its_own_delay(tmp_path):
    """Trained end to end (`fcemu train --loop-delay`); the export's parity samples draw delays."""
    from dataclasses import replace

    from fcemu.firmware.controller import RateSetpoint
    from fcemu.firmware.sensors import SensorFrame

    run = _tiny_run(tmp_path, "ppo", 2, 1024, {"n_steps": 64, "batch_size": 64}, loop_delay=True,
                    airframe="iris_realistic")
    info = export_policy(run, tmp_path / "p.onnx", parity_samples=2000)
    assert info["parity_max_abs_diff"] <= 1e-4
    spec = ObservationSpec.from_json(read_metadata(tmp_path / "p.onnx")["observation"])
    assert spec.fields[-1] == "loop_delay" and spec.size == 16
    frame = SensorFrame(0, np.array([0.3, -0.2, 0.1]), np.array([0.0, 0.0, -9.81]), np.full(4, 600.0))
    realistic = airframe_spec("iris_realistic")  # ESC 1 + gyro 2 ticks
    flown = {d: NeuralRateController(tmp_path / "p.onnx", airframe=replace(realistic, loop_delay_ticks=d))
             .update(RateSetpoint(np.zeros(3), 0.5), frame, 1e-3) for d in (0, 3)}
    assert not np.array_equal(flown[0], flown[3])


@pytest.mark.parametrize("algo", ["ppo", "sac", "td3"])
def test_parity_and_metadata_round_trip(runs, algo, tmp_path):
    run = runs[algo]
    out = tmp_path / f"{algo}.onnx"
    report = export_policy(run, out, parity_samples=10_000)
    assert report["parity_samples"] >= 10_000
    assert report["parity_max_abs_diff"] <= 1e-5 and report["parity_ok"]
    assert json.loads(out.with_suffix(".parity.json").read_text())["parity_ok"]

    config = json.loads((run / "config.json").read_text())
    meta = read_metadata(out)
    spec = ObservationSpec.from_json(meta["observation"])
    assert spec == ObservationSpec.from_json(json.dumps(config["observation"]))
    assert spec.memory == {"ppo": 2, "sac": 1, "td3": 3}[algo]
    assert meta["action_mapping"] == "throttle"
    assert meta["algorithm"] == algo
    assert int(meta["training_steps"]) == config["trained_steps"] > 0
    assert meta["seed"] == "7"
    assert meta["fcemu_version"] == __version__
    assert float(meta["loop_rate_hz"]) == 1000.0
    ctrl = NeuralRateController(out)
    assert ctrl.spec == spec and ctrl.action_mapping == "throttle"
    assert meta["airframe"] == "iris"  # no randomisation: the airframe within a margin
    assert Envelope.from_json(meta["envelope"]) == envelope("iris")


def test_an_older_export_gets_its_envelope_and_keeps_its_network(tmp_path):
    import onnx

    shipped = onnx.load(str(DEFAULT_POLICY))
    older = onnx.load(str(DEFAULT_POLICY))
    recorded = ("fcemu.airframe", "fcemu.envelope")
    kept = [(p.key, p.value) for p in older.metadata_props if p.key not in recorded]
    del older.metadata_props[:]
    for key, value in kept:
        older.metadata_props.add(key=key, value=value)
    onnx.save(older, str(tmp_path / "older.onnx"))
    record_envelope(tmp_path / "older.onnx", airframe_spec("iris"), envelope("iris", "iris"))
    again = onnx.load(str(tmp_path / "older.onnx"))
    assert again.graph.SerializeToString() == shipped.graph.SerializeToString()
    assert {p.key: p.value for p in again.metadata_props} == {p.key: p.value for p in shipped.metadata_props}


@pytest.mark.parametrize("algo", ["ppo", "ppo_unclipped", "ppo_squashed", "sac"])
def test_onnx_is_the_normalised_deterministic_actor(runs, algo, tmp_path):
    """Independently of export's own check: ONNX(raw obs) == SB3 predict(VecNormalize(obs))."""
    import pickle

    run = runs[algo]
    out = tmp_path / "p.onnx"
    export_policy(run, out)
    ckpt = find_checkpoint(run)
    model = load_model(ckpt)
    with open(ckpt.vecnormalize_path, "rb") as fh:
        vecnorm = pickle.load(fh)
    assert vecnorm.norm_obs and not np.allclose(vecnorm.obs_rms.mean, 0.0)  # normalisation was learnt
    spec = ObservationSpec.from_json(json.dumps(ckpt.config["observation"]))
    obs = np.random.default_rng(1).normal(0.0, 1.0, (2000, spec.size)).astype(np.float32)
    obs[:, 3:7] = np.abs(obs[:, 3:7])  # rotor speeds are non-negative
    expected = model.predict(vecnorm.normalize_obs(obs), deterministic=True)[0]
    got = ort.InferenceSession(str(out)).run(None, {"observation": obs})[0]
    inside = np.abs(got).max(axis=1) < 1.0  # predict clips to the action box; the ONNX output does not
    assert inside.sum() > 100
    np.testing.assert_allclose(got[inside], expected[inside], atol=1e-5)


def test_without_an_observation_clip_the_normalisation_folds_into_the_first_layer(runs, tmp_path):
    import onnx

    def ops(name: str, folded: bool) -> list[str]:
        out = tmp_path / f"{name}.onnx"
        report = export_policy(runs[name], out)
        assert report["parity_ok"] and report["normalisation"].startswith("folded" if folded else "in the")
        return [n.op_type for n in onnx.load(str(out)).graph.node]

    assert ops("ppo_unclipped", True) == ["Gemm", "Tanh", "Gemm", "Tanh", "Gemm"]  # the bare MLP
    clipped = ops("ppo", False)
    assert clipped[:2] == ["Sub", "Mul"] and "Clip" in clipped  # the clip at 10 σ keeps the normalisation
    assert json.loads((runs["ppo_unclipped"] / "config.json").read_text())["obs_clip"] == 0.0


@pytest.mark.parametrize("spoilt, normalisation, ops", [
    ((False,), "1/σ folded into the first layer, μ subtracted in the graph", ["Sub", "Gemm"]),
    ((False, True), "in the graph", ["Sub", "Mul", "Gemm"]),
])
def test_a_fold_that_loses_parity_falls_back_to_a_cheaper_one_then_to_the_graph(runs, tmp_path, monkeypatch,
                                                                                 spoilt, normalisation, ops):
    import onnx

    import fcemu.export.onnx_export as onnx_export

    class OffByALittle(onnx_export.FoldedActor):
        def __init__(self, actor, centred: bool = False) -> None:
            super().__init__(actor, centred)
            if centred in spoilt:
                self.net[0].bias.data += 1e-3  # what float32 cancellation would do, only larger

    monkeypatch.setattr(onnx_export, "FoldedActor", OffByALittle)
    report = export_policy(runs["ppo_unclipped"], tmp_path / "p.onnx")
    assert report["parity_ok"] and report["normalisation"] == normalisation
    assert [n.op_type for n in onnx.load(str(tmp_path / "p.onnx")).graph.node][:len(ops)] == ops


def test_parity_allows_a_wide_sum_four_times_the_float32_networks_own_error(runs, tmp_path, monkeypatch):
    """Observations far out (as a long history of random errors is) make the float32 actor itself
    miss exact arithmetic by more than 1e-5; the graph is held to four times that, no looser."""
    import fcemu.export.onnx_export as onnx_export

    near = export_policy(runs["ppo_unclipped"], tmp_path / "near.onnx")
    assert near["parity_tolerance"] == onnx_export.PARITY_TOLERANCE
    usual = onnx_export.parity_observations
    monkeypatch.setattr(onnx_export, "parity_observations",
                        lambda spec, n, top, seed=0: 3e4 * usual(spec, n, top))
    far = export_policy(runs["ppo_unclipped"], tmp_path / "far.onnx")
    assert far["parity_ok"] and far["parity_tolerance"] > onnx_export.PARITY_TOLERANCE
    assert far["parity_max_abs_diff"] <= far["parity_tolerance"]


def test_checkpoint_zip_exports_with_its_own_normalisation(runs, tmp_path):
    ckpts = sorted((runs["ppo"] / "checkpoints").glob("ppo_*_steps.zip"))
    assert ckpts, "CheckpointCallback wrote no checkpoint"
    ckpt = find_checkpoint(ckpts[0])
    assert ckpt.vecnormalize_path is not None and "vecnormalize" in ckpt.vecnormalize_path.name
    assert ckpt.vecnormalize_path.parent.name == "checkpoints"
    report = export_policy(ckpts[0], tmp_path / "ckpt.onnx")
    assert report["parity_ok"]


def test_missing_config_is_refused(runs, tmp_path):
    run = tmp_path / "noconfig"
    shutil.copytree(runs["ppo"], run)
    (run / "config.json").unlink()
    with pytest.raises(ExportError, match=r"config\.json missing"):
        export_policy(run, tmp_path / "x.onnx")


def test_unknown_and_wrong_algorithm_are_refused(runs, tmp_path):
    run = tmp_path / "wrong"
    shutil.copytree(runs["ppo"], run)
    config = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**config, "algo": "a2c"}))
    with pytest.raises(ExportError, match="algorithm 'a2c'"):
        export_policy(run, tmp_path / "x.onnx")
    (run / "config.json").write_text(json.dumps({**config, "algo": "sac"}))  # a PPO zip said to be SAC
    with pytest.raises(ExportError, match="cannot load as SAC"):
        export_policy(run, tmp_path / "x.onnx")


def test_corrupt_zip_is_refused(runs, tmp_path):
    run = tmp_path / "corrupt"
    shutil.copytree(runs["ppo"], run)
    (run / "model.zip").write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(ExportError, match="cannot load as PPO"):
        export_policy(run, tmp_path / "x.onnx")
    assert not (tmp_path / "x.onnx").exists()


def test_observation_shape_mismatch_is_refused(runs, tmp_path):
    run = tmp_path / "mismatch"
    shutil.copytree(runs["ppo"], run)
    config = json.loads((run / "config.json").read_text())
    config["observation"]["memory"] = 5  # the policy was trained with memory 2
    (run / "config.json").write_text(json.dumps(config))
    with pytest.raises(ExportError, match="does not match"):
        export_policy(run, tmp_path / "x.onnx")


def test_cli_exit_codes(runs, tmp_path, capsys):
    class Args:
        checkpoint, out, parity_samples, json = str(runs["sac"]), str(tmp_path / "cli.onnx"), 10_000, True

    assert export_command(Args) == 0
    assert json.loads(capsys.readouterr().out)["parity_ok"]
    Args.checkpoint = str(tmp_path / "nowhere.zip")
    assert export_command(Args) == 2
    err = capsys.readouterr().err
    assert err.startswith("fcemu: error: ") and "no such checkpoint" in err and err.count("\n") == 1


def test_actor_output_is_independent_of_batch(runs):
    ckpt = find_checkpoint(runs["td3"])
    model = load_model(ckpt)
    spec = ObservationSpec.from_json(json.dumps(ckpt.config["observation"]))
    actor = build_actor(model, ckpt, spec)
    x = torch.rand(16, spec.size)
    with torch.no_grad():
        batch = actor(x)
        single = torch.cat([actor(x[i:i + 1]) for i in range(16)])
    torch.testing.assert_close(batch, single, atol=1e-6, rtol=0)
