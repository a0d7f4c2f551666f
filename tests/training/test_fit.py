import argparse
import json
import re
import shlex
import subprocess
import sys
from dataclasses import replace
from itertools import product
from pathlib import Path

import numpy as np
import pytest

from fcemu.cli import build_parser, main
from fcemu.evaluation.bar import SMOOTHNESS_BAR, airframe_bar_verdict
from fcemu.evaluation.metrics import compute_metrics
from fcemu.evaluation.runner import EvalConfig, run_controller
from fcemu.firmware.controllers import load_controller
from fcemu.firmware.neural import NeuralRateController
from fcemu.firmware.pid_controller import PRESET_DIR, PIDRateController
from fcemu.sim_bridge.airframe import AIRFRAME_DIR
from fcemu.sim_bridge.airframe_spec import airframe_spec
from fcemu.sitl.sitl import build_sitl
from fcemu.training.distill_teacher import DistillError, make_teacher
from fcemu.training.fit import STUDENT_MOTOR_MARGIN, student_smoothness, taught_student
from fcemu.training.fit_options import FitOptions, shipped_pid
from fcemu.training.fit_report import command_line
from fcemu.training.fit_teacher import (
    BRAKING_CHOICES,
    ERROR_TIE,
    STUDENT_SMOOTHING,
    TEACHER_SPEEDS,
    YAW_FIRST_CHOICES,
    first_teacher,
    more_damped_taken,
    shape_admitted,
)
from fcemu.training.inversion_teacher import BRAKING_SHARE, DAMPING
from fcemu.training.options import command_line as options_command_line
from fcemu.training.options import from_args
from fcemu.training.tune_options import TuneOptions

pytestmark = pytest.mark.no_wall_clock


