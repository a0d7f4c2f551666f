"""`fcemu bench loop --json` prints exactly one JSON object, with --mavlink too."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.timeout(120)
def test_bench_loop_with_mavlink_prints_one_object() -> None:
    out = subprocess.run([sys.executable, "-m", "fcemu.cli", "bench", "loop", "--controller", "pid",
                          "--seconds", "1", "--mavlink", "--json"], cwd=ROOT, capture_output=True, text=True,
                         timeout=110, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert out.returncode == 0, out.stderr[-2000:]
    result = json.loads(out.stdout)
    assert isinstance(result, dict)
    assert result["rate_hz"] == 1000 and result["ticks"] > 0 and "deadline_misses" in result
    link = result["mavlink"]
    assert link["ticks"] > 0 and {"deadline_misses", "compute_us", "rx_frames", "tx_frames"} <= set(link)
    assert link["armed"] and link["mode"] == "OFFBOARD"
