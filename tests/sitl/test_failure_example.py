"""examples/mavsdk_failure_handover.py against a real `fcemu sitl` flying the default policy on the
free rig: MAVSDK's failure plugin sticks motor 1's ESC telemetry in OFFBOARD hover, the policy hands
over to the PID (said once), the vehicle flies on and lands; against the PID the script exits 1."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.firmware.mavlink.conftest import free_udp_port
from tests.test_examples import run_example

pytestmark = pytest.mark.slow


@pytest.mark.timeout(180)
def test_motor_telemetry_stuck_hands_the_policy_over_and_the_vehicle_lands(sitl, tmp_path: Path) -> None:
    pytest.importorskip("mavsdk.asyncio", reason="MAVSDK-Python 4.x is not installed")
    from fcemu.firmware.controllers import DEFAULT_POLICY

    offboard = free_udp_port()
    s = sitl(rig="free", offboard=offboard, controller=str(DEFAULT_POLICY))
    summary_path = tmp_path / "handover.json"
    script = run_example("mavsdk_failure_handover.py", "--connect", f"udpin://127.0.0.1:{offboard}",
                         "--summary", str(summary_path))
    assert script.returncode == 0, script.stdout[-2000:] + script.stderr[-3000:] + s.stop()[-2000:]
    summary = json.loads(summary_path.read_text())
    assert summary["failure_text"] == "Failure injected: esc-telemetry 1 stuck", summary
    # a reading stuck while the motor's command moves: stale (bit-identical) or lagging (the fitted delay)
    assert summary["handover_text"] in (f"Policy hands over to PID: rotor speed 1 {why}"
                                        for why in ("stale", "lagging")), summary
    texts = summary["status_texts"]
    assert sum("hands over" in t for t in texts) == 1, texts
    assert summary["mode_after_handover"] == "OFFBOARD" and summary["altitude_after_handover_m"] > 2.0
    # the script clears the fault once disarmed; that report may arrive before it stops listening
    flown = [t for t in texts if "Failure injected: unit 101" not in t]
    assert summary["landed"] and flown[-1] == "INFO: Disarmed: landed", texts


@pytest.mark.timeout(180)  # the same flight up to the injection as above; the script's own limit is 150 s
def test_exits_1_when_no_policy_flies_to_hand_over(sitl, tmp_path: Path) -> None:
    pytest.importorskip("mavsdk.asyncio", reason="MAVSDK-Python 4.x is not installed")
    offboard = free_udp_port()
    sitl(rig="free", offboard=offboard, controller="pid")
    script = run_example("mavsdk_failure_handover.py", "--connect", f"udpin://127.0.0.1:{offboard}",
                         "--timeout", "1")
    assert script.returncode == 1, script.stdout[-2000:] + script.stderr[-3000:]
    assert "no 'Policy hands over to PID' within 1 s of the injection" in script.stderr
