"""The fit's teacher stage: the teacher's speed and the share of yaw it serves first, as the bar's
lines choose them on the tuning commands."""

from pathlib import Path

import pytest

from fcemu.evaluation.bar import ERROR_RATIO_BAR, PEAK_MARGIN_PCT, SMOOTHNESS_BAR
from fcemu.firmware.pid_controller import PRESET_DIR
from fcemu.sim_bridge.airframe import load_airframe
from fcemu.training.fit_options import STUDENT_STEPS, FitOptions
from fcemu.training.fit_teacher import (
    BRAKING_CHOICES,
    ERROR_ROOM,
    ERROR_TIE,
    MORE_DAMPING,
    STUDENT_SMOOTHING,
    TEACHER_SPEEDS,
    YAW_FIRST_CHOICES,
    first_teacher,
    more_damped_taken,
    shape_admitted,
    student_kind,
    teacher_stage,
)
from fcemu.training.inversion_teacher import BRAKING_SHARE, DAMPING

pytestmark = pytest.mark.no_wall_clock


def test_the_first_teacher_is_the_smoothest_of_least_error_unless_it_rises_later_than_the_pid():
    def teacher(multiple: float, error: float, rise: float) -> dict:
        return {"lag_multiple": multiple, "error_sum": error, "smoothness": 1.0, "rise_ms": [rise, rise]}

    room = (ERROR_RATIO_BAR - ERROR_ROOM) * 100.0  # the PID's Error sum 100
    flown = [teacher(0.5, room + 6.0, 50.0), teacher(0.35, room - 2.0, 41.0),
             teacher(0.18, room - 2.0 + 0.5 * ERROR_TIE * room, 39.0), teacher(0.13, room - 0.5, 38.0),
             teacher(0.1, room + 1.0, 37.0)]
    rises = {"error_sum": 100.0, "rise_ms": [41.0, 41.0]}
    assert first_teacher(flown, rises)["lag_multiple"] == 0.35  # 0.18 ties it on Error; 0.35 rises in time
    late = {"error_sum": 100.0, "rise_ms": [40.0, 41.0]}
    assert first_teacher(flown, late)["lag_multiple"] == 0.18  # the slowest with room that rises in time
    later = {"error_sum": 100.0, "rise_ms": [38.5, 41.0]}
    assert first_teacher(flown, later)["lag_multiple"] == 0.13
    none_in_time = {"error_sum": 100.0, "rise_ms": [37.5, 41.0]}
    assert first_teacher(flown, none_in_time)["lag_multiple"] == 0.13  # the fastest with room under the line
    assert first_teacher(flown, {"error_sum": 90.0, "rise_ms": [40.0, 41.0]})["lag_multiple"] == 0.35


def test_student_kind_follows_the_sensors() -> None:
    """A twin whose gyro or ESC telemetry is noisy, vibrating, delayed or lossy gets a student of
    sensed history (its own admission ratio and steps); the nominal twin one that reads what its
    teacher reads."""
    assert student_kind(load_airframe("iris")) == "exact"
    assert student_kind(load_airframe("iris_realistic")) == "sensed"
    assert set(STUDENT_SMOOTHING) == set(STUDENT_STEPS) == {"exact", "sensed"}


def test_speed_stage_admits_by_the_kind_of_student(tmp_path) -> None:
    """On a twin with noisy, delayed sensors the teachers admitted are those within the bar's motor
    line over a sensed student's smoothing, not an exact student's: the stage's order follows it."""
    opts = FitOptions(airframe="iris_realistic", out=str(tmp_path), episodes=2, jobs=1, progress=False)
    lines: list[str] = []
    speed = teacher_stage(opts, Path(str(PRESET_DIR / "pid_iris.json")), log=lines.append)
    assert speed["student"] == "sensed"
    limit = SMOOTHNESS_BAR / STUDENT_SMOOTHING["sensed"] * speed["pid_smoothness"]
    admitted = [f for f in speed["flown"] if f["smoothness"] <= limit] or speed["flown"][:1]
    first = first_teacher(admitted, {"error_sum": speed["pid_error_sum"], "rise_ms": speed["pid_rise_ms"]})
    slower = sorted(f["lag_multiple"] for f in admitted if f["lag_multiple"] > first["lag_multiple"])
    assert speed["order"] == [first["lag_multiple"], *slower]
    assert STUDENT_SMOOTHING["sensed"] > STUDENT_SMOOTHING["exact"]
    # then the first teacher flown again in every other shape, each admitted by the rule
    pid = {"rise_ms": speed["pid_rise_ms"], "peak_pct": speed["pid_peak_pct"]}
    shapes = speed["shapes"]
    assert len(shapes) == len(YAW_FIRST_CHOICES) * len(BRAKING_CHOICES) - 1
    assert all(f["admitted"] == shape_admitted(f, first, pid, limit) for f in shapes)
    assert len(lines) == len(TEACHER_SPEEDS) + len(shapes) + 1  # and the chosen shape more damped
    assert speed["damping"] in (DAMPING, MORE_DAMPING) and lines[-1].startswith(f"  damping {MORE_DAMPING:g}")
    assert (speed["damping"] == MORE_DAMPING) == lines[-1].endswith("(taken)")
    assert sum("(not admitted)" in line for line in lines) == sum(not f["admitted"] for f in shapes)
    chosen = (speed["yaw_first"], speed["braking"])
    assert chosen == (0.0, BRAKING_SHARE) or next(
        f for f in shapes if (f["yaw_first"], f["braking"]) == chosen)["admitted"]


