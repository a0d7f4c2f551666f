"""The time left that long commands print: counted work at its pace so far, stages scaled by the pace
the finished ones showed, a few lines where stderr is not a terminal."""

from __future__ import annotations

import io

import pytest

from fcemu.evaluation.progress import Counted, Stages, duration, left_text

pytestmark = pytest.mark.no_wall_clock


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_durations_are_as_precise_as_an_estimate_is_worth() -> None:
    assert [duration(s) for s in (0.4, 45, 89.4, 200, 725)] == ["0 s", "45 s", "89 s", "3 min 20 s", "12 min"]
    assert left_text(None) == "time left not yet known"
    assert left_text(30) == "about 30 s left, an estimate"
    assert left_text(0.2) == "less than a second left"


def test_counted_work_says_its_time_left_at_each_quarter_off_a_terminal() -> None:
    clock, stream = Clock(), io.StringIO()
    count = Counted("refinement", 100, "flight", stream, clock=clock)
    assert count.bar is None and count.left() is None
    for done in range(1, 81):
        clock.now += 0.5
        count.update(done, note=f"mismatch {1.0 / done:.3f}")
    lines = stream.getvalue().splitlines()
    assert len(lines) == 3  # at 25, 50 and 75 of 100
    assert lines[0] == ("  refinement: 25/100 flights, mismatch 0.040; 12 s so far; "
                        "about 38 s left, an estimate")
    assert lines[2].startswith("  refinement: 75/100 flights") and "about 12 s left" in lines[2]
    # the optimiser stopped early: the plan shrinks, and so does the time left
    count.update(80, 90)
    assert count.left() == pytest.approx(0.5 * 10)
    count.update(91, 90)  # an optimiser may overrun its plan by a step
    assert count.total == 91 and count.left() == 0.0
    assert count.close() == pytest.approx(40.0)
    assert stream.getvalue().splitlines()[-1] == "  refinement: 91 flights in 40 s"


def test_stages_tick_down_and_take_the_pace_of_the_finished_ones() -> None:
    clock, lines = Clock(), []
    stages = Stages({"tune": 100.0, "teacher": 20.0, "policy": 40.0, "check": 10.0}, lines.append,
                    calibrate=("teacher", "policy", "check"), clock=clock)
    stages.start("tune", "tuning")
    assert lines[-1] == "[    0 s] tuning; about 2 min 50 s left, an estimate"
    clock.now += 30
    assert stages.left() == pytest.approx(140.0)  # the current stage's expectation less its time so far
    clock.now += 90  # the tune ran over its budget: that says nothing of the machine's pace
    assert stages.left() == pytest.approx(70.0)
    stages.start("teacher", "the teacher")
    assert lines[-1] == "[  120 s] the teacher; about 70 s left, an estimate"
    clock.now += 40  # twice as long as expected: the rest is expected to take twice as long too
    stages.start("policy", None)
    assert len(lines) == 2 and stages.pace() == pytest.approx(2.0)
    assert stages.left() == pytest.approx(2.0 * (40.0 + 10.0))
    stages.note("the policy")
    assert lines[-1] == "[  160 s] the policy; about 1 min 40 s left, an estimate"
    stages.skip("check")
    clock.now += 100
    assert stages.left() == 0.0  # late: nothing is promised below nothing
