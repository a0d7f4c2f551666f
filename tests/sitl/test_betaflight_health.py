"""`python -m fcemu.sitl.betaflight_health`: the per-scenario summary and the refusals (no SITL flown)."""

from __future__ import annotations

import re

import pytest

from fcemu.export.betaflight.build import PATCH
from fcemu.sitl.betaflight_health import SCENARIOS, main, summarise
from fcemu.sitl.betaflight_process import NEURAL_STATES


def _row(scenario: str, error: float | None, dropped: str = "", after: int | None = None,
         at: int | None = None, age: int = 0, loss: float = 0.0) -> dict:
    return {"scenario": scenario, "fault_at_tick": at, "dropped": dropped, "dropped_after_ticks": after,
            "max_rpm_age_ticks": age, "max_loss_rate": loss, "roll_error_rad_s": error}


def test_the_summary_counts_drops_per_reason_and_compares_with_the_fault_free_error():
    rows = [_row("fault-free", 0.004), _row("fault-free", 0.006),
            _row("stop", 0.01, "rpm too old", 121, 100, 21, 0.19),
            _row("stop", 0.02, "rpm too old", 122, 100, 21),
            _row("stop", 0.03, "rpm losing frames", 130, 100, 5, 0.21),
            _row("gyro", None, "gyro too old", 111, 100)]
    summary = {s["scenario"]: s for s in summarise(rows)}
    assert summary["fault-free"]["flew_to_the_end"] == 2 and summary["fault-free"]["error_ratio"] == 1.0
    stop = summary["stop"]
    assert stop["flew_to_the_end"] == 0 and stop["dropped"] == {"rpm too old": 2, "rpm losing frames": 1}
    assert stop["dropped_ticks_after_fault"] == [21, 22, 30]
    assert (stop["max_rpm_age_ticks"], stop["max_loss_rate"], stop["error_ratio"]) == (21, 0.21, 4.0)
    assert summary["gyro"]["roll_error_rad_s_median"] is None and summary["gyro"]["error_ratio"] is None


def test_every_scenario_has_a_fault_but_the_first_and_unique_names():
    assert SCENARIOS[0].fault is None and all(s.fault is not None for s in SCENARIOS[1:])
    assert len({s.name for s in SCENARIOS}) == len(SCENARIOS)


def test_bad_arguments_are_one_line_and_exit_2(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--firmware", str(tmp_path), "--episodes", "0"])
    assert exit_.value.code == 2 and capsys.readouterr().err == "fcemu: error: --episodes must be >= 1\n"
    with pytest.raises(SystemExit) as exit_:
        main(["--firmware", str(tmp_path)])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.startswith("fcemu: error: ") and "not a Betaflight export" in err


def test_the_neural_states_read_over_msp_are_the_patch_s_enum_in_order():
    enum = re.findall(r"^\+    NEURAL_(\w+)(?: = 0)?,", PATCH.read_text(), re.MULTILINE)
    assert [name.lower().replace("_", " ") for name in enum] == list(NEURAL_STATES)
