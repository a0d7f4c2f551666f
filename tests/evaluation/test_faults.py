"""`fcemu eval --fault`: specs, the seeded fault time, the table, and the attitude test of "upright"."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from fcemu.evaluation.faults import (
    FaultPlan,
    attitude_departure_deg,
    fault_result,
    fault_table,
    fault_ticks,
    parse_fault,
)
from fcemu.evaluation.runner import EvalConfig, run_controller
from fcemu.sim_bridge.faults import Fault, FaultSpecError

pytestmark = pytest.mark.no_wall_clock


def fcemu(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fcemu", *args], capture_output=True, text=True,
                          timeout=300, check=False)


def test_specs() -> None:
    assert parse_fault("gyro:stuck") == Fault("gyro", "stuck")
    assert parse_fault("esc-telemetry:delayed:5ms") == Fault("esc-telemetry", "delayed", 0, 0.005)
    assert parse_fault("motor:2:thrust=0.7") == Fault("motor", "thrust", 2, 0.7)
    assert parse_fault("esc-telemetry:3:slow:50Hz") == Fault("esc-telemetry", "slow", 3, 0.02)
    assert parse_fault("battery:wrong=75%") == Fault("battery", "wrong", 0, 0.75)
    assert parse_fault("esc-telemetry:intermittent:1%") == Fault("esc-telemetry", "intermittent", 0, 0.01)
    assert parse_fault("esc-telemetry:burst:20ms@1%") == Fault("esc-telemetry", "burst", 0, 0.01, 0.02)
    assert parse_fault("esc-telemetry:2:burst=50ms") == Fault("esc-telemetry", "burst", 2, None, 0.05)
    assert parse_fault("esc-telemetry:burst:5%") == Fault("esc-telemetry", "burst", 0, 0.05)
    for bad in ("gyro", "gyro:melted", "motor:9:off", "motor:2:thrust=1.7", "esc-telemetry:delayed:soon",
                "magnet:off", "gyro:stuck:1:2:3", "esc-telemetry:burst:20ms@100%",
                "esc-telemetry:burst:0ms@1%", "gyro:delayed:5ms@1%"):
        with pytest.raises(FaultSpecError):
            parse_fault(bad)


def test_the_fault_time_is_seeded_and_inside_the_window() -> None:
    a, b = fault_ticks(7, 50, 1000, 0), fault_ticks(7, 50, 1000, 0)
    assert np.array_equal(a, b) and not np.array_equal(a, fault_ticks(8, 50, 1000, 0))
    assert a.min() >= 200 and a.max() < 500
    assert np.all(fault_ticks(7, 50, 1000, 300) == a + 300)


def test_attitude_departure() -> None:
    t = 1000
    sp = np.zeros((t, 3))
    sp[:, 0] = 2.0
    assert attitude_departure_deg(sp.copy(), sp, 0, 0.001) == pytest.approx(0.0, abs=1e-6)
    off = sp.copy()
    off[:, 0] = 1.0  # half the commanded roll rate for a second: 1 rad behind
    assert attitude_departure_deg(off, sp, 0, 0.001) == pytest.approx(math.degrees(1.0), rel=1e-3)
    assert attitude_departure_deg(off, sp, 500, 0.001) == pytest.approx(math.degrees(0.5), rel=1e-2)


def test_a_dead_motor_under_the_pid_and_its_table_row() -> None:
    cfg = EvalConfig(episodes=4, seed=3)
    nominal = run_controller("pid", cfg, progress=False)
    plan = FaultPlan(Fault("motor", "off", 1), cfg.seed, cfg.episodes, cfg.n_ticks)
    faulted = run_controller("pid", cfg, progress=False, faults=plan)
    assert np.array_equal(faulted.rate[0, :plan.ticks[0] + 1], nominal.rate[0, :plan.ticks[0] + 1])
    r = fault_result(plan, faulted, nominal, 0.001, policy=False)
    assert r.error_after > 5 * r.error_after_nominal and r.episodes == 4
    assert "motor 1 off" in fault_table([("pid", r)])


@pytest.mark.slow
def test_eval_cli_fault_json_and_report(tmp_path) -> None:
    out = fcemu("eval", "--controller", "pid", "--episodes", "3", "--seed", "2", "--json",
                "--fault", "gyro:stuck", "--fault", "esc-telemetry:delayed:5ms", "--report", str(tmp_path))
    assert out.returncode == 0, out.stderr
    faults = json.loads(out.stdout)["faults"]
    assert [f["fault"] for f in faults] == ["gyro stuck", "esc-telemetry delayed 0.005 s"]
    delayed = faults[1]  # the PID does not read rotor speed
    assert delayed["upright"] == 3
    assert delayed["error_after"] == pytest.approx(delayed["error_after_fault_free"])
    stuck = faults[0]["answers"]["gyro_failed"]  # each episode's ticks, summarised
    assert stuck["median_ticks"] <= stuck["p95_ticks"] <= stuck["worst_ticks"]
    assert "## Faults" in (tmp_path / "report.md").read_text()
    plain = fcemu("eval", "--controller", "pid", "--episodes", "3", "--seed", "2", "--json")
    assert "faults" not in json.loads(plain.stdout)


def test_a_bad_spec_is_one_line_exit_2() -> None:
    out = fcemu("eval", "--episodes", "1", "--fault", "gyro:melted")
    assert out.returncode == 2 and out.stdout == ""
    assert out.stderr.startswith("fcemu: error: --fault 'gyro:melted'") and out.stderr.count("\n") == 1
