"""`fcemu sweep` on a real local Ray: two short trials, the table, the best policy, resume."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from fcemu.firmware.neural import NeuralRateController
from fcemu.training.sweep import parse_seeds, parse_space

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]  # Ray start-up on a loaded machine
ROOT = Path(__file__).resolve().parents[2]
# Two trials of 2048 steps (8 twins, rollouts of 1024), two evaluations each on 2 commands.
SHORT = ["--steps", "2048", "--envs", "8", "--eval-every", "1024", "--eval-commands", "2",
         "--checkpoint-every", "1024", "--best-episodes", "2"]

PERTURB = ["--perturb", "2", "--perturb-seed", "5", "--perturb-episodes", "2"]  # each trial, then the PID


def fcemu(*args: str, **kwargs) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    return subprocess.Popen([sys.executable, "-m", "fcemu", *args], env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, **kwargs)


def test_seeds_and_space_parse():
    assert parse_seeds("0-4") == [0, 1, 2, 3, 4] and parse_seeds("0-1,7,1") == [0, 1, 7]
    assert parse_space(["learning_rate=1e-4,3e-4", "net=[64, 64]", "lr=lin_3e-4,lin_1e-4"]) == {
        "learning_rate": [1e-4, 3e-4], "net": [[64, 64]], "lr": ["lin_3e-4", "lin_1e-4"]}
    with pytest.raises(ValueError, match="seeds"):
        parse_seeds("a-b")


def test_spec_from_yaml_and_command_line(tmp_path):
    from fcemu.cli import build_parser
    from fcemu.training.cli import SWEEP_DEFAULTS
    from fcemu.training.sweep import spec_from_args

    path = tmp_path / "sweep.yaml"
    path.write_text("seeds: 0-2\nsteps: 300000\nsquash: true\naction_rate_penalty: 1.0\n"
                    "space:\n  action_rate_penalty: [1, 2]\n  learning_rate: [lin_3e-4, lin_1e-4]\n")
    args = build_parser().parse_args(["sweep", "--config", str(path), "--steps", "500000",
                                      "--hp", "gamma=0.98,0.99"])
    spec = spec_from_args(args, SWEEP_DEFAULTS)
    assert spec.seeds == [0, 1, 2] and spec.n_trials == 3 * 2 * 2 * 2
    assert spec.space == {"action_rate_penalty": [1, 2], "learning_rate": ["lin_3e-4", "lin_1e-4"],
                          "gamma": [0.98, 0.99]}
    assert spec.train["steps"] == 500_000 and spec.train["squash"] and spec.train["eval_every"] == 250_000
    cfg = spec.config(2, {"action_rate_penalty": 4, "gamma": 0.98}, "runs/x", threads=1)
    assert (cfg.seed, cfg.action_rate_penalty, cfg.hyper["gamma"], cfg.squash) == (2, 4, 0.98, True)
    bad = build_parser().parse_args(["sweep", "--hp", "algo=ppo,a2c"])
    with pytest.raises(ValueError, match="a2c"):
        spec_from_args(bad, SWEEP_DEFAULTS)
    path.write_text("seeds: 0\nlearning_rat: 1\n")
    with pytest.raises(ValueError, match="unknown options"):
        spec_from_args(build_parser().parse_args(["sweep", "--config", str(path)]), SWEEP_DEFAULTS)


@pytest.fixture(scope="module")
def sweep(tmp_path_factory) -> tuple[Path, dict, str]:
    out = tmp_path_factory.mktemp("sweep") / "out"
    proc = fcemu("sweep", "--seeds", "0-1", *SHORT, "--hp", "n_steps=128", "batch_size=256",
                 "--cpus", "2", "--no-early-stop", "--out", str(out), "--json", *PERTURB)
    stdout, stderr = proc.communicate(timeout=600)
    assert proc.returncode == 0, stderr[-3000:]
    return out, json.loads(stdout), stderr  # stdout holds one JSON object and nothing else


def test_a_sweep_saved_before_an_option_existed_is_the_same_sweep():
    import dataclasses
    import json

    from fcemu.cli import build_parser
    from fcemu.training.cli import SWEEP_DEFAULTS
    from fcemu.training.sweep import saved_spec, spec_from_args

    spec = spec_from_args(build_parser().parse_args(["sweep", "--hp", "gamma=0.98,0.99"]), SWEEP_DEFAULTS)
    stored = json.dumps(dataclasses.asdict(spec), sort_keys=True, default=list)
    old = json.loads(stored)
    for added in ("episode_s", "omega_max", "hold_s", "rest_s"):  # options newer than the saved sweep
        del old["train"][added]
    del old["perturb"]
    assert json.dumps(saved_spec(old, spec), sort_keys=True, default=list) == stored
    spec = spec_from_args(build_parser().parse_args(["sweep", "--perturb", "2"]), SWEEP_DEFAULTS)
    old = json.loads(json.dumps(dataclasses.asdict(spec), default=list))
    del old["perturb"]["airframe"]  # saved before the perturbed flights named their airframe
    assert saved_spec(old, spec)["perturb"] == spec.perturb == {**old["perturb"], "airframe": "iris"}
    old["train"]["omega_max"] = 3.0  # a sweep that set it is another sweep
    assert json.dumps(saved_spec(old, spec), sort_keys=True, default=list) != stored


def test_one_json_object_with_a_row_per_trial(sweep):
    out, payload, stderr = sweep
    assert payload["engine"] == "ray" and payload["steps"] == 2048
    trials = payload["trials"]
    assert sorted(t["seed"] for t in trials) == [0, 1]
    for t in trials:
        assert t["status"] == "done" and t["steps"] == 2048
        assert t["settings"] == {"n_steps": 128, "batch_size": 256}
        assert t["best_error_ratio"] > 0 and len(t["success_pct"]) == 3 and t["smoothness"] >= 0
        run = out / "runs" / t["trial"]  # each trial is a `fcemu train` run directory
        for name in ("config.json", "model.zip", "vecnormalize.pkl", "policy.onnx", "summary.json"):
            assert (run / name).is_file(), name
        config = json.loads((run / "config.json").read_text())
        assert config["seed"] == t["seed"] and config["hyperparameters"]["batch_size"] == 256
        evals = json.loads((run / "summary.json").read_text())["in_training_evals"]
        assert [e["steps"] for e in evals] == [1024, 2048]
        exported = min(evals, key=lambda e: tuple(e["selection_key"]))  # the race's pick, not the min ratio
        assert t["best_error_ratio"] == pytest.approx(exported["error_ratio"])
        assert t["best_steps"] == exported["steps"] and t["meets_bar"] == exported["meets_bar"]
    assert "best ratio" in stderr  # Tune's live table


def test_tables_hold_every_trial(sweep):
    out, payload, _ = sweep
    with (out / "results.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [int(r["seed"]) for r in rows] == [0, 1]
    assert {r["trial"] for r in rows} == {t["trial"] for t in payload["trials"]}
    assert all(r["status"] == "done" and r["settings"] == "n_steps=128 batch_size=256" for r in rows)
    md = (out / "results.md").read_text().splitlines()
    assert md[0].startswith("| trial | seed |") and len(md) == 2 + len(rows)
    assert md[0].endswith("| perturbed Error ratio vs PID, worse task "
                          "| perturbed Success % r/p/y, lower task "
                          "| meets the perturbed lines, rest and in flight |")
    assert all(r["meets_perturbed"] in ("yes", "no") for r in rows)


def _eval_perturbed(controller: str, task: str) -> dict:
    proc = fcemu("eval", "--controller", controller, "--episodes", "2", "--seed", "7", *PERTURB[:4],
                 "--task", task, "--json")
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 0, stderr[-2000:]
    return json.loads(stdout)["perturbed"]  # one controller: one object


def test_each_trial_and_the_pid_fly_the_perturbed_airframes_of_fcemu_eval_from_rest_and_in_flight(sweep):
    out, payload, _ = sweep
    pid = payload["perturbed_pid"]
    assert (pid["airframes"], pid["seed"], pid["episodes"], pid["ranges"]) == (2, 5, 2, "iris")
    for task in ("episodic", "inflight"):
        reference = _eval_perturbed("pid", task)
        assert pid[task]["error"] == pytest.approx(sum(v[0] for v in reference["error"].values()))
    for t in payload["trials"]:
        p = t["perturbed"]
        for task in ("episodic", "inflight"):
            reference = _eval_perturbed(str(out / "runs" / t["trial"] / "policy.onnx"), task)
            assert p[task]["error"] == pytest.approx(sum(v[0] for v in reference["error"].values()))
            assert p[task]["success_pct"] == pytest.approx([v[0] for v in reference["success_pct"].values()])
        tasks = ("episodic", "inflight")
        ratios = [p[k]["error"] / pid[k]["error"] for k in tasks]
        assert t["perturbed_error_ratio"] == pytest.approx(max(ratios))
        assert t["meets_perturbed"] == all(r <= 1.0 and min(p[k]["success_pct"]) >= 99.0
                                           for r, k in zip(ratios, tasks, strict=True))


def test_a_bad_perturbed_flight_fails_before_any_trial():
    from fcemu.cli import build_parser
    from fcemu.training.cli import SWEEP_DEFAULTS
    from fcemu.training.sweep import spec_from_args

    for bad in (["--perturb", "-1"], ["--perturb", "2", "--perturb-episodes", "0"],
                ["--perturb", "2", "--randomize", "no_such_ranges"]):
        with pytest.raises(ValueError, match=r"perturb|no_such_ranges"):
            spec_from_args(build_parser().parse_args(["sweep", *bad]), SWEEP_DEFAULTS)
    spec = spec_from_args(build_parser().parse_args(["sweep", *PERTURB]), SWEEP_DEFAULTS)
    assert spec.perturb == {"airframes": 2, "seed": 5, "episodes": 2, "ranges": "iris", "airframe": "iris"}
    assert spec_from_args(build_parser().parse_args(["sweep"]), SWEEP_DEFAULTS).perturb == {}


def test_the_best_trial_is_exported_and_flown(sweep):
    out, payload, _ = sweep
    best = payload["best"]
    assert best["selection_key"] == min(t["selection_key"] for t in payload["trials"])
    assert best["export"]["parity_ok"] and Path(best["policy"]) == out / "best" / "policy.onnx"
    meta = NeuralRateController(out / "best" / "policy.onnx").metadata
    assert meta["seed"] == str(best["seed"]) and meta["training_steps"] == str(best["best_steps"])
    flown = json.loads((out / "best" / "eval.json").read_text())
    assert flown["episodes"] == 2 and flown["bar"] == best["eval"]["bar"]
    assert flown["results"][-1]["controller"] == str(out / "best" / "policy.onnx")


def test_a_different_sweep_in_the_same_directory_is_refused(sweep):
    out, _, _ = sweep
    proc = fcemu("sweep", "--seeds", "0-2", *SHORT, "--out", str(out))
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 2 and stderr.startswith("fcemu: error:") and "different sweep" in stderr


def test_an_interrupted_sweep_resumes_without_redoing_finished_trials(tmp_path):
    out = tmp_path / "out"
    args = ["sweep", "--seeds", "0-1", *SHORT, "--hp", "batch_size=256", "--cpus", "1", "--no-early-stop",
            "--best-episodes", "0", "--out", str(out), "--json"]
    proc = fcemu(*args)
    deadline = time.monotonic() + 400
    # One CPU: the second trial starts (writes its config) only once Tune has closed the first.
    while len(list((out / "runs").glob("*/config.json"))) < 2:
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()[1][-3000:]
        time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130 and "resumes" in stderr, stderr[-3000:]
    (first,) = list((out / "runs").glob("*/summary.json"))
    stamp = first.stat().st_mtime_ns

    proc = fcemu(*args)
    stdout, stderr = proc.communicate(timeout=600)
    assert proc.returncode == 0 and "resuming" in stderr, stderr[-3000:]
    payload = json.loads(stdout)
    assert [t["status"] for t in payload["trials"]] == ["done", "done"]
    assert first.stat().st_mtime_ns == stamp  # the finished trial was kept, not trained again
