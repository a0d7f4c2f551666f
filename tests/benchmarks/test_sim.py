"""`fcemu bench sim --json`: one JSON object on stdout, with the figures it promises."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytestmark = pytest.mark.timeout(60)


@pytest.mark.parametrize("airframe", [[], ["--airframe", "crazyflie"]])
def test_bench_sim_json_prints_one_object_with_positive_rates(airframe: list[str]) -> None:
    command = [sys.executable, "-m", "fcemu", "bench", "sim", "--json", "--seconds", "0.3", "--envs", "16",
               *airframe]
    done = subprocess.run(command, capture_output=True, text=True, timeout=60, check=True)
    result = json.loads(done.stdout)  # raises if stdout holds anything but one JSON document
    assert isinstance(result, dict)
    for key in ("twin_steps_per_s", "udp_steps_per_s", "env_steps_per_s", "vec_env_steps_per_s",
                "sitl_lockstep_ticks_per_s"):
        assert isinstance(result[key], float) and result[key] > 0, key
