"""`fcemu eval` end to end: the runner flies real controllers through the firmware loop."""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fcemu.evaluation.metrics import AXES, METRIC_KEYS, compute_metrics
from fcemu.evaluation.runner import EvalConfig, run_controller, setpoint_schedules
from fcemu.sim_bridge.airframe import AIRFRAME_DIR, load_airframe
from fcemu.sim_bridge.tasks import episodic_commands
from fcemu.sim_bridge.twin import Twin, hover_state
from fcemu.sitl.traces import load_traces


def fcemu(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fcemu", *args], capture_output=True, text=True,
                          timeout=300, check=False)


def test_commands_come_from_the_seed_alone():
    a = setpoint_schedules(EvalConfig(episodes=5, seed=7))
    b = setpoint_schedules(EvalConfig(episodes=5, seed=7))
    c = setpoint_schedules(EvalConfig(episodes=5, seed=8))
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert np.array_equal(a[:, 0], episodic_commands(7, 5))
    cont = setpoint_schedules(EvalConfig(task="continuous", episodes=2, seed=7, episode_s=3.0))
    assert cont.shape == (2, 3000, 3) and not np.array_equal(cont[0], cont[1])


def test_runner_records_what_the_loop_flew():
    cfg = EvalConfig(episodes=3, seed=1)
    traces = run_controller("pid:paper", cfg, progress=False)
    assert traces.setpoint.shape == (3, 1000, 3) and traces.pwm.shape == (3, 1000, 4)
    assert np.all(traces.rate[:, 0] == 0.0)  # sample 0: the vehicle at rest
    assert traces.pwm.min() >= 1000 and traces.pwm.max() <= 2000
    # The PID follows the command: by the end of the episode the rate is near the setpoint.
    assert np.abs(traces.rate[:, -100:] - traces.setpoint[:, -100:]).mean() < 0.5
    again = run_controller("pid:paper", cfg, progress=False)
    assert np.array_equal(traces.rate, again.rate)  # deterministic


def test_eval_json_has_the_design_keys_and_saved_traces_recompute(tmp_path):
    npz = tmp_path / "traces.npz"
    out = fcemu("eval", "--controller", "pid:paper", "--episodes", "12", "--seed", "3", "--json",
                "--save-traces", str(npz))
    assert out.returncode == 0, out.stderr
    payload = json.loads(out.stdout)
    assert {"controller", "episodes", "seed", "task", "metrics"} <= payload.keys()
    assert payload["controller"] == "pid:paper" and payload["episodes"] == 12 and payload["seed"] == 3
    assert set(payload["metrics"]) == set(METRIC_KEYS)
    for metric in payload["metrics"].values():
        assert set(metric) == {"roll", "pitch", "yaw"} and all(len(v) == 2 for v in metric.values())
    recomputed = compute_metrics(load_traces(npz)).to_json()
    assert json.loads(json.dumps(recomputed)) == payload["metrics"]


def test_eval_report_compares_controllers_side_by_side(tmp_path):
    out = fcemu("eval", "--controller", "pid:paper", "--controller", "pid", "--episodes", "6",
                "--report", str(tmp_path))
    assert out.returncode == 0, out.stderr
    md = (tmp_path / "report.md").read_text()
    header = next(line for line in md.splitlines() if line.startswith("| Metric"))
    assert "| pid:paper |" in header and "| pid |" in header
    assert "66.6" in md  # the paper's PPO roll rise, beside ours
    assert (tmp_path / "step_response.png").stat().st_size > 10_000
    assert len(list(tmp_path.glob("continuous_*.png"))) == 2


def test_an_airframe_with_gyro_noise_flies_the_same_for_the_same_seed():
    cfg = EvalConfig(episodes=2, episode_s=0.05, seed=3, airframe="iris_realistic")
    assert load_airframe(cfg.airframe).gyro_noise_std > 0.0
    first, again = run_controller("pid", cfg, progress=False), run_controller("pid", cfg, progress=False)
    np.testing.assert_array_equal(first.rate, again.rate)
    np.testing.assert_array_equal(first.pwm, again.pwm)
    other = run_controller("pid", EvalConfig(episodes=2, episode_s=0.05, seed=4, airframe="iris_realistic"),
                           progress=False)
    assert not np.array_equal(other.rate[:, 1:], first.rate[:, 1:])


def test_a_bad_task_is_refused():
    with pytest.raises(ValueError):
        EvalConfig(task="hover")


