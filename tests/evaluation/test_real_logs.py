"""Blackbox logs of real quads (tests/data/real_logs, with their licences) read end to end:
`fcemu identify` on one stretch, the log's own tune, `fcemu replay` on another; and the logs a
user may bring that cannot be read are one line, exit 2, nothing written."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fcemu.cli import main
from fcemu.evaluation.identify_blackbox import (
    check_motors_move,
    check_rate,
    check_throttle_leaves_idle,
    read_blackbox_logs,
)
from fcemu.evaluation.identify_log import LogError, joined
from fcemu.firmware.pid_controller import PIDRateController
from fcemu.sim_bridge.airframe import load_airframe

pytestmark = pytest.mark.no_wall_clock

pytest.importorskip("orangebox", reason="the blackbox decoder is the extra fcemu[blackbox]")

LOGS = Path(__file__).resolve().parents[1] / "data" / "real_logs"
GECKO = LOGS / "gecko_btfl_002.bbl"  # Betaflight 4.2.8, 500 Hz, props out, setpoint logged
CS110 = LOGS / "cs110_example_smooth_tune.BBL"  # Betaflight 3.1.5, 2 kHz, rcCommand only


@pytest.fixture(scope="module")
def gecko():
    return read_blackbox_logs(GECKO)


@pytest.fixture(scope="module")
def cs110():
    return read_blackbox_logs(CS110)


def test_betaflight_naming_itself_cleanflight_is_read_at_its_own_rate(gecko, cs110) -> None:
    (g,), (c,) = gecko, cs110
    assert g.dt == pytest.approx(0.002, rel=0.02)  # 500 Hz frames used as they are
    assert c.dt == pytest.approx(0.001)  # 2 kHz readings held onto the twin's step
    assert g.t[-1] > 100 and 20 < c.t[-1] < 40
    for log in (g, c):
        # the setpoint (logged on 4.x, the sticks through the rates on 3.x) is what the gyro follows
        assert all(np.corrcoef(log.setpoint[:, i], log.gyro[:, i])[0, 1] > 0.95 for i in range(3))
        assert 0.3 < log.gyro_filter_lag_s * 1e3 < 4.0  # gyroADC's filters, from the header
    assert 13.0 < np.median(g.battery_v) < 17.0 and 6.5 < np.median(c.battery_v) < 8.5  # 4S, 2S
    assert any("garbled" in note for note in g.notes)  # inter frames before its first intra frame


def test_each_arming_in_a_file_is_a_flight_of_its_own(tmp_path: Path) -> None:
    both = tmp_path / "two_armings.bbl"
    both.write_bytes(CS110.read_bytes() + CS110.read_bytes())
    flights = read_blackbox_logs(both)
    assert [f.title for f in flights] == ["log 1 of the 2 in the file", "log 2 of the 2 in the file"]
    np.testing.assert_array_equal(flights[0].gyro, flights[1].gyro)
    assert len(joined(flights).t) == 2 * len(flights[0].t)
    assert joined(flights).notes[0].startswith("2 flights joined")


def test_identify_then_replay_a_stretch_it_did_not_see(tmp_path: Path, capsys) -> None:
    """Without the closed-loop refinement (quick): the file, the log's tune, replay's figures."""
    out = tmp_path / "gecko"
    assert main(["identify", str(GECKO), "--out", str(out / "airframe.json"), "--span", "0:60",
                 "--no-refine", "--json"]) == 0
    figures = json.loads(capsys.readouterr().out)
    airframe = load_airframe(out / "airframe.json")
    assert airframe.spin[0] > 0 and figures["props"].startswith("props out")  # from the data: no header line
    assert "props out" in json.loads((out / "airframe.json").read_text())["sources"]["motors"]
    tune = json.loads((out / "pid_log.json").read_text())
    controller = PIDRateController.from_dict(tune)
    assert controller.gains.kp[0] == pytest.approx(35 * 0.032029, rel=1e-4)  # rollPID 35
    assert any("anti-gravity" in item for item in tune["not_modelled"])
    assert main(["replay", str(GECKO), "--airframe", str(out / "airframe.json"), "--span", "100:115",
                 "--out", str(out / "replay"), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    for axis in ("roll", "pitch", "yaw"):
        row = result["axes"][axis]
        for side in ("log", "twin"):
            assert set(row[side]) == {"tracking_rms_rad_s", "step_peak", "step_rise_ms"}
        assert 0 < row["log"]["tracking_rms_rad_s"] < 0.2  # the pilot's quad tracks its sticks
        assert 0.8 < row["log"]["step_peak"] < 1.6 and 2 < row["log"]["step_rise_ms"] < 40
        assert np.isfinite(row["prediction_fit_pct"]) and np.isfinite(row["base_prediction_fit_pct"])
    assert (out / "replay" / "replay.png").stat().st_size > 10_000
    assert (out / "replay" / "step_response.png").stat().st_size > 10_000


def test_a_betaflight_3_log_without_setpoints_identifies_refines_and_replays(tmp_path: Path, capsys) -> None:
    """The whole path: the log's own tune flies the twin to refine it, and the refined twin, flown by
    that tune on a stretch it never saw, tracks as the quad did."""
    out = tmp_path / "cs110"
    assert main(["identify", str(CS110), "--out", str(out / "airframe.json"), "--span", ":17", "--json"]) == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures["props"].startswith("props in")
    refined = figures["closed_loop"]
    assert sum(refined["mismatch_after"]) < sum(refined["mismatch_before"])
    sources = json.loads((out / "airframe.json").read_text())["sources"]
    assert "refined in closed loop" in sources["base_inertia_kg_m2"]
    assert main(["replay", str(CS110), "--airframe", str(out / "airframe.json"),
                 "--span", "17:", "--json"]) == 0
    axes = json.loads(capsys.readouterr().out)["axes"]
    for axis, row in axes.items():
        log, twin = row["log"]["tracking_rms_rad_s"], row["twin"]["tracking_rms_rad_s"]
        assert 0.5 * log < twin < 1.5 * log, axis
        assert abs(row["twin"]["step_peak"] - row["log"]["step_peak"]) < 0.45, axis


def _renamed(tmp_path: Path, old: bytes, new: bytes) -> Path:
    data = GECKO.read_bytes()
    assert old in data
    path = tmp_path / "renamed.bbl"
    path.write_bytes(data.replace(old, new, 1))
    return path


@pytest.mark.parametrize(("revision", "named"), [
    (b"H Firmware revision:INAV 5.1.0 (abcdef0) MATEKF405", "INAV"),
    (b"H Firmware revision:Cleanflight 2.5.0 (abcdef0) SPRACINGF3", "Cleanflight"),
    (b"H Firmware revision:EmuFlight 0.4.1 (abcdef0) STM32F7X2", "EmuFlight"),
])
def test_another_firmwares_log_is_one_line_naming_it(tmp_path: Path, capsys, revision: bytes,
                                                     named: str) -> None:
    log = _renamed(tmp_path, b"H Firmware revision:Betaflight 4.2.8 (101738d8e) STM32F7X2", revision)
    out = tmp_path / "out" / "airframe.json"
    assert main(["identify", str(log), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and named in err
    assert not out.parent.exists()


def test_a_log_too_slow_or_not_flown_is_refused() -> None:
    check_rate(Path("ok.bbl"), 0.004)  # 250 Hz is enough
    with pytest.raises(LogError, match=r"logged at 100 Hz: a rate twin needs at least 200 Hz"):
        check_rate(Path("slow.bbl"), 0.01)
    still = np.full((500, 4), 0.055) + np.random.default_rng(0).normal(0, 0.001, (500, 4))
    with pytest.raises(LogError, match="the motors never move"):
        check_motors_move(Path("bench.bbl"), still)
    check_motors_move(Path("flown.bbl"), still + np.linspace(0, 0.2, 500)[:, None])
    with pytest.raises(LogError, match="armed on the ground, not flown"):
        check_throttle_leaves_idle(Path("ground.bbl"), np.r_[np.zeros(980), np.full(20, 0.5)])
    check_throttle_leaves_idle(Path("flown.bbl"), np.r_[np.zeros(100), np.full(900, 0.3)])


def test_replay_of_a_log_without_a_tune_of_its_own_needs_a_controller(tmp_path: Path, capsys) -> None:
    assert main(["replay", str(tmp_path / "missing.bbl"), "--airframe", "iris"]) == 2
    assert "missing.bbl" in capsys.readouterr().err
