import json
import subprocess
import sys
from dataclasses import replace
from itertools import product

import numpy as np
import pytest

from fcemu.cli import main
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
from fcemu.training.fit import STUDENT_MOTOR_MARGIN, FitOptions, shipped_pid, taught_student
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
    assert "fcemu bench mcu" in report and "not measured" in report and "motor lags" in report
    assert f"--controller {out / 'policy.onnx'} --fallback pid:{out / 'pid.json'}" in report
    # the policy carries its airframe: flown on it by the firmware, refused on another's envelope
    policy = NeuralRateController(out / "policy.onnx", airframe=airframe_spec("racer5"))
    assert policy.spec.fields == ("rate_error", "rotor_speed", "rate")
    # and the SITL flies it over the fit's own PID, not the shipped racer tune
    fitted = PIDRateController.from_dict(json.loads((out / "pid.json").read_text())).gains
    assert fitted != load_controller("pid:racer5").gains
    sitl = build_sitl(str(out / "policy.onnx"), rig="rig", realtime=False, airframe="racer5",
                      fallback=f"pid:{out / 'pid.json'}")
    assert sitl.selected == "neural" and sitl.loop.controllers["pid"].gains == fitted
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


def test_a_shipped_airframe_is_fitted_against_its_shipped_pid_and_a_file_is_tuned():
    assert shipped_pid("racer5") == str(PRESET_DIR / "pid_racer5.json")
    assert shipped_pid("iris_realistic") == str(PRESET_DIR / "pid_iris.json")  # a variant flies its base's
    assert shipped_pid("x500") is None  # none ships: the fit tunes one
    assert shipped_pid(str(AIRFRAME_DIR / "racer5.json")) is None  # a file is tuned, whatever its name


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


def test_the_teacher_s_damping_reaches_the_teacher_and_the_command_line():
    teacher = make_teacher("inversion:0.2:0.4", "crazyflie")
    assert teacher.damping == 0.4 and teacher.time_constant[0] == pytest.approx(0.2 * teacher.model.lag_s)
    assert make_teacher("inversion:0.2", "crazyflie").damping == DAMPING
    with pytest.raises(DistillError, match="damping ratio must be > 0"):
        make_teacher("inversion:0.2:-1", "crazyflie")
    opts = FitOptions("crazyflie", "runs/x", lag_multiple=0.2, damping=0.4)
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
    opts = FitOptions("racer5", str(out), seed=5, episodes=2, rounds=1, steps=40, envs=4, fit_steps=20,
                      net_arch=(8,), jobs=1, mcu=False, progress=False)
    speed = {"lag_multiple": 0.35, "order": [0.35, 0.5], "pid_smoothness": 1e-6}  # every student too rough
    lines: list[str] = []
    student = taught_student(opts, speed, out, lines.append)
    taught = student["speed"]
    assert [f["lag_multiple"] for f in taught["tried"]] == [0.35, 0.5] and taught["lag_multiple"] == 0.5
    assert all(f["student_smoothness"] > 0.0 for f in taught["tried"])
    assert student["teacher"] == "inversion:0.5" and taught["order"] == [0.35, 0.5]
    assert speed == {"lag_multiple": 0.35, "order": [0.35, 0.5], "pid_smoothness": 1e-6}  # as given
    assert "the next slower teacher" in lines[0] and "next slower" not in lines[1]


def test_fit_takes_the_pid_fcemu_tune_wrote_for_the_airframe_in_its_folder(tmp_path) -> None:
    import json

    from fcemu.training.fit import tuned_in

    assert tuned_in(tmp_path, "x500") is None  # nothing there: it tunes
    (tmp_path / "pid.json").write_text(json.dumps({"pid": {}, "tuning": {"airframe": "x500"}}))
    assert tuned_in(tmp_path, "x500") == str(tmp_path / "pid.json")
    assert tuned_in(tmp_path, "racer5") is None  # tuned for another airframe
    (tmp_path / "pid.json").write_text("not json")
    assert tuned_in(tmp_path, "x500") is None
