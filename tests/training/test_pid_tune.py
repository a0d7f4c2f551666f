import json
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fcemu.cli import main
from fcemu.evaluation.pid_carry_over import carried_over, iris_tune_carried_over
from fcemu.evaluation.runner import EvalConfig, run_controller
from fcemu.firmware.mixer import QuadXMixer
from fcemu.firmware.pid_controller import load_preset
from fcemu.sim_bridge.airframe import AIRFRAME_DIR, load_airframe
from fcemu.sim_bridge.tasks import episodic_commands
from fcemu.training.pid_search import Score
from fcemu.training.pid_tune import (
    SMOOTHNESS_CAP,
    cost,
    held_out_steps,
    knobs_for,
    loop_physics,
    settle_limits,
)
from fcemu.training.tune_options import TuneOptions


def test_loop_physics_follows_inertia_thrust_and_motor_lag():
    iris = load_airframe("iris")
    base = loop_physics(iris)
    assert np.all(base.authority > 0.0)
    heavy = loop_physics(iris.scaled(inertia=2.0))
    # The rotors' masses on the arms keep their inertia: doubling the body's divides B by less than 2.
    assert np.all(base.authority / heavy.authority > 1.5) and np.all(base.authority / heavy.authority < 2.0)
    slow = loop_physics(iris.scaled(tau_up=2.0, tau_down=2.0))
    assert slow.lag_s == pytest.approx(2.0 * base.lag_s)
    np.testing.assert_allclose(slow.authority, base.authority)
    # Thrust ×2 at the same weight: hover at 1/√2 of the rotor speed, the slope kf·ω ×√2.
    np.testing.assert_allclose(loop_physics(iris.scaled(kf=2.0)).authority, base.authority * np.sqrt(2.0))


def test_the_reference_airframe_starts_from_the_reference_tune_and_others_scale_by_physics():
    iris_preset = load_preset("iris")
    iris = loop_physics(load_airframe("iris"), QuadXMixer(**iris_preset["mixer"]))
    assert carried_over(iris_preset, iris, iris)["pid"] == iris_preset["pid"]
    slower = loop_physics(load_airframe("iris").scaled(inertia=2.0, tau_up=2.0, tau_down=2.0))
    start = carried_over(iris_preset, iris, slower)["pid"]
    gain = iris.authority / slower.authority
    np.testing.assert_allclose(start["kp"], np.array(iris_preset["pid"]["kp"]) * gain / 2.0, rtol=1e-5)
    np.testing.assert_allclose(start["ki"], np.array(iris_preset["pid"]["ki"]) * gain / 4.0, rtol=1e-5)
    np.testing.assert_allclose(start["kd"], np.array(iris_preset["pid"]["kd"]) * gain, rtol=1e-5)
    assert start["dterm_lowpass_hz"] == pytest.approx(iris_preset["pid"]["dterm_lowpass_hz"] / 2.0)
    limits = np.minimum(1.0, np.array(iris_preset["pid"]["pidsum_limit"]) * gain)
    np.testing.assert_allclose(start["pidsum_limit"], limits, rtol=1e-6)
    knobs = {k.name: k for k in knobs_for(iris, slower, iris_preset)}
    assert knobs["kp_roll"].lowest < start["kp"][0] / 5.0 < start["kp"][0] * 5.0 < knobs["kp_roll"].highest


def test_an_axis_gains_move_scales_its_terms_together_and_a_d_left_off_starts_where_physics_puts_it():
    iris_preset = load_preset("iris")
    iris = loop_physics(load_airframe("iris"), QuadXMixer(**iris_preset["mixer"]))
    knobs = {k.name: k for k in knobs_for(iris, iris, iris_preset)}
    up = knobs["gains_yaw"].moved(iris_preset, 2.0)["pid"]
    for key in ("kp", "ki", "kff"):
        assert up[key][2] == pytest.approx(2.0 * iris_preset["pid"][key][2], rel=1e-5)
        assert up[key][:2] == iris_preset["pid"][key][:2]
    assert up["kd"][2] == 0.0  # the axis's D is off, and moving its loop gain leaves it off
    assert knobs["kd_yaw"].moved(iris_preset, 1.0 / 1.4) is None
    on = knobs["kd_yaw"].moved(iris_preset, 1.4)["pid"]["kd"][2]
    pid = iris_preset["pid"]  # the roll's D to P ratio
    assert on == pytest.approx(pid["kp"][2] * pid["kd"][0] / pid["kp"][0], rel=1e-5)


def test_settle_limits_say_which_commands_no_controller_settles():
    commands = episodic_commands(2019, 50)
    iris = settle_limits(load_airframe("iris"), commands)
    assert iris["unsettleable_commands"] == {"roll": 0, "pitch": 0, "yaw": 0}
    weak_yaw = settle_limits(load_airframe("iris").scaled(km=0.05), commands)
    accel = weak_yaw["max_angular_acceleration_rad_s2"]["yaw"]
    assert accel == pytest.approx(0.05 * iris["max_angular_acceleration_rad_s2"]["yaw"], abs=0.01)
    largest = weak_yaw["largest_settleable_rad_s"]["yaw"]
    assert 0.5 * accel < largest < accel  # it must be reached by about half the window
    assert weak_yaw["unsettleable_commands"]["yaw"] == int((np.abs(commands[:, 2]) > largest).sum()) > 0


