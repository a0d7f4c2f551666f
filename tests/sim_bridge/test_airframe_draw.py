"""Airframes drawn from the distribution of quads (sim_bridge/airframe_draw.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fcemu.cli import main
from fcemu.evaluation import runner
from fcemu.evaluation.metrics import compute_metrics
from fcemu.sim_bridge.airframe import load_airframe
from fcemu.sim_bridge.airframe_draw import AirframeRanges, draw_airframes, figures
from fcemu.training.inversion_teacher import InversionController, InversionTeacher

RANGES = AirframeRanges()


def _within(value: float, box: tuple[float, float]) -> bool:
    return box[0] * (1 - 1e-9) <= value <= box[1] * (1 + 1e-9)


def test_every_drawn_airframe_is_a_file_the_twin_reads_within_the_ranges_which_it_spans(tmp_path) -> None:
    drawn = draw_airframes(11, 300)
    seen = {key: [] for key in ("mass_kg", "thrust_to_weight", "arm_m", "motor_tau_up_s")}
    for raw in drawn[:40]:  # the file check and the model build (MuJoCo) on a sample
        path = tmp_path / f"{raw['name']}.json"
        path.write_text(json.dumps(raw))
        airframe = load_airframe(path)
        assert airframe.mass == pytest.approx(raw["base_mass_kg"])
        assert 0.0 < airframe.hover_rotor_speed() < airframe.motor.max_rotor_speed
    for raw in drawn:
        f = figures(raw)
        for key in seen:
            seen[key].append(f[key])
        assert _within(f["mass_kg"], RANGES.mass_kg)
        assert _within(f["thrust_to_weight"], RANGES.thrust_to_weight)
        assert _within(f["arm_m"], RANGES.arm_m) and _within(f["motor_tau_up_s"], RANGES.motor_tau_s)
        assert f["motor_tau_up_s"] <= f["motor_tau_down_s"] <= RANGES.motor_tau_s[1]
        assert raw["rotor_radius_m"] < f["arm_m"] / np.sqrt(2.0)  # clear of the neighbouring prop
        assert _within(raw["effects"]["gyro_delay_ticks"]["value"], RANGES.gyro_delay_ticks)
    # Each box is spanned: its lowest and highest tenth both drawn.
    for key, box in (("mass_kg", RANGES.mass_kg), ("thrust_to_weight", RANGES.thrust_to_weight),
                     ("motor_tau_up_s", RANGES.motor_tau_s)):
        ratio = box[1] / box[0]
        assert min(seen[key]) < box[0] * ratio**0.1 and max(seen[key]) > box[1] / ratio**0.1, key
    small, large = np.argmin(seen["mass_kg"]), np.argmax(seen["mass_kg"])
    assert seen["arm_m"][small] < 0.06 and seen["arm_m"][large] > 0.15  # the arm follows the mass


def test_the_same_seed_draws_the_same_airframes() -> None:
    assert draw_airframes(5, 3) == draw_airframes(5, 3)
    assert draw_airframes(5, 3) != draw_airframes(6, 3)
    assert [raw["name"] for raw in draw_airframes(5, 2)] == ["drawn_5_0", "drawn_5_1"]


def test_fcemu_twin_draw_writes_the_files_it_reports(tmp_path, capsys) -> None:
    assert main(["twin", "draw", "--seed", "4", "--count", "3", "--out", str(tmp_path), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["seed"] == 4 and len(report["airframes"]) == 3
    for f, raw in zip(report["airframes"], draw_airframes(4, 3), strict=True):
        assert json.loads(open(f["file"]).read()) == raw and f == {**figures(raw), "file": f["file"]}
    assert main(["twin", "draw", "--count", "0", "--out", str(tmp_path)]) == 2
    assert "--count must be at least 1" in capsys.readouterr().err


def test_the_lightest_and_heaviest_of_a_draw_are_flown_by_the_model_based_teacher(tmp_path) -> None:
    """The files are quads a controller can fly at 1 kHz through their delays, not only files that load."""
    drawn = draw_airframes(12, 20)
    masses = [figures(raw)["mass_kg"] for raw in drawn]
    for raw in (drawn[int(np.argmin(masses))], drawn[int(np.argmax(masses))]):
        path = tmp_path / f"{raw['name']}.json"
        path.write_text(json.dumps(raw))
        cfg = runner.EvalConfig(episodes=2, seed=3, airframe=str(path))
        teacher = InversionTeacher(load_airframe(path))
        m = compute_metrics(runner.run_controller("inversion", cfg, progress=False,
                                                  controller=InversionController(teacher, mapped=True)))
        success = [m.stat("success_pct", axis).mean for axis in ("roll", "pitch", "yaw")]
        assert success == [100.0] * 3, raw["name"]