def test_inflight_starts_at_steady_hover_and_steps_at_t0():
    cfg = EvalConfig(task="inflight", episodes=3, seed=7)
    traces = run_controller("pid", cfg, progress=False)
    k0 = cfg.warmup_ticks
    assert k0 == 200 and traces.t[0] == pytest.approx(-0.2) and traces.t[k0] == 0.0
    assert traces.setpoint.shape == (3, 1200, 3)
    assert not traces.setpoint[:, :k0].any()
    assert np.array_equal(traces.setpoint[:, k0], episodic_commands(7, 3))
    iris = load_airframe("iris")
    hover = [iris.hover_rotor_speed()] * 4
    np.testing.assert_allclose(traces.extra["initial_rotor_speed"], hover, rtol=1e-12)
    assert np.all(traces.rate[:, 0] == 0.0)  # rates zero at the first tick
    np.testing.assert_allclose(traces.pwm[:, 0], iris.hover_pwm(), rtol=1e-12)  # hover from the first tick
    # The warm-up holds the hover: no rate, no change of output, right up to the step.
    assert np.abs(traces.rate[:, :k0 + 1]).max() < 1e-9
    assert np.ptp(traces.pwm[:, :k0], axis=1).max() < 1e-6
    twin = Twin()
    twin.reset(state=hover_state(twin.airframe, cfg.hover_throttle))
    np.testing.assert_allclose(twin.rotor_speed, iris.hover_rotor_speed(), rtol=1e-12)


def test_inflight_scores_from_the_step_and_has_less_error_than_from_rest():
    commands = dict(episodes=4, seed=7)
    inflight = run_controller("pid", EvalConfig(task="inflight", **commands), progress=False)
    episodic = run_controller("pid", EvalConfig(task="episodic", **commands), progress=False)
    m_in, m_ep = compute_metrics(inflight), compute_metrics(episodic)
    step = inflight.rate[:, 200:]
    expected = np.abs(inflight.setpoint[:, 200:] - step).sum(axis=1).mean(axis=0)
    np.testing.assert_allclose([m_in.stat("error", a).mean for a in AXES], expected, rtol=1e-12)
    for axis in AXES:
        assert m_in.stat("error", axis).mean < m_ep.stat("error", axis).mean


def test_the_trace_is_the_body_rate_not_the_noisy_delayed_gyro():
    """Metrics judge what the vehicle did: replaying the recorded PWM on the same airframe gives
    the recorded rates exactly, although the controller read a noisy, delayed gyro."""
    airframe = dataclasses.replace(load_airframe("iris"), gyro_noise_std=0.2, gyro_delay_ticks=2)
    traces = run_controller("pid", EvalConfig(episodes=1, episode_s=0.2, seed=3), progress=False,
                            airframe=airframe)
    twin = Twin(airframe, rig="rig")
    twin.reset(0)
    replay = [twin.clean_gyro()]
    for pwm in traces.pwm[0, :-1]:
        twin.step(pwm)
        replay.append(twin.clean_gyro())
    np.testing.assert_array_equal(traces.rate[0], np.array(replay))
    assert np.abs(traces.rate[0, -50:] - traces.setpoint[0, -50:]).mean() < 0.2  # and it flew the step


def test_eval_flies_another_airframe_end_to_end():
    out = fcemu("eval", "--airframe", "crazyflie", "--controller", "pid:iris", "--episodes", "2",
                "--seed", "7", "--json")
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)  # one controller: its result
    assert result["airframe"] == "crazyflie" and result["metrics"]["error"]


def test_eval_flies_a_scaled_iris_file_and_perturbs_it_with_ranges_around_it(tmp_path):
    raw = json.loads((AIRFRAME_DIR / "iris.json").read_text())
    raw.update(name="iris_heavy", base_mass_kg=1.7)
    path = tmp_path / "iris_heavy.json"
    path.write_text(json.dumps(raw))
    flown = fcemu("eval", "--airframe", str(path), "--controller", "pid:iris", "--episodes", "2", "--json")
    assert flown.returncode == 0, flown.stderr
    nominal = fcemu("eval", "--controller", "pid:iris", "--episodes", "2", "--json")
    heavy, iris = (json.loads(p.stdout)["metrics"] for p in (flown, nominal))
    assert heavy != iris
    perturbed = fcemu("eval", "--airframe", str(path), "--controller", "pid:iris", "--episodes", "1",
                      "--perturb", "2", "--json")  # none of its own: the relative ranges, built for it
    assert perturbed.returncode == 0, perturbed.stderr
    assert Path(json.loads(perturbed.stdout)["perturbation"]["ranges"]).name == "relative.randomization.json"
    refused = fcemu("eval", "--airframe", str(path), "--controller", "pid:iris", "--episodes", "1",
                    "--perturb", "1", "--ranges", "iris")  # the Iris's are another airframe's
    assert refused.returncode == 2 and refused.stderr.startswith("fcemu: error: ")
    assert refused.stderr.count("\n") == 1 and "iris_heavy" in refused.stderr


