"""Each example in examples/ flies what it says against a real `fcemu sitl` on loopback ports:
the pymavlink flip (the script `fcemu demo` flies) lands and disarms without a refusal; the MAVSDK
offboard-rates example exits 1 when the vehicle does not follow (that it climbs before it steps on
the free rig, and follows, is tests/firmware/mavlink/test_mavsdk.py's flight, checked from both ends)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from pymavlink import mavutil

from tests.firmware.mavlink.conftest import ROOT, free_udp_port

EXAMPLES = ROOT / "examples"
pytestmark = pytest.mark.slow


def run_example(name: str, *argv: str, timeout: float = 150.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(EXAMPLES / name), *argv], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT, env={**os.environ, "PYTHONUNBUFFERED": "1"})


def test_every_example_is_flown_by_a_test() -> None:
    tests = "".join(p.read_text() for p in (ROOT / "tests").rglob("test_*.py"))
    untested = [p.name for p in EXAMPLES.glob("*.py") if p.name not in tests]
    assert not untested, f"examples no test runs: {untested}"


@pytest.mark.timeout(180)
def test_pymavlink_flip_lands_then_disarms_without_a_refusal(sitl, tmp_path: Path) -> None:
    """The script `fcemu demo` flies (the example runs sitl/demo_flight.py), faster than real time:
    take-off above 2 m, the flip, a level landing, and the disarm once ON_GROUND."""
    gcs = free_udp_port()
    s = sitl(gcs=gcs, speed="2", controller="pid")
    summary_path = tmp_path / "flip.json"
    script = run_example("pymavlink_flip.py", "--connect", f"udpin:127.0.0.1:{gcs}", "--summary",
                         str(summary_path), "--timeout", "120")
    output = s.stop()
    assert script.returncode == 0, script.stdout[-2000:] + script.stderr[-2000:] + output[-2000:]
    flight = json.loads(summary_path.read_text())
    assert flight["completed"] and flight["phase"] == "done", flight
    assert flight["flip_deg"] > 250 and flight["max_altitude_m"] > 2.0, flight
    assert flight["final_altitude_m"] < 0.3 and flight["final_tilt_deg"] < 20, flight
    vehicle_line = next(line for line in output.splitlines() if line.startswith("vehicle:"))
    assert "disarm_denied" not in vehicle_line, vehicle_line  # it waited for ON_GROUND
    assert not any("Disarming denied" in text for text in flight["vehicle_messages"]), flight
    # the vehicle's clock against the wall clock of its record; the script's frames in that record
    log = mavutil.mavlink_connection(str(s.tlog))
    attitudes, from_script = [], 0
    while (m := log.recv_match()) is not None:
        if m.get_srcSystem() == 254:
            from_script += 1
        elif m.get_type() == "ATTITUDE":
            attitudes.append((m.time_boot_ms / 1000.0, m._timestamp))
    (vehicle0, wall0), (vehicle1, wall1) = attitudes[0], attitudes[-1]
    speed = (vehicle1 - vehicle0) / (wall1 - wall0)
    assert speed > 1.0 and from_script > 500, (speed, from_script)


@pytest.mark.timeout(120)
def test_mavsdk_offboard_rates_exits_1_when_the_vehicle_does_not_follow(sitl, tmp_path: Path) -> None:
    """1500 deg/s steps of 0.4 s on the rig: roll gets there, yaw (a reaction torque) cannot; the
    default threshold catches it, the script says so and fails."""
    pytest.importorskip("mavsdk.asyncio", reason="MAVSDK-Python 4.x is not installed")
    offboard = free_udp_port()
    sitl(rig="rig", offboard=offboard, controller="pid")
    summary_path = tmp_path / "rates.json"
    script = run_example("mavsdk_offboard_rates.py", "--connect", f"udpin://127.0.0.1:{offboard}",
                         "--rate", "1500", "--hold", "0.4", "--summary", str(summary_path))
    assert script.returncode == 1, script.stdout[-2000:] + script.stderr[-3000:]
    summary = json.loads(summary_path.read_text())
    assert summary["rig"] == "rig" and summary["completed"] and not summary["followed"], summary
    assert summary["worst_error_deg_s"] > summary["max_error_deg_s"] == 10.0, summary
    assert "the vehicle did not follow: worst error" in script.stderr
