"""`fcemu identify` on Betaflight's own blackbox: a short flight of Betaflight 4.6's SITL on the twin,
logged by Betaflight (blackbox_device VIRTUAL), read back as the arrays a ULog gives; and blackbox
logs that cannot be identified are one line and exit 2."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from fcemu.cli import main
from fcemu.evaluation.flight_logs import read_flight_log
from fcemu.evaluation.identify_blackbox import _rotor_speed
from fcemu.evaluation.identify_flight import _Excitation
from fcemu.sim_bridge.airframe import load_airframe
from fcemu.sim_bridge.twin import Twin
from fcemu.sitl.betaflight import BetaflightFlight
from fcemu.sitl.betaflight_process import BetaflightError, port_in_use, sitl_binary
from fcemu.sitl.betaflight_rc import RcMap

pytestmark = pytest.mark.quiet_machine

pytest.importorskip("orangebox", reason="the blackbox decoder is the extra fcemu[blackbox]")

DOUBLET = 2.0  # rad/s
HALF_S = 0.2


def _doublets(hover: float) -> tuple[np.ndarray, np.ndarray]:
    """0.5 s of hover, then a doublet on roll, pitch and yaw: (rates (T, 3), throttle (T,)) at 1 kHz."""
    rows = [np.zeros((500, 3))]
    for axis in range(3):
        for sign in (1.0, -1.0):
            piece = np.zeros((round(HALF_S * 1000), 3))
            piece[:, axis] = sign * DOUBLET
            rows.append(piece)
    rates = np.concatenate([*rows, np.zeros((200, 3))])
    return rates, np.full(len(rates), hover)


@pytest.fixture(scope="module")
def betaflight_log(tmp_path_factory):
    try:
        sitl_binary()
    except BetaflightError as exc:
        pytest.skip(f"Betaflight SITL unavailable: {exc}")
    if port_in_use(5761):
        pytest.fail("another Betaflight SITL holds TCP 5761; its UDP ports would take our packets")
    out = tmp_path_factory.mktemp("betaflight_blackbox")
    airframe = load_airframe("iris_realistic")  # a gyro with noise: every packet a new reading
    rates, throttle = _doublets(airframe.hover_throttle())
    with BetaflightFlight(out / "run", Twin(airframe, rig="rig"), RcMap(), speed=0.5,
                          blackbox=out / "flight.BFL") as flight:
        traces = flight.fly_script(_Excitation(rates, throttle, 1000), len(rates) / 1000.0)
    assert flight.blackbox_logs == 1
    return out / "flight.BFL", traces, airframe


@pytest.mark.slow
def test_betaflights_blackbox_reads_as_the_flight_the_twin_flew(betaflight_log) -> None:
    path, traces, airframe = betaflight_log
    log = read_flight_log(path)
    sent = traces.rate[0]
    # 8 kHz frames, the raw gyro new once per packet: one sample per packet, the twin's 1 ms
    assert log.dt == pytest.approx(0.001, rel=0.02)
    assert any("frames with the raw gyro new at" in note for note in log.notes), log.notes
    # one sample per twin step flown; Betaflight's log begins after its header, some 100 ms in
    assert len(sent) - 300 <= len(log.t) <= len(sent)
    assert log.rotor_speed is None  # stock Betaflight on PWM: no eRPM
    # the raw gyro Betaflight logged is the twin's, in FRD: same extremes with the same signs
    np.testing.assert_allclose(log.gyro.max(axis=0), sent.max(axis=0), rtol=0.02)
    np.testing.assert_allclose(log.gyro.min(axis=0), sent.min(axis=0), rtol=0.02)
    assert np.all(sent.max(axis=0) > 0.8 * DOUBLET)
    # the motor outputs are the µs the twin flew on, as 0..1 commands
    pwm = traces.pwm[0]
    assert np.median(log.command, axis=0) == pytest.approx((np.median(pwm, axis=0) - 1000) / 1000, abs=0.01)
    assert log.command.min() >= 0.0 and log.command.max() <= 1.0
    assert np.median(log.throttle) == pytest.approx(airframe.hover_throttle(), abs=0.01)


def _fail(path, capsys, tmp_path) -> str:
    assert main(["identify", str(path), "--out", str(tmp_path / "out.json")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"fcemu: error: {path}: ") and err.count("\n") == 1
    assert not (tmp_path / "out.json").exists()
    return err


def _header_end(data: bytes) -> int:
    return data.index(b"\nI") + 1


@pytest.mark.parametrize(("case", "line"), [
    ("header only", "0 data frames decoded: no flight in the log (truncated?)"),
    ("cleanflight", "a Cleanflight blackbox log (Cleanflight "),
    ("no motors", "no motor[0..3] fields (the motor outputs): clear blackbox_disable_motors"),
    ("no gyro", "no gyroADC or gyroUnfilt fields (the gyro): clear blackbox_disable_gyro"),
    ("cut short", "with the motors armed and above idle, at least 1 s needed: a ground-only log"),
])
def test_a_blackbox_log_that_cannot_be_identified_is_one_line_and_exit_2(case, line, betaflight_log, tmp_path,
                                                                         capsys) -> None:
    data = betaflight_log[0].read_bytes()
    if case == "header only":
        data = data[:_header_end(data)]
    elif case == "cleanflight":
        data = data.replace(b"H Firmware type:Betaflight", b"H Firmware type:Cleanflight", 1)
        data = data.replace(b"H Firmware revision:Betaflight", b"H Firmware revision:Cleanflight", 1)
    elif case == "no motors":  # the fields under other names of the same length: decoded, not found
        data = data.replace(b"motor[", b"mOtor[")
    elif case == "no gyro":
        data = data.replace(b"gyroADC[", b"gyroXYZ[").replace(b"gyroUnfilt[", b"gyroXYZXYZ[")
    else:
        data = data[:_header_end(data) + (len(data) - _header_end(data)) // 3]
    path = tmp_path / "bad.BFL"
    path.write_bytes(data)
    assert line in _fail(path, capsys, tmp_path)


def test_neither_a_ulog_nor_a_blackbox_log_says_so(tmp_path, capsys) -> None:
    path = tmp_path / "notes.BFL"
    path.write_text("H Product:something else\n")
    err = _fail(path, capsys, tmp_path)
    assert "not a PX4 ULog or a Betaflight blackbox log (no header of either)" in err


def test_without_the_decoder_a_blackbox_log_names_the_extra(betaflight_log, monkeypatch, tmp_path,
                                                            capsys) -> None:
    monkeypatch.setitem(sys.modules, "orangebox", None)  # as where fcemu[blackbox] is not installed
    assert "pip install 'fcemu[blackbox]' (orangebox, GPL-3.0" in _fail(betaflight_log[0], capsys, tmp_path)


def test_erpm_becomes_rotor_speed_with_the_pole_count() -> None:
    names = ["time", "eRPM[0]", "eRPM[1]", "eRPM[2]", "eRPM[3]"]
    table = np.array([[0, 70, 70, 140, 0], [125, 70, 70, 140, 0]], dtype=float)  # eRPM / 100
    speed, note = _rotor_speed(names, table, {"motor_poles": 14}, None)
    assert note == ""
    np.testing.assert_allclose(speed[0], np.array([1000, 1000, 2000, 0]) * 2 * np.pi / 60)
    from_airframe, _ = _rotor_speed(names, table, {}, 14)
    np.testing.assert_allclose(from_airframe, speed)
    unknown, note = _rotor_speed(names, table, {}, None)
    assert unknown is None and "no pole count is known (motor_poles)" in note