def test_the_twin_can_fly_another_airframe_than_the_firmware_is_set_up_for(tmp_path):
    raw = json.loads((AIRFRAME_DIR / "iris.json").read_text())
    raw.update(name="iris_heavy", base_mass_kg=1.7)
    heavy = tmp_path / "iris_heavy.json"
    heavy.write_text(json.dumps(raw))
    base = EvalConfig(episodes=1, seed=3, episode_s=0.2)
    iris = run_controller("pid:iris", base, progress=False)
    same = run_controller("pid:iris", dataclasses.replace(base, twin="iris"), progress=False)
    np.testing.assert_array_equal(same.pwm, iris.pwm)
    # the firmware set up for the Iris, the twin the heavy one: flown as the heavy airframe is flown
    on_heavy = run_controller("pid:iris", dataclasses.replace(base, twin=str(heavy)), progress=False)
    heavy_alone = run_controller("pid:iris", dataclasses.replace(base, airframe=str(heavy)), progress=False)
    np.testing.assert_array_equal(on_heavy.pwm, heavy_alone.pwm)
    assert not np.array_equal(on_heavy.pwm, iris.pwm)
    refused = fcemu("eval", "--twin", str(heavy), "--perturb", "1", "--episodes", "1")
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1 and "--twin" in refused.stderr
    reported = fcemu("eval", "--twin", str(heavy), "--episodes", "1", "--controller", "pid:iris",
                     "--report", str(tmp_path / "report"))
    assert reported.returncode == 0, reported.stderr
    assert f"airframe `iris` (the twin flies `{heavy}`)" in (tmp_path / "report" / "report.md").read_text()


def test_a_policy_on_an_airframe_without_a_shipped_tune_falls_back_to_the_pid_flown_beside_it(
        untuned_airframe: Path) -> None:
    from fcemu.evaluation.evaluate import fallback_for

    untuned = str(untuned_airframe)
    fitted = ["pid:runs/my_quad/pid.json", "runs/my_quad/policy.onnx"]
    for default in (None, "pid"):  # the policies name none (no such file): the airframe's own tune
        assert fallback_for(untuned, default, fitted) == "pid:runs/my_quad/pid.json"  # it ships no tune
        assert fallback_for("iris", default, fitted) == "pid"  # its own tune first
        assert fallback_for(untuned, default, [*fitted, "pid:b.json"]) == "pid"  # which one: not guessed
    assert fallback_for(untuned, "pid:other.json", fitted) == "pid:other.json"  # as asked


def policy_naming_its_pid(folder: Path) -> Path:
    """The shipped policy as `fcemu fit` leaves one: in `folder` beside the PID its metadata names
    (pid.json, here the paper's gains: not the Iris tune `pid` flies)."""
    from fcemu.export.onnx_export import record_metadata
    from fcemu.firmware.contract import FALLBACK_META
    from fcemu.firmware.controllers import DEFAULT_POLICY
    from fcemu.firmware.pid_controller import PRESET_DIR

    folder.mkdir(parents=True)
    policy = folder / "policy.onnx"
    shutil.copy(DEFAULT_POLICY, policy)
    record_metadata(policy, {FALLBACK_META: "pid.json"})
    shutil.copy(PRESET_DIR / "pid_paper.json", folder / "pid.json")
    return policy


def test_a_policy_that_names_its_pid_hands_over_to_it_unless_told_otherwise(tmp_path, monkeypatch,
                                                                            capsys) -> None:
    from fcemu.cli import main
    from fcemu.evaluation import runner
    from fcemu.evaluation.evaluate import fallback_for

    policy = policy_naming_its_pid(tmp_path / "fit")
    named = f"pid:{tmp_path / 'fit' / 'pid.json'}"
    assert fallback_for("iris", None, [str(policy)]) == named
    assert fallback_for("iris", None, ["pid:paper", str(policy)]) == named
    assert fallback_for("iris", "pid", [str(policy)]) == "pid"  # as asked
    assert fallback_for("iris", "pid:iris", [str(policy)]) == "pid:iris"
    loaded: list[str] = []

    def recorded(spec: str, *args, **kwargs):
        loaded.append(spec)
        return load_controller(spec, *args, **kwargs)

    load_controller = runner.load_controller
    monkeypatch.setattr(runner, "load_controller", recorded)
    for given, fallback in (([], named), (["--fallback", "pid:iris"], "pid:iris")):
        loaded.clear()
        assert main(["eval", "--controller", str(policy), "--episodes", "1", "--episode-s", "0.1", "--json",
                     *given]) == 0
        assert loaded == [str(policy), fallback]
        assert json.loads(capsys.readouterr().out)["controller"] == str(policy)
    (tmp_path / "fit" / "pid.json").unlink()
    assert main(["eval", "--controller", str(policy), "--episodes", "1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fcemu: error: ") and err.count("\n") == 1
    assert f"names its fallback PID {tmp_path / 'fit' / 'pid.json'}, which is missing" in err
