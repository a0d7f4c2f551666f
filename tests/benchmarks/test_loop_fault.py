"""`fcemu bench loop --fault SPEC`: the same figures again with the fault active, and the firmware's
answer to it; a SPEC that names no fault is one error line and status 2."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _bench(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fcemu.cli", "bench", "loop", *argv], cwd=ROOT,
                          capture_output=True, text=True, timeout=110,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_bench_loop_with_a_fault_repeats_the_run_and_reports_the_hand_over() -> None:
    from fcemu.firmware.controllers import DEFAULT_POLICY

    out = _bench("--controller", str(DEFAULT_POLICY), "--seconds", "1.5", "--fault", "esc-telemetry:off",
                 "--json")
    assert out.returncode == 0, out.stderr[-2000:]
    result = json.loads(out.stdout)
    faulted = result["with_fault"]
    assert result["ticks"] > 0 and faulted["ticks"] > 0 and "deadline_misses" in faulted
    assert "fault" not in result
    assert faulted["fault"]["spec"] == "esc-telemetry off"
    why = faulted["fault"]["handover"]
    assert why.startswith("rotor speed") and why.endswith("too old"), why  # its age, as no reading comes
    # once its last reading is older than NN_ESC_MAX_AGE (the rule's default), at 1 kHz
    from fcemu.firmware.health import HealthRules

    max_age_ticks = round(HealthRules.esc_max_age_s * 1000)
    assert 0 < faulted["fault"]["answers_ticks"]["handover"] <= max_age_ticks + 2


def test_bench_loop_refuses_a_fault_it_cannot_inject() -> None:
    out = _bench("--fault", "gyro:melted", "--seconds", "1")
    assert out.returncode == 2 and out.stdout == ""
    assert out.stderr.startswith("fcemu: error: argument --fault: --fault 'gyro:melted': gyro has no fault")
    assert len(out.stderr.strip().splitlines()) == 1