def _score(error: float = 100.0, smoothness: float = 2.0, success: float = 100.0) -> Score:
    three = np.ones(3)
    return Score(error * three, 40.0 * three, 110.0 * three, success * three, np.zeros(3), smoothness,
                 2.0 * three)


def test_cost_rewards_error_and_caps_motor_roughness_on_the_noisy_gyro():
    ref = _score()
    assert cost(_score(error=90.0), ref, True) < cost(ref, ref, True)
    assert cost(_score(success=98.0), ref, True) > cost(ref, ref, True) + 1.0
    rough = _score(smoothness=2.0 * (SMOOTHNESS_CAP + 0.1))
    assert cost(rough, ref, True) - cost(rough, ref, False) == pytest.approx(100.0 * 0.1)
    # a start quieter than the reference tune is allowed the reference's roughness, and only on the noisy gyro
    assert cost(rough, ref, True, floor_us=10.0) == cost(rough, ref, False, floor_us=10.0) - 0.25 * (
        rough.smoothness / ref.smoothness - rough.smoothness / 10.0)
    assert cost(rough, ref, True, floor_us=1.0) == cost(rough, ref, True)
    never = Score(ref.error, ref.rise_ms, ref.peak_pct, ref.success_pct, np.array([0, 1, 0]), 2.0,
                  ref.worst_settle_pct)
    assert cost(never, ref, False) == float("inf")
    # A start that never rises on some commands (physics may forbid them) is no wall: a candidate that
    # leaves no more of them is scored, one that leaves more is not.
    assert math.isfinite(cost(never, never, False)) and cost(ref, never, False) <= cost(never, never, False)
    worse = Score(ref.error, ref.rise_ms, ref.peak_pct, ref.success_pct, np.array([0, 2, 0]), 2.0,
                  ref.worst_settle_pct)
    assert cost(worse, never, False) == float("inf")
    nothing = Score(ref.error, np.array([40.0, np.nan, 40.0]), ref.peak_pct, ref.success_pct,
                    np.array([0, 50, 0]), 2.0, ref.worst_settle_pct)
    assert math.isfinite(cost(nothing, nothing, False))  # an axis on which no command rose


