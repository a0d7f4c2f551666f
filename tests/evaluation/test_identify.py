"""`fcemu identify`: the twin an identification flight was flown on comes back from its log,
and a log that cannot be identified is one line and exit 2."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fcemu.cli import main
from fcemu.evaluation.flight_logs import read_flight_log
from fcemu.evaluation.identify_airframe import identified_document, identify
from fcemu.evaluation.identify_flight import fly_identification
from fcemu.firmware.controller import RateSetpoint
from fcemu.firmware.loop import Command
from fcemu.sim_bridge.airframe import load_airframe
from fcemu.sitl.sitl import build_sitl
from fcemu.sitl.ulog_writer import TOPICS, ULogRecorder

TRUE = "iris_realistic"  # every effect a log shows is on: delays, noise, vibration, damping, battery sag


@pytest.fixture(scope="module")
def flown(tmp_path_factory):
    out = tmp_path_factory.mktemp("fly")
    assert main(["identify", "--fly", TRUE, "--out", str(out), "--json"]) == 0
    return out


def _effectiveness(airframe) -> np.ndarray:
    inertia, m = airframe.inertia(), airframe.motor
    return np.array([m.kf / inertia[0], m.kf / inertia[1], m.kf * m.km / inertia[2]])


def test_the_flight_s_log_gives_back_the_twin_it_was_flown_on(flown) -> None:
    assert {"flight.ulg", "airframe.json", "report.md", "rates.png"} <= {p.name for p in flown.iterdir()}
    identified, true = load_airframe(flown / "airframe.json"), load_airframe(TRUE)
    assert identified.motor.tau_up == pytest.approx(true.motor.tau_up, rel=0.05)
    assert identified.motor.tau_down == pytest.approx(true.motor.tau_down, rel=0.05)
    assert np.allclose(_effectiveness(identified), _effectiveness(true), rtol=0.02)
    assert (identified.esc_delay_ticks, identified.gyro_delay_ticks) == (true.esc_delay_ticks,
                                                                        true.gyro_delay_ticks)
    assert identified.gyro_noise_std == pytest.approx(true.gyro_noise_std, rel=0.1)
    assert np.allclose(identified.gyro_vibration, true.gyro_vibration, rtol=0.1)
    assert identified.hover_throttle() == pytest.approx(true.hover_throttle(), abs=0.01)
    assert np.allclose(np.array(identified.rate_damping) / identified.inertia(),
                       np.array(true.rate_damping) / true.inertia(), rtol=0.1)
    doc = json.loads((flown / "airframe.json").read_text())
    assert doc["sources"]["motor.time_constant_up_s"].startswith("identified from flight.ulg")
    assert "95 % interval" in doc["sources"]["motor.time_constant_up_s"]
    assert doc["sources"]["base_mass_kg"].startswith("from the base airframe iris")
    assert doc["effects"]["gyro_delay_ticks"]["source"].startswith("identified from flight.ulg")
    report = (flown / "report.md").read_text()
    assert "| motor time constant up |" in report and "![measured and predicted rates](rates.png)" in report


def test_without_esc_rpm_the_time_constants_come_from_the_rate_response(tmp_path) -> None:
    true = load_airframe("iris")
    path = fly_identification(true, "pid", axis_s=3.0).write(
        tmp_path / "no_rpm.ulg", topics=[t for t in TOPICS if t != "esc_status"])
    log = read_flight_log(path)
    assert log.rotor_speed is None
    ident = identify(log, true, "iris")
    assert not ident.motors.from_rpm
    assert ident.motors.tau_up.value == pytest.approx(true.motor.tau_up, rel=0.15)
    assert ident.motors.tau_up.low <= ident.motors.tau_up.value <= ident.motors.tau_up.high
    doc = identified_document(ident, "no_rpm")
    assert "no ESC rpm" in doc["sources"]["motor.thrust_coefficient_N_per_rad_s2"]


class _Held:
    """A commander holding one command: the vehicle on the ground, armed or not."""

    def __init__(self, armed: bool, throttle: float) -> None:
        self.cmd = Command(armed, RateSetpoint(np.zeros(3), throttle), "pid")

    def command(self, t_us: int, frame) -> Command:
        return self.cmd


def _ground_log(path, armed: bool) -> str:
    recorder = ULogRecorder()
    sitl = build_sitl("pid", rig="free", realtime=False, commander=_Held(armed, 0.0), sinks=[recorder])
    sitl.loop.run(1.5)
    return str(recorder.write(path))


def _log_without(flown, tmp_path, topic: str) -> str:
    recorder = fly_identification(load_airframe("iris"), "pid", axis_s=0.6)
    return str(recorder.write(tmp_path / f"no_{topic}.ulg", topics=[t for t in TOPICS if t != topic]))


@pytest.mark.parametrize(("case", "line"), [
    ("text", "not a PX4 ULog"),
    ("header only", "ends at byte 300 before any logged data: no flight to read (cut off?)"),
    ("no gyro", "no vehicle_angular_velocity topic"),
    ("no motors", "no actuator_motors or actuator_outputs topic"),
    ("disarmed", "never armed (actuator_armed): a ground-only log"),
    ("on the ground", "never reach 0.3 rad/s (peak 0.00, 0.00, 0.00): a ground-only"),
])
def test_a_log_that_cannot_be_identified_is_one_line_and_exit_2(case, line, flown, tmp_path, capsys) -> None:
    if case == "text":
        log = tmp_path / "notes.ulg"
        log.write_text("not a log\n")
    elif case == "header only":
        log = tmp_path / "cut.ulg"
        log.write_bytes((flown / "flight.ulg").read_bytes()[:300])  # cut inside its format definitions
    elif case == "no gyro":
        log = _log_without(flown, tmp_path, "vehicle_angular_velocity")
    elif case == "no motors":
        recorder = fly_identification(load_airframe("iris"), "pid", axis_s=0.6)
        log = recorder.write(tmp_path / "no_motors.ulg",
                             topics=[t for t in TOPICS if t not in ("actuator_motors", "actuator_outputs")])
    else:
        log = _ground_log(tmp_path / "ground.ulg", armed=case != "disarmed")
    assert main(["identify", str(log), "--out", str(tmp_path / "out.json")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"fcemu: error: {log}: ") and line in err and err.count("\n") == 1
    assert not (tmp_path / "out.json").exists()


def test_a_log_cut_off_mid_message_is_read_up_to_the_cut_and_says_so(flown, tmp_path, capsys) -> None:
    whole = (flown / "flight.ulg").read_bytes()
    log = tmp_path / "cut.ulg"
    log.write_bytes(whole[:-7])  # the battery pulled while its last message was written
    assert main(["identify", str(log), "--out", str(tmp_path / "cut.json")]) == 0
    read = read_flight_log(log)
    cut = int(read.notes[0].split("read up to byte ")[1].split(" of ")[0])
    assert read.notes[0] == f"the log ends cut off (power lost?): read up to byte {cut} of {len(whole) - 7}"
    assert len(whole) - 7 - 200 < cut < len(whole) - 7
    assert read.notes[0] in (tmp_path / "report.md").read_text()
    assert read.notes[0] in json.loads((tmp_path / "cut.json").read_text())["source"]
    # cut far earlier, mid-flight: the flight before the cut is what is read
    (tmp_path / "earlier.ulg").write_bytes(whole[:len(whole) * 9 // 10 + 5])
    assert read_flight_log(tmp_path / "earlier.ulg").t[-1] < read.t[-1] - 1.0


def test_identify_takes_a_log_or_fly_not_both(tmp_path, capsys) -> None:
    assert main(["identify", "--out", str(tmp_path / "a.json")]) == 2
    assert "a LOG or --fly AIRFRAME, one of them" in capsys.readouterr().err


def test_perturb_seed_draws_the_flown_airframe_from_the_ranges_and_keeps_it(tmp_path) -> None:
    from fcemu.evaluation.identify_cli import _flown_airframe

    drawn = _flown_airframe("iris", 201, tmp_path)
    kept = load_airframe(tmp_path / "true_airframe.json")
    assert kept.name == drawn.name == "iris_perturbed_201"
    assert kept.motor == drawn.motor and np.allclose(kept.inertia(), drawn.inertia())
    assert (kept.esc_delay_ticks, kept.gyro_noise_std) == (drawn.esc_delay_ticks, drawn.gyro_noise_std)
    assert kept.motor.tau_up != load_airframe("iris").motor.tau_up
    assert _flown_airframe("iris", 201, tmp_path / "again").motor == drawn.motor  # the seed decides


def test_identify_log_writes_the_airframe_fly_wrote_and_its_report_beside_it(flown, tmp_path, capsys) -> None:
    out = tmp_path / "mine" / "quad.json"
    assert main(["identify", str(flown / "flight.ulg"), "--out", str(out)]) == 0
    assert "tau up" in capsys.readouterr().out
    mine, flown_doc = json.loads(out.read_text()), json.loads((flown / "airframe.json").read_text())
    assert mine["name"] == "quad" and mine["motor"] == flown_doc["motor"]
    assert mine["effects"] == flown_doc["effects"]
    assert (out.parent / "report.md").exists() and (out.parent / "rates.png").exists()
    assert load_airframe(out).inertia() == pytest.approx(load_airframe(flown / "airframe.json").inertia())


def test_pwm_outputs_stand_in_for_the_normalised_motor_commands(tmp_path) -> None:
    recorder = fly_identification(load_airframe("iris"), "pid", axis_s=0.6)
    both = read_flight_log(recorder.write(tmp_path / "both.ulg"))
    pwm_only = read_flight_log(recorder.write(tmp_path / "pwm.ulg", topics=[t for t in TOPICS
                                                                          if t != "actuator_motors"]))
    assert both.command_source == "actuator_motors" and pwm_only.command_source.startswith("actuator_outputs")
    assert np.allclose(both.command, pwm_only.command, atol=1e-6)


def test_esc_rpm_slower_than_the_gyro_is_left_out_and_said(tmp_path) -> None:
    from pyulog import ULog

    full = fly_identification(load_airframe("iris"), "pid", axis_s=0.6).write(tmp_path / "full.ulg")
    log = ULog(str(full))
    esc = log.get_dataset("esc_status")
    esc.data = {key: value[::10] for key, value in esc.data.items()}  # ESC telemetry at 100 Hz
    log.write_ulog(str(tmp_path / "slow_esc.ulg"))
    read = read_flight_log(tmp_path / "slow_esc.ulg")
    assert read.rotor_speed is None
    assert read.notes == ("esc_status at 100 Hz against the gyro's 1000 Hz is too slow for the motor lag: "
                          "its rpm is left out (log esc_status at the loop rate: docs/identify.md)",)


def test_the_yawing_doublets_give_the_yaw_inertia_and_moment_constant_a_rate_log_hid(tmp_path) -> None:
    from fcemu.evaluation.rate_boxes import gyro_coefficients

    out = tmp_path / "drawn"
    assert main(["identify", "--fly", "iris", "--perturb-seed", "206", "--out", str(out)]) == 0
    true, identified = load_airframe(out / "true_airframe.json"), load_airframe(out / "airframe.json")
    base = load_airframe("iris")
    coupling = {name: gyro_coefficients(a.inertia()) for name, a in
                (("true", true), ("identified", identified), ("base", base))}
    assert np.allclose(coupling["identified"], coupling["true"], rtol=0.15), coupling
    assert not np.allclose(coupling["base"], coupling["true"], rtol=0.15)  # the draw moved them
    assert identified.motor.km == pytest.approx(true.motor.km, rel=0.05)
    assert abs(base.motor.km / true.motor.km - 1) > 0.1
    doc = json.loads((out / "airframe.json").read_text())
    assert "gyroscopic coupling" in doc["sources"]["motor.moment_constant_m"]
    report = (out / "report.md").read_text()
    assert "| roll gyroscopic coupling |" in report and "k_M from it" in report
    assert "(the base's)" not in report


def test_rates_that_never_coupled_keep_the_base_s_moment_constant() -> None:
    from fcemu.evaluation.identify import Estimate
    from fcemu.evaluation.identify_airframe import yaw_inertia

    # I_xx 0.02, I_yy 0.03, I_zz 0.04: roll reads (0.03 − 0.04)/0.02, pitch (0.04 − 0.02)/0.03
    tight = yaw_inertia([0.02, 0.03], Estimate.normal(-0.5, 0.01), Estimate.normal(2 / 3, 0.01))
    assert tight is not None and tight.value == pytest.approx(0.04, rel=1e-9)
    assert yaw_inertia([0.02, 0.03], Estimate.normal(-0.5, 2.0), Estimate.normal(0.5, 2.0)) is None
