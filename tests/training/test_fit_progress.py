"""What `fcemu fit` expects its stages to take, for the time left its log lines estimate."""

from __future__ import annotations

import pytest

from fcemu.training.fit_options import FitOptions
from fcemu.training.fit_progress import BOUND_S_PER_COMMAND, MCU_S, TYPICAL_S, expected_s, fit_stages

pytestmark = pytest.mark.no_wall_clock


def test_the_stages_expected_take_the_budget_the_bound_and_the_work_asked_for(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))  # no bound cached
    tuned = expected_s(FitOptions(airframe="racer5", out="o", jobs=1))
    assert tuned == pytest.approx({"tune": 480.0, **TYPICAL_S,  # the bound inside the tune's budget
                                   "check": TYPICAL_S["check"] + MCU_S})
    given = expected_s(FitOptions(airframe="racer5", out="o", pid="racer5", lag_multiple=0.35, rounds=3,
                                  episodes=10, mcu=False, jobs=1))
    assert "teacher" not in given  # its speed given: the teacher stage is not flown
    assert given["tune"] == BOUND_S_PER_COMMAND * 10
    assert given["policy"] == pytest.approx(TYPICAL_S["policy"] / 2)  # half the rounds
    assert given["check"] == pytest.approx(TYPICAL_S["check"] / 5)
    lines: list[str] = []
    stages = fit_stages(FitOptions(airframe="racer5", out="o", jobs=1), lines.append)
    assert stages.calibrate == {"teacher", "policy", "check"}  # the tune's seconds are its budget's anywhere
    assert stages.left() == pytest.approx(sum(tuned.values()))
