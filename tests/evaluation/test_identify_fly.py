"""`fcemu identify --fly` on an airframe no PID tune is shipped for: fcemu tune's start flies it."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from fcemu.cli import main
from fcemu.evaluation.identify_flight import identification_controller
from fcemu.firmware.controllers import ControllerSpecError, load_controller
from fcemu.firmware.pid_controller import load_preset
from fcemu.sim_bridge.airframe import AIRFRAME_DIR, load_airframe
from fcemu.sim_bridge.airframe_spec import airframe_spec


def _untuned(tmp_path):
    """The Iris under another name and 20 % lighter: an airframe file no tune is shipped for."""
    doc = json.loads((AIRFRAME_DIR / "iris.json").read_text())
    doc["name"] = "my_quad"
    doc["base_mass_kg"] = round(doc["base_mass_kg"] * 0.8, 6)
    path = tmp_path / "my_quad.json"
    path.write_text(json.dumps(doc, indent=1))
    return path


def test_a_shipped_tune_or_another_controller_flies_as_asked(tmp_path: Path, untuned_airframe: Path) -> None:
    assert identification_controller(load_airframe("iris_realistic"), "pid", tmp_path) == ("pid", None)
    untuned = load_airframe(untuned_airframe)
    assert identification_controller(untuned, "pid:iris", tmp_path) == ("pid:iris", None)
    assert not list(tmp_path.iterdir())


def test_fly_an_airframe_with_no_tune_flies_the_iris_tune_carried_over(tmp_path, capsys) -> None:
    airframe_file, out = _untuned(tmp_path), tmp_path / "out"
    with pytest.raises(ControllerSpecError, match="no PID tuned for my_quad"):
        load_controller("pid", 1000.0, airframe_spec(load_airframe(airframe_file)))
    assert main(["identify", "--fly", str(airframe_file), "--out", str(out)]) == 0
    # each stage said on stderr as it starts, with the time so far and an estimate of the time left
    stages = [line for line in capsys.readouterr().err.splitlines() if line.startswith("[")]
    assert [line.split("] ")[1].split()[0] for line in stages] == ["flying", "identifying", "writing"]
    said = re.compile(r"\[ +\d+ s\] .+; (about \d+ s left, an estimate|less than a second left)")
    assert all(said.fullmatch(line) for line in stages), stages
    written = {p.name for p in out.iterdir()}
    assert {"flight.ulg", "airframe.json", "report.md", "pid_carried_over.json"} <= written
    carried = json.loads((out / "pid_carried_over.json").read_text())
    assert carried["name"] == "pid_my_quad"
    iris = load_preset("iris")["pid"]
    # lighter on the same inertia: a slower hover rotor, less torque per command, larger gains (×√(1/0.8))
    assert [k / k_iris for k, k_iris in zip(carried["pid"]["kp"], iris["kp"], strict=True)] == pytest.approx(
        [0.8 ** -0.5] * 3, rel=0.01)
    report = (out / "report.md").read_text()
    assert ("The flight was flown by the Iris tune carried over to my_quad by the loop's physics "
            "(fcemu tune's start, pid_carried_over.json): no tune is shipped for it.") in report
    identified, true = load_airframe(out / "airframe.json"), load_airframe(airframe_file)
    assert identified.motor.tau_up == pytest.approx(true.motor.tau_up, rel=0.05)
    assert identified.hover_throttle() == pytest.approx(true.hover_throttle(), abs=0.01)
