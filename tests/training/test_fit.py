import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fcemu.cli import main
from fcemu.evaluation.bar import ERROR_RATIO_BAR, SMOOTHNESS_BAR, airframe_bar_verdict
from fcemu.evaluation.metrics import compute_metrics
from fcemu.evaluation.runner import EvalConfig, run_controller
from fcemu.firmware.controllers import load_controller
from fcemu.firmware.neural import NeuralRateController
from fcemu.firmware.pid_controller import PRESET_DIR, PIDRateController
from fcemu.sim_bridge.airframe import AIRFRAME_DIR, load_airframe
from fcemu.sim_bridge.airframe_spec import airframe_spec
from fcemu.sitl.sitl import build_sitl
from fcemu.training.distill_teacher import DistillError, make_teacher
from fcemu.training.fit import (
    ERROR_ROOM,
    ERROR_TIE,
    STUDENT_MOTOR_MARGIN,
    STUDENT_SMOOTHING,
    STUDENT_STEPS,
    TEACHER_SPEEDS,
    FitOptions,
    first_teacher,
    shipped_pid,
    student_kind,
    taught_student,
    teacher_speed_stage,
)
from fcemu.training.fit_report import command_line
from fcemu.training.inversion_teacher import DAMPING

pytestmark = pytest.mark.no_wall_clock


def test_a_small_fit_writes_the_pid_the_policy_and_the_report(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    out = tmp_path / "fit"
    code = main(["fit", "--airframe", "racer5", "--tune", "--out", str(out), "--episodes", "2",
                 "--tune-budget-s", "10", "--rounds", "1", "--steps", "40", "--envs", "4", "--fit-steps",
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
    assert summary["student"]["teacher"] == f"inversion:{speed['lag_multiple']:g}"
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
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 4 and all(line.startswith("fcemu: error: fit:") for line in err)
    assert not (tmp_path / "x").exists()


def test_the_teacher_s_damping_reaches_the_teacher_and_the_command_line():
    teacher = make_teacher("inversion:0.2:0.4", "crazyflie")
    assert teacher.damping == 0.4 and teacher.time_constant[0] == pytest.approx(0.2 * teacher.model.lag_s)
    assert make_teacher("inversion:0.2", "crazyflie").damping == DAMPING
    with pytest.raises(DistillError, match="damping ratio must be > 0"):
        make_teacher("inversion:0.2:-1", "crazyflie")
    opts = FitOptions("crazyflie", "runs/x", lag_multiple=0.2, damping=0.4)
    assert command_line(opts).endswith("--lag-multiple 0.2 --damping 0.4 --tune")  # no --pid: it tuned


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


def test_the_first_teacher_is_the_smoothest_of_least_error_unless_it_rises_later_than_the_pid():
    def teacher(multiple: float, error: float, rise: float) -> dict:
        return {"lag_multiple": multiple, "error_sum": error, "smoothness": 1.0, "rise_ms": [rise, rise]}

    room = (ERROR_RATIO_BAR - ERROR_ROOM) * 100.0  # the PID's Error sum 100
    flown = [teacher(0.5, room + 6.0, 50.0), teacher(0.35, room - 2.0, 41.0),
             teacher(0.18, room - 2.0 + 0.5 * ERROR_TIE * room, 39.0), teacher(0.13, room - 0.5, 38.0),
             teacher(0.1, room + 1.0, 37.0)]
    rises = {"error_sum": 100.0, "rise_ms": [41.0, 41.0]}
    assert first_teacher(flown, rises)["lag_multiple"] == 0.35  # 0.18 ties it on Error; 0.35 rises in time
    late = {"error_sum": 100.0, "rise_ms": [40.0, 41.0]}
    assert first_teacher(flown, late)["lag_multiple"] == 0.13  # the fastest with room under the line
    assert first_teacher(flown, {"error_sum": 90.0, "rise_ms": [40.0, 41.0]})["lag_multiple"] == 0.35


def test_student_kind_follows_the_sensors() -> None:
    """A twin whose gyro or ESC telemetry is noisy, vibrating, delayed or lossy gets a student of
    sensed history (its own admission ratio and steps); the nominal twin one that reads what its
    teacher reads."""
    assert student_kind(load_airframe("iris")) == "exact"
    assert student_kind(load_airframe("iris_realistic")) == "sensed"
    assert set(STUDENT_SMOOTHING) == set(STUDENT_STEPS) == {"exact", "sensed"}


def test_speed_stage_admits_by_the_kind_of_student(tmp_path) -> None:
    """On a twin with noisy, delayed sensors the teachers admitted are those within the bar's motor
    line over a sensed student's smoothing, not an exact student's: the stage's order follows it."""
    opts = FitOptions("iris_realistic", str(tmp_path), episodes=2, jobs=1, progress=False)
    speed = teacher_speed_stage(opts, Path(str(PRESET_DIR / "pid_iris.json")), log=lambda line: None)
    assert speed["student"] == "sensed"
    limit = SMOOTHNESS_BAR / STUDENT_SMOOTHING["sensed"] * speed["pid_smoothness"]
    admitted = [f for f in speed["flown"] if f["smoothness"] <= limit] or speed["flown"][:1]
    first = first_teacher(admitted, {"error_sum": speed["pid_error_sum"], "rise_ms": speed["pid_rise_ms"]})
    slower = sorted(f["lag_multiple"] for f in admitted if f["lag_multiple"] > first["lag_multiple"])
    assert speed["order"] == [first["lag_multiple"], *slower]
    assert STUDENT_SMOOTHING["sensed"] > STUDENT_SMOOTHING["exact"]