def test_a_small_fit_writes_the_pid_the_policy_and_the_report(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    out = tmp_path / "fit"
    code = main(["fit", "--airframe", "racer5", "--tune", "--out", str(out), "--episodes", "2",
                 "--tune-budget-s", "2", "--rounds", "1", "--steps", "40", "--envs", "4", "--fit-steps",
                 "20", "--net-arch", "8", "--jobs", "1", "--no-mcu", "--seed", "5", "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    summary = json.loads(captured.out)
    assert "fitting the policy to the model-based teacher" in captured.err
    # each stage said as it starts, with the time so far and an estimate of the time left
    stages = [line for line in captured.err.splitlines() if line.startswith("[")]
    assert [line.split("] ")[1].split()[0] for line in stages] == ["tuning", "PID:", "choosing", "fitting",
                                                                   "policy"]
    assert all(re.search(r"; (about [\d a-z]+ left, an estimate|less than a second left)$", line)
               for line in stages), stages
    for name in ("pid.json", "tune.json", "policy.onnx", "fit.json", "report.md"):
        assert (out / name).is_file(), name
    assert json.loads((out / "fit.json").read_text()) == summary
    assert summary["student"]["inputs"] == 10
    assert set(summary["time_s"]) == {"tune", "teacher", "policy", "check", "total"}
    speed = summary["student"]["speed"]
    assert speed["commands"] == 2
    assert [f["lag_multiple"] for f in speed["flown"]] == list(TEACHER_SPEEDS)
    # taught first: `first_teacher` of the admitted teachers; then slower ones while the student is rough
    assert speed["student"] == "exact"
    limit = SMOOTHNESS_BAR / STUDENT_SMOOTHING["exact"] * speed["pid_smoothness"]
    admitted = [f for f in speed["flown"] if f["smoothness"] <= limit] or speed["flown"][:1]
    pid = {"error_sum": speed["pid_error_sum"], "rise_ms": speed["pid_rise_ms"]}
    first = first_teacher(admitted, pid)["lag_multiple"]
    slower = sorted(f["lag_multiple"] for f in admitted if f["lag_multiple"] > first)
    assert speed["order"] == [first, *slower]
    tried = speed["tried"]
    assert [f["lag_multiple"] for f in tried] == speed["order"][:len(tried)]
    assert speed["lag_multiple"] == tried[-1]["lag_multiple"]
    rough = [f["student_smoothness"] > STUDENT_MOTOR_MARGIN * SMOOTHNESS_BAR * speed["pid_smoothness"]
             for f in tried]
    assert all(rough[:-1]) and (not rough[-1] or len(tried) == len(speed["order"]))
    # its shape: every other pair flown at that speed, the least Error admitted where it beats the
    # first teacher's past the tie; then in the teacher's name and the command line
    without = next(f for f in speed["flown"] if f["lag_multiple"] == first)
    pid["peak_pct"] = speed["pid_peak_pct"]
    shapes = speed["shapes"]
    assert {(f["yaw_first"], f["braking"]) for f in shapes} == set(
        product(YAW_FIRST_CHOICES, BRAKING_CHOICES)) - {(0.0, BRAKING_SHARE)}
    assert all(f["admitted"] == shape_admitted(f, without, pid, limit) for f in shapes)
    best = min((f for f in shapes if f["admitted"]), key=lambda f: f["error_sum"], default=None)
    if best is None or best["error_sum"] >= (1 - ERROR_TIE) * without["error_sum"]:
        best = {"yaw_first": 0.0, "braking": BRAKING_SHARE}
    assert (speed["yaw_first"], speed["braking"]) == (best["yaw_first"], best["braking"])
    # then the chosen shape more damped, taken where admitted, tied on Error and lower at its highest Peak
    pair = (best["yaw_first"], best["braking"])
    chosen = next((f for f in shapes if (f["yaw_first"], f["braking"]) == pair), without)
    (damped,) = speed["dampings"]
    assert damped["admitted"] == shape_admitted(damped, without, pid, limit)
    taken = damped["admitted"] and more_damped_taken(damped, chosen)
    assert speed["damping"] == (damped["damping"] if taken else DAMPING)
    taught = make_teacher(summary["student"]["teacher"], "racer5")
    assert (taught.yaw_first, taught.braking, taught.damping) == (speed["yaw_first"], speed["braking"],
                                                                  speed["damping"])
    assert f"--yaw-first {speed['yaw_first']:g} --braking {speed['braking']:g}" in summary["command"]
    check = summary["check"]
    assert check["seed"] == 6 and check["bound_sum"] > 0.0 and check["mcu_us_f405"] is None
    episodic = check["tasks"]["episodic"]["bar"]
    assert set(episodic["checks"]) == {"error_ratio", "times_bound", "success", "peak", "smoothness", "rise",
                                       "mcu"}
    assert episodic["unjudged"] == ["mcu"] and check["tasks"]["inflight"]["bar"]["times_bound"] is None
    assert summary["meets_bar"] == all(t["bar"]["meets_bar"] for t in check["tasks"].values())
    report = (out / "report.md").read_text()
    assert "fcemu fit --airframe racer5" in report and "Success %" in report
    # the check's flights drawn: the policy's step responses beside the PID's, linked from the report
    assert check["step_plot"] == "step_response.png"
    assert "![Step responses: the policy and the PID](step_response.png)" in report
    assert (out / "step_response.png").read_bytes().startswith(b"\x89PNG")
    assert "fcemu bench mcu" in report and "not measured" in report and "motor lags" in report
    assert f"fcemu sitl --airframe racer5 --controller {out / 'policy.onnx'}   #" in report  # no --fallback
    # the policy carries its airframe: flown on it by the firmware, refused on another's envelope
    policy = NeuralRateController(out / "policy.onnx", airframe=airframe_spec("racer5"))
    assert policy.spec.fields == ("rate_error", "rotor_speed", "rate")
    # and the SITL flies it over the fit's own PID, not the shipped racer tune
    fitted = PIDRateController.from_dict(json.loads((out / "pid.json").read_text())).gains
    assert fitted != load_controller("pid:racer5").gains
    sitl = build_sitl(str(out / "policy.onnx"), rig="rig", realtime=False, airframe="racer5",
                      fallback=f"pid:{out / 'pid.json'}")
    assert sitl.selected == "neural" and sitl.loop.controllers["pid"].gains == fitted
    # the policy names that PID, beside it, as its fallback: flown so without --fallback
    assert policy.metadata["fallback"] == "pid.json"
    named = build_sitl(str(out / "policy.onnx"), rig="rig", realtime=False, airframe="racer5")
    assert named.loop.controllers["pid"].gains == fitted
    for fallback, code in ((f"pid:{out / 'pid.json'}", 0), (f"pid:{out / 'missing.json'}", 2)):
        done = subprocess.run([sys.executable, "-m", "fcemu", "sitl", "--airframe", "racer5", "--rig", "rig",
                               "--controller", str(out / "policy.onnx"), "--fallback", fallback,
                               "--no-mavlink", "--speed", "max", "--duration", "0.3", "--quiet"],
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == code, done.stderr
        assert code == 0 or (done.stderr.startswith("fcemu: error: ") and done.stderr.count("\n") == 1)


def test_the_airframe_bar_takes_the_pids_own_success_and_the_bound():
    cfg = EvalConfig(episodes=3, seed=4, airframe="racer5")
    pid = compute_metrics(run_controller("pid", cfg, progress=False))
    same = airframe_bar_verdict(pid, pid, bound_sum=None)
    assert same["checks"]["error_ratio"] is False and same["checks"]["success"] and same["checks"]["rise"]
    assert same["checks"]["times_bound"] is None and same["unjudged"] == ["times_bound", "mcu"]
    error = same["pid_error_sum"]
    assert airframe_bar_verdict(pid, pid, bound_sum=error / 1.25)["checks"]["times_bound"] is False
    assert airframe_bar_verdict(pid, pid, bound_sum=error / 1.15)["checks"]["times_bound"] is True
    assert airframe_bar_verdict(pid, pid, None, mcu_us=260.0)["checks"]["mcu"] is False
    assert np.isclose(same["error_ratio"], 1.0)


def test_a_shipped_airframe_is_fitted_against_its_shipped_pid_and_a_file_is_tuned(
        monkeypatch: pytest.MonkeyPatch, untuned_airframe: Path) -> None:
    from fcemu.sim_bridge import airframe

    assert shipped_pid("racer5") == str(PRESET_DIR / "pid_racer5.json")
    assert shipped_pid("iris_realistic") == str(PRESET_DIR / "pid_iris.json")  # a variant flies its base's
    assert shipped_pid(str(AIRFRAME_DIR / "racer5.json")) is None  # a file is tuned, whatever its name
    monkeypatch.setattr(airframe, "AIRFRAME_DIR", untuned_airframe.parent)  # my_quad as if shipped
    assert shipped_pid("my_quad") is None  # none ships: the fit tunes one


def test_fit_refuses_a_bad_airframe_and_a_bad_budget_in_one_line(tmp_path, capsys):
    assert main(["fit", "--airframe", "no_such_quad", "--out", str(tmp_path / "x")]) == 2
    assert main(["fit", "--airframe", "iris", "--out", str(tmp_path / "x"), "--tune-budget-s", "0"]) == 2
    assert main(["fit", "--airframe", "iris", "--out", str(tmp_path / "x"), "--damping", "0"]) == 2
    assert main(["fit", "--airframe", "iris", "--out", str(tmp_path / "x"), "--pid", "iris", "--tune"]) == 2
    assert main(["fit", "--airframe", "iris", "--out", str(tmp_path / "x"), "--yaw-first", "1.5"]) == 2
    assert main(["fit", "--airframe", "iris", "--out", str(tmp_path / "x"), "--braking", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 6 and all(line.startswith("fcemu: error: fit:") for line in err)
    assert not (tmp_path / "x").exists()


def test_fit_refuses_an_airframe_whose_props_spin_out_before_any_work(tmp_path, capsys):
    raw = json.loads((AIRFRAME_DIR / "racer5.json").read_text())
    for motor in raw["motors"]:
        motor["spin"] = {"cw": "ccw", "ccw": "cw"}[motor["spin"]]
    out_quad = tmp_path / "out_quad.json"
    out_quad.write_text(json.dumps(raw))
    assert airframe_spec(str(out_quad)).props_out
    assert main(["fit", "--airframe", str(out_quad), "--out", str(tmp_path / "x"), "--tune"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fcemu: error: fit: ") and err.count("\n") == 1
    assert "props spin out" in err and "a policy is made for props in" in err
    assert not (tmp_path / "x").exists()


def test_the_teacher_s_damping_reaches_the_teacher_and_the_command_line():
    teacher = make_teacher("inversion:0.2:0.4", "crazyflie")
    assert teacher.damping == 0.4 and teacher.time_constant[0] == pytest.approx(0.2 * teacher.model.lag_s)
    assert make_teacher("inversion:0.2", "crazyflie").damping == DAMPING
    with pytest.raises(DistillError, match="damping ratio must be > 0"):
        make_teacher("inversion:0.2:-1", "crazyflie")
    opts = FitOptions(airframe="crazyflie", out="runs/x", lag_multiple=0.2, damping=0.4)
    assert command_line(opts).endswith("--lag-multiple 0.2 --damping 0.4 --tune")  # no --pid: it tuned
    # and the share of yaw served first, an empty field taking the default
    first = make_teacher("inversion:0.2::0.3", "crazyflie")
    assert first.yaw_first == 0.3 and first.damping == DAMPING
    assert make_teacher("inversion", "iris").yaw_first == 0.0
    braking = make_teacher("inversion:0.2:::0.3", "crazyflie")
    assert (braking.yaw_first, braking.braking) == (0.0, 0.3) and first.braking == BRAKING_SHARE
    for bad, why in (("inversion:0.2::1.5", "share of yaw"), ("inversion:0.2:::0", "braking share"),
                     ("inversion:0.2:0.7:0.3:0.3:1", "at most four")):
        with pytest.raises(DistillError, match=why):
            make_teacher(bad, "crazyflie")
    assert command_line(replace(opts, yaw_first=0.3, braking=0.2)).endswith(
        "--damping 0.4 --yaw-first 0.3 --braking 0.2 --tune")


def test_a_student_rougher_than_the_bar_is_taught_again_by_the_next_slower_teacher(tmp_path):
    out = tmp_path / "fit"
    out.mkdir()
    (out / "pid.json").write_text(json.dumps(load_controller("pid:racer5").to_dict()))
    opts = FitOptions(airframe="racer5", out=str(out), seed=5, episodes=2, rounds=1, steps=40, envs=4,
                      fit_steps=20, net_arch=(8,), jobs=1, mcu=False, progress=False)
    speed = {"lag_multiple": 0.35, "order": [0.35, 0.5], "pid_smoothness": 1e-6}  # every student too rough
    lines: list[str] = []
    student = taught_student(opts, speed, out, lines.append)
    taught = student["speed"]
    assert [f["lag_multiple"] for f in taught["tried"]] == [0.35, 0.5] and taught["lag_multiple"] == 0.5
    assert all(f["student_smoothness"] > 0.0 for f in taught["tried"])
    assert student["teacher"] == "inversion:0.5" and taught["order"] == [0.35, 0.5]
    assert speed == {"lag_multiple": 0.35, "order": [0.35, 0.5], "pid_smoothness": 1e-6}  # as given
    assert "the next slower teacher" in lines[0] and "next slower" not in lines[1]


def test_a_student_of_sensors_is_judged_against_the_pid_on_its_own_twin(tmp_path):
    """Where the sensors are not the truth, the PID's roughness the student is held to is the PID's on
    the airframe as the check flies it (noise on), not the nominal twin's the speed stage measured."""
    out = tmp_path / "fit"
    out.mkdir()
    (out / "pid.json").write_text(json.dumps(load_controller("pid:iris").to_dict()))
    opts = FitOptions(airframe="iris_realistic", out=str(out), seed=5, episodes=2, rounds=1, steps=40, envs=4,
                      fit_steps=20, net_arch=(8,), jobs=1, mcu=False, progress=False)
    speed = {"lag_multiple": 0.5, "order": [0.5], "pid_smoothness": 1e-6}  # as if nothing could pass
    taught = taught_student(opts, speed, out, lambda _line: None)["speed"]["tried"]
    on_its_twin = student_smoothness(opts, f"pid:{out / 'pid.json'}", out / "pid.json", True)
    assert taught[0]["pid_smoothness"] == on_its_twin > 1.0


def test_fit_takes_the_pid_fcemu_tune_wrote_for_the_airframe_in_its_folder(tmp_path: Path,
                                                                           untuned_airframe: Path) -> None:
    import json

    from fcemu.training.fit import tuned_in

    untuned = str(untuned_airframe)
    assert tuned_in(tmp_path, untuned) is None  # nothing there: it tunes
    (tmp_path / "pid.json").write_text(json.dumps({"pid": {}, "tuning": {"airframe": "my_quad"}}))
    assert tuned_in(tmp_path, untuned) == str(tmp_path / "pid.json")
    assert tuned_in(tmp_path, "racer5") is None  # tuned for another airframe
    (tmp_path / "pid.json").write_text("not json")
    assert tuned_in(tmp_path, untuned) is None


def _command_parser(name: str) -> argparse.ArgumentParser:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


@pytest.mark.parametrize("name", ["fit", "tune"])
def test_every_option_of_fit_and_tune_shows_its_default(name: str) -> None:
    for action in _command_parser(name)._actions:
        if not isinstance(action, argparse._HelpAction):
            assert "(default" in action.help or "(required)" in action.help, action.option_strings


def test_the_command_lines_repeat_the_options_and_parse_back_to_them() -> None:
    opts = FitOptions(airframe="x500", out="runs/x", steps=1500, net_arch=(32, 16), braking=0.3, pid="p.json",
                      jobs=3, mcu=False, progress=False)
    line = command_line(opts)
    assert line == ("fcemu fit --airframe x500 --out runs/x --seed 2018 --episodes 50 --tune-budget-s 480 "
                    "--rounds 6 --steps 1500 --envs 64 --fit-steps 3000 --net-arch 32 16 --braking 0.3 "
                    "--pid p.json")
    args = build_parser().parse_args([*shlex.split(line)[1:], "--jobs", "3", "--no-mcu"])
    assert from_args(FitOptions, args, progress=False) == opts
    tune = TuneOptions(airframe="iris", jobs=2)
    line = options_command_line("fcemu tune", tune)
    assert line == ("fcemu tune --airframe iris --seed 2018 --episodes 50 --check-episodes 50 --rounds 12 "
                    "--budget-s 570 --jobs 2")
    args = build_parser().parse_args([*shlex.split(line)[1:], "--out", "o"])
    assert from_args(TuneOptions, args) == tune