def test_a_small_tune_writes_a_preset_the_firmware_flies_and_beats_its_start(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    out = tmp_path / "tune"
    iris_file = str(AIRFRAME_DIR / "iris.json")  # a file, as a user's quad is
    code = main(["tune", "--airframe", iris_file, "--out", str(out), "--episodes", "3", "--check-episodes",
                 "1", "--rounds", "1", "--budget-s", "300", "--jobs", "1", "--seed", "5", "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    summary = json.loads(captured.out)
    assert "clean: start cost" in captured.err and "/300 s]" in captured.err
    # the budget is the whole tune's: the search's lines count on from the bound's solve time (both
    # in whole seconds as the lines print them)
    bound_lines = [line for line in captured.err.splitlines() if "] bound: " in line]
    first_search = next(line for line in captured.err.splitlines() if "/300 s]" in line)
    charged = float(f"{summary['time_s']['bound_charged']:.0f}")
    assert bound_lines and float(first_search.split("/")[0].strip("[ ")) >= charged
    for key in ("airframe", "cost_version", "physics", "stages", "tuning_set", "held_out", "meets_lines",
                "fails",
                "time_s"):
        assert key in summary
    clean = summary["stages"][0]
    assert clean["stage"] == "clean" and clean["cost"] < clean["start_cost"]
    held = summary["held_out"]
    assert held["seed"] == 6 and held["bound"]["sum"] > 0.0
    for key in ("error", "rise_ms", "peak_pct", "success_pct"):
        assert set(held["tuned"][key]) == {"roll", "pitch", "yaw"}
    assert held["tuned"]["smoothness_us"] > 0.0 and held["tuned_noisy_gyro"]["smoothness_us"] > 0.0
    times = held["tuned"]["error_sum"] / held["bound"]["sum"]
    assert held["tuned"]["times_bound"] == pytest.approx(times, 1e-3)
    assert set(held["lines"]) == {"error_times_bound", "success_pct", "smoothness_noisy_gyro_vs_allowance"}
    # the Iris is its own reference: its allowance is its start's roughness, the reference's own
    assert held["noise_allowance_us"] == pytest.approx(held["start_noisy_gyro"]["smoothness_us"], abs=0.002)
    preset = json.loads((out / "pid.json").read_text())
    assert preset["name"] == "pid_iris" and preset["tuning"]["cost_version"] == summary["cost_version"]
    assert json.loads((out / "tune.json").read_text())["held_out"] == held
    # the report shows the tuned PID's step responses on the held-out commands, as the check flew them
    assert summary["report"] == str(out / "tune_report.md") and "/tune_report.md in " in captured.err
    report = (out / "tune_report.md").read_text()
    assert "![Step responses of the tuned PID](tune_step_response.png)" in report
    assert f"--controller pid:{out / 'pid.json'}" in report and "| Error sum | " in report
    assert (out / "tune_step_response.png").read_bytes().startswith(b"\x89PNG")
    steps = held_out_steps(TuneOptions(airframe="iris", seed=5, check_episodes=1, jobs=1), preset)
    assert steps.n_episodes == 3  # one command an axis: here the only one, three times
    drawn = np.abs(steps.setpoint - steps.rate).sum(axis=1)[0]
    assert drawn == pytest.approx([held["tuned"]["error"][a] for a in ("roll", "pitch", "yaw")], abs=0.006)
    assert len(list((tmp_path / "cache" / "fcemu" / "bound").glob("*.json"))) == 1
    traces = run_controller(f"pid:{out / 'pid.json'}", EvalConfig(episodes=1, seed=6), progress=False)
    flown = np.abs(traces.setpoint - traces.rate).sum(axis=1)[0]
    assert flown.sum() == pytest.approx(held["tuned"]["error_sum"], abs=0.006)  # the JSON rounds to 0.01
    fit_takes_the_tune_for_its_airframe_alone(out, iris_file, tmp_path, monkeypatch, capsys)


def fit_takes_the_tune_for_its_airframe_alone(out: Path, iris_file: str, tmp_path: Path, monkeypatch,
                                              capsys) -> None:
    """`fcemu fit --out` the tune's folder flies the tune's PID for the airframe it was tuned for,
    named as the tune named it, by its shipped name or as a copy elsewhere, before the shipped tune;
    for an edited airframe it tunes anew."""
    from fcemu.firmware.errors import UserError
    from fcemu.training import fit

    raw = json.loads(Path(iris_file).read_text())
    (tmp_path / "elsewhere").mkdir()
    copy, heavier = tmp_path / "elsewhere" / "my_quad.json", tmp_path / "elsewhere" / "heavier.json"
    copy.write_text(json.dumps(raw, indent=4))
    heavier.write_text(json.dumps({**raw, "base_mass_kg": raw["base_mass_kg"] * 1.1}))
    tuning = json.loads((out / "pid.json").read_text())["tuning"]
    assert tuning["airframe"] == iris_file and len(tuning["airframe_sha256"]) == 64
    for airframe in (iris_file, "iris", str(copy)):
        assert fit.tuned_in(out, airframe) == str(out / "pid.json")
    assert fit.tuned_in(out, str(heavier)) is None

    def stop(opts, out, log):
        raise UserError(f"stopped before the bound; --pid {opts.pid}")

    monkeypatch.setattr(fit, "given_pid_stage", stop)
    tuned = out / "pid.json"
    before = tuned.read_bytes()
    assert main(["fit", "--airframe", "iris", "--out", str(out), "--no-mcu"]) == 2
    err = capsys.readouterr().err
    assert f"the PID tuned in {tuned} by fcemu tune: not tuned again" in err  # not the shipped pid_iris
    assert err.endswith(f"stopped before the bound; --pid {tuned}\n") and tuned.read_bytes() == before


@pytest.mark.parametrize("args, message", [
    (["--airframe", "no_such_frame"], "cannot load airframe"),
    (["--airframe", "iris", "--budget-s", "0"], "--budget-s must be > 0"),
])
def test_bad_input_is_one_line(tmp_path, capsys, args, message):
    assert main(["tune", "--out", str(tmp_path / "o"), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("fcemu: error:") and message in err and "\n" not in err


def test_an_out_that_cannot_be_written_is_one_line(tmp_path: Path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["tune", "--airframe", "iris", "--out", str(blocker / "sub")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("fcemu: error:") and "not a writable directory" in err and "\n" not in err


def test_a_props_out_airframe_starts_from_the_iris_tune_with_yaw_reversed() -> None:
    iris = load_airframe("iris")
    out = replace(iris, name="iris_out", spin=-iris.spin)
    start = iris_tune_carried_over(out)
    assert start["mixer"]["yaw_reversed"] and "yaw_reversed" not in iris_tune_carried_over(iris)["mixer"]
    assert start["pid"] == iris_tune_carried_over(iris)["pid"]  # the same physics, yaw mixed the other way


def test_a_cached_bound_is_charged_the_time_its_programmes_took(tmp_path, monkeypatch) -> None:
    """A tune's search gets the same time whether its bound is solved now or read from the cache."""
    from types import SimpleNamespace

    from fcemu.evaluation.bound import rig_constants
    from fcemu.training.pid_tune import cached_bounds

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    rig, commands = rig_constants("iris"), episodic_commands(3, 2)
    solved: list[int] = []

    def solve() -> list[SimpleNamespace]:
        solved.append(1)
        time.sleep(0.3)
        return [SimpleNamespace(bound=float(i), split=np.array([0.5, 0.3, 0.2]) * i) for i in (1, 2)]

    first, first_s = cached_bounds(rig, commands, solve)
    again, again_s = cached_bounds(rig, commands, solve)
    assert len(solved) == 1 and first_s >= 0.3 and again_s == first_s
    np.testing.assert_array_equal(first, again)
    np.testing.assert_array_equal(first[:, 0], [1.0, 2.0])
