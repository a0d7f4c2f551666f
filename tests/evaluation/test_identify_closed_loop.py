"""The closed-loop refinement's pieces: the factors keep a body MuJoCo builds, the busiest stretch
is where the sticks move, and an identified file that --airframe would refuse is never written."""

from __future__ import annotations

import io
import json
import re
from pathlib import Path

import numpy as np
import pytest

from fcemu.evaluation import identify_closed_loop
from fcemu.evaluation.identify_airframe import airframe_document, is_rigid_body, write_airframe
from fcemu.evaluation.identify_cli import refined_with_progress
from fcemu.evaluation.identify_closed_loop import busiest_stretch, planned_flights, with_factors
from fcemu.evaluation.identify_flight import fly_identification
from fcemu.evaluation.identify_log import FlightLog, LogError, read_ulog
from fcemu.evaluation.replay import span_of
from fcemu.sim_bridge.airframe import load_airframe
from fcemu.sim_bridge.twin import Twin

pytestmark = pytest.mark.no_wall_clock

IRIS = load_airframe("iris")


@pytest.mark.parametrize("factors", [(1, 1, 1, 1, 1), (1.5, 0.5, 2, 0.7, 0.3), (0.3, 1.2, 0.2, 2, 1)])
def test_the_factors_scale_each_axis_and_keep_a_rigid_body(factors) -> None:
    roll, pitch, yaw, tau, spin = factors
    scaled = with_factors(IRIS, roll, pitch, yaw, tau, spin)
    before, after = IRIS.inertia(), scaled.inertia()
    np.testing.assert_allclose(before[:2] / after[:2], (roll, pitch), rtol=1e-9)
    yaw_effectiveness = scaled.motor.kf * scaled.motor.km / after[2]
    np.testing.assert_allclose(yaw_effectiveness, yaw * IRIS.motor.kf * IRIS.motor.km / before[2], rtol=1e-9)
    assert scaled.motor.tau_up == pytest.approx(IRIS.motor.tau_up * tau)
    assert is_rigid_body(list(scaled.base_inertia))
    Twin(scaled)  # MuJoCo builds it


def test_factors_that_leave_the_body_no_inertia_of_its_own_are_refused() -> None:
    with pytest.raises(ValueError, match="no inertia of its own"):
        with_factors(IRIS, 50.0, 1.0, 1.0, 1.0, 1.0)


def test_the_busiest_stretch_is_where_the_setpoint_moves() -> None:
    t = np.arange(0, 30, 0.002)
    setpoint = np.zeros((len(t), 3))
    busy = (t > 12) & (t < 20)
    setpoint[busy] = np.sin(2 * np.pi * 3 * t[busy])[:, None]
    log = FlightLog(Path("x.bbl"), t, setpoint, np.zeros((len(t), 4)), None, None, "test", setpoint=setpoint)
    start, end = busiest_stretch(log, 8.0)
    assert 11.0 < start < 13.0 and end == pytest.approx(start + 8.0)


def test_an_airframe_fcemu_would_refuse_is_never_written(tmp_path: Path) -> None:
    doc = airframe_document(IRIS, "test", {})
    doc["base_inertia_kg_m2"] = [0.001, 0.001, 0.01]  # no rigid body
    out = tmp_path / "quad.json"
    with pytest.raises(LogError, match=r"not one fcemu flies, so .*quad\.json is not written"):
        write_airframe(doc, out)
    assert list(tmp_path.iterdir()) == []
    write_airframe(airframe_document(IRIS, "test", {}), out)
    assert json.loads(out.read_text())["name"] == "iris"


def test_the_refinement_counts_its_flights_and_says_the_time_left(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(identify_closed_loop, "MAX_EVALUATIONS", 8)  # a tiny problem: a dozen short flights
    log = span_of(read_ulog(fly_identification(IRIS, "pid", axis_s=0.6).write(tmp_path / "flight.ulg")),
                  (2.0, 4.5))
    stream = io.StringIO()  # not a terminal: lines, not a bar
    refinement = refined_with_progress(log, IRIS, "pid", stream)
    *progress, last = stream.getvalue().splitlines()
    assert last.startswith(f"  closed-loop refinement: {refinement.flights} flights in ")
    line = re.compile(r"  closed-loop refinement: \d+/\d+ flights, least mismatch [\d.]+; \d+ s so far; "
                      r"(about \d+ s left, an estimate|less than a second left)")
    assert progress and all(line.fullmatch(text) for text in progress)
    done = [int(re.search(r"(\d+)/", text)[1]) for text in progress]
    # the gyro delay fitted and up to three ticks shorter, an optimiser's flights each; the twin before, after
    assert done == sorted(done) and planned_flights(IRIS) == (min(IRIS.gyro_delay_ticks, 3) + 1) * 8 + 2
