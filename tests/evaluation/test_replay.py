"""`fcemu replay` against a log whose quad is known: the identification flight fcemu's own firmware
flew on the Iris twin, replayed on that twin with the same tune, is the log again."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fcemu.cli import main
from fcemu.evaluation.flight_logs import read_flight_log
from fcemu.evaluation.identify_flight import fly_identification
from fcemu.evaluation.replay import fly_log, span_of
from fcemu.sim_bridge.airframe import load_airframe

pytestmark = pytest.mark.no_wall_clock


@pytest.fixture(scope="module")
def iris_flight(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("replay")
    return fly_identification(load_airframe("iris"), "pid", axis_s=3.0).write(out / "flight.ulg", {})


def test_the_known_quad_replayed_with_its_own_tune_flies_the_log_again(iris_flight: Path) -> None:
    log = read_flight_log(iris_flight)
    assert log.setpoint is not None and log.throttle is not None
    flown = fly_log(log, load_airframe("iris"), "pid:pid_iris")
    # the same twin, tune, setpoints and start: the same rates, to the log's float32
    np.testing.assert_allclose(flown.twin_gyro[5:], flown.log_gyro[5:], atol=2e-3)


def test_replay_reports_each_axis_and_a_stretch(iris_flight: Path, tmp_path: Path, capsys) -> None:
    log = read_flight_log(iris_flight)
    assert len(span_of(log, (5.0, 10.0)).t) == pytest.approx(5000, abs=2)
    assert main(["replay", str(iris_flight), "--airframe", "iris", "--controller", "pid:pid_iris",
                 "--span", "5:", "--out", str(tmp_path), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert json.loads((tmp_path / "replay.json").read_text())["axes"] == result["axes"]
    for axis, row in result["axes"].items():
        log, twin = row["log"], row["twin"]
        # the stretch starts the twin at rest where the quad was turning: close, not the same
        assert twin["tracking_rms_rad_s"] == pytest.approx(log["tracking_rms_rad_s"], rel=0.1), axis
        assert twin["step_peak"] == pytest.approx(log["step_peak"], abs=0.05), axis
        assert row["prediction_fit_pct"] == pytest.approx(row["base_prediction_fit_pct"])  # iris is the base


def test_a_stretch_too_short_or_a_log_without_a_tune_is_one_line(iris_flight: Path, capsys) -> None:
    short = ["replay", str(iris_flight), "--airframe", "iris", "--controller", "pid", "--span", "3:4"]
    assert main(short) == 2
    assert "at least 2 s needed" in capsys.readouterr().err
    assert main(["replay", str(iris_flight), "--airframe", "iris"]) == 2  # a ULog carries no tune
    assert "give --controller" in capsys.readouterr().err