def test_a_shape_is_admitted_with_the_motors_rise_and_peaks_the_bar_allows() -> None:
    without = {"error_sum": 100.0, "smoothness": 1.0, "rise_ms": [30.0, 40.0],
               "peak_pct": [110.0, 102.0, 101.0]}
    pid = {"error_sum": 120.0, "rise_ms": [35.0, 38.0], "peak_pct": [108.0, 104.0, 103.0]}

    def flown(roll_peak: float = 110.0, smoothness: float = 1.0, rise: tuple = (30.0, 40.0)) -> dict:
        return {"error_sum": 95.0, "smoothness": smoothness, "rise_ms": list(rise),
                "peak_pct": [roll_peak, 102.0, 101.0]}

    assert shape_admitted(flown(), without, pid, 2.0)
    assert not shape_admitted(flown(smoothness=2.1), without, pid, 2.0)  # motors past the admission
    # Rise: no later than the PID's, or than the teacher's own where it already rose later (pitch here)
    assert shape_admitted(flown(rise=(35.0, 40.0)), without, pid, 2.0)
    assert not shape_admitted(flown(rise=(35.5, 40.0)), without, pid, 2.0)
    assert not shape_admitted(flown(rise=(30.0, 40.5)), without, pid, 2.0)
    # a Peak may rise to the bar's room over the PID's (111), or stay where it was without (110 here)
    assert shape_admitted(flown(roll_peak=108.0 + PEAK_MARGIN_PCT), without, pid, 2.0)
    assert not shape_admitted(flown(roll_peak=111.5), without, pid, 2.0)
    over = {**without, "peak_pct": [112.0, 102.0, 101.0]}
    assert shape_admitted(flown(roll_peak=112.0), over, pid, 2.0)
    assert not shape_admitted(flown(roll_peak=112.5), over, pid, 2.0)


def test_a_more_damped_teacher_is_taken_within_a_tie_on_error_where_its_highest_peak_is_lower() -> None:
    chosen = {"error_sum": 100.0, "peak_pct": [104.0, 102.0, 101.0]}

    def damped(error: float, peaks: tuple) -> dict:
        return {"error_sum": error, "peak_pct": list(peaks)}

    assert more_damped_taken(damped(100.0 + 100.0 * ERROR_TIE, (103.0, 103.5, 101.0)), chosen)
    assert not more_damped_taken(damped(101.5, (100.0, 100.0, 100.0)), chosen)  # past the tie
    assert not more_damped_taken(damped(95.0, (104.0, 100.0, 100.0)), chosen)  # the highest Peak as high


def test_the_stages_flights_in_worker_processes_are_those_flown_in_one() -> None:
    from fcemu.training.fit_teacher import stage_flights
    from fcemu.training.pid_tune import nominal

    opts = FitOptions(airframe="iris", out="o", episodes=2, jobs=2, progress=False)
    work = [(opts, f"pid:{PRESET_DIR / 'pid_iris.json'}", None),
            (opts, {"lag_multiple": 0.35, "braking": 0.3}, nominal(load_airframe("iris")))]
    with stage_flights(2) as fly:
        parallel = fly(work)
    with stage_flights(1) as fly:
        alone = fly(work)
    assert parallel == alone and parallel[0] != parallel[1]
