"""MAVSDK-Python (4.x, native core) flies examples/mavsdk_offboard_rates.py against the real SITL
on the free rig: connect, arm, climb, offboard with attitude-rate setpoints, offboard.stop() (HOLD),
LAND. The vehicle's rates must follow, as MAVSDK measures them and as the vehicle's own record (its
.tlog) shows."""

from __future__ import annotations

import json
import math
import os
import statistics
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as M

from tests.firmware.mavlink.conftest import ROOT, connect, free_udp_port, wait_for

pytest.importorskip("mavsdk.asyncio", reason="MAVSDK-Python 4.x is not installed")
pytestmark = pytest.mark.timeout(180)
EXAMPLE = ROOT / "examples" / "mavsdk_offboard_rates.py"
HOLD_PEER = Path(__file__).with_name("mavsdk_hold.py")
RATE_DEG_S = 60.0


def rate_tracking_from_tlog(path: Path, settle_s: float = 0.3) -> dict[tuple, list[float]]:
    """Per body-rate setpoint (rad/s, rounded) the vehicle received: |ATTITUDE rate − setpoint| on
    the vehicle's telemetry once the setpoint had held for `settle_s` of wall time."""
    log = mavutil.mavlink_connection(str(path))
    errors: dict[tuple, list[float]] = defaultdict(list)
    setpoint, since = None, 0.0
    while (m := log.recv_match(type=["SET_ATTITUDE_TARGET", "ATTITUDE"])) is not None:
        if m.get_type() == "SET_ATTITUDE_TARGET":
            sp = (round(m.body_roll_rate, 3), round(m.body_pitch_rate, 3), round(m.body_yaw_rate, 3))
            if sp != setpoint:
                setpoint, since = sp, m._timestamp
        elif setpoint is not None and m._timestamp - since > settle_s:
            measured = (m.rollspeed, m.pitchspeed, m.yawspeed)
            errors[setpoint].append(max(abs(a - b) for a, b in zip(measured, setpoint, strict=True)))
    return errors


def test_mavsdk_offboard_attitude_rates_are_followed(sitl, tmp_path) -> None:
    """On the free rig (the example's default): it climbs before it steps, and follows."""
    offboard_port = free_udp_port()  # MAVSDK binds it; the GCS link is our observer
    s = sitl(rig="free", offboard=offboard_port)
    gcs = connect(s.gcs_port)
    summary_path = tmp_path / "mavsdk.json"
    script = subprocess.run(
        [sys.executable, str(EXAMPLE), "--connect", f"udpin://127.0.0.1:{offboard_port}",
         "--rate", str(RATE_DEG_S), "--hold", "1.0", "--summary", str(summary_path)],
        # about 40 s alone; on a loaded host the landing alone may take 40 s (the script waits that long
        # for the disarm), and a run cut off at 120 s had written its summary: each call has its own
        # limit in the script, so a hang still ends there
        capture_output=True, text=True, timeout=240, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert script.returncode == 0, script.stdout[-2000:] + script.stderr[-3000:] + s.stop()[-2000:]
    summary = json.loads(summary_path.read_text())
    # what MAVSDK saw
    assert summary["rig"] == "free" and summary["followed"], summary
    assert summary["altitude_before_stop_m"] > 2.0, summary  # it flew the steps in the air
    assert summary["completed"] and summary["mode_during"] == "OFFBOARD", summary
    assert summary["mode_after_stop"] == "HOLD", summary
    assert summary["worst_error_deg_s"] < 6.0, summary
    assert all(r["samples"] >= 5 for r in summary["steps"]), summary
    # the vehicle went through OFFBOARD armed, and is disarmed after LAND
    wait_for(gcs, "HEARTBEAT", lambda m: not m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED, timeout=10)
    s.stop()
    log = mavutil.mavlink_connection(str(s.tlog))
    modes = set()
    while (hb := log.recv_match(type="HEARTBEAT")) is not None:
        if hb.get_srcSystem() == 1 and hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED:
            modes.add(mavutil.interpret_px4_mode(hb.base_mode, hb.custom_mode))
    assert {"OFFBOARD", "LOITER", "LAND"} <= modes, modes  # pymavlink names PX4's AUTO.LOITER "LOITER"
    # what the vehicle recorded: each ±60 deg/s step, on each axis, was flown (the setpoints that
    # level the vehicle between axes are others)
    tracking = rate_tracking_from_tlog(s.tlog)
    step = round(math.radians(RATE_DEG_S), 3)
    steps = [sp for sp in tracking if sorted(map(abs, sp)) == [0.0, 0.0, step]]
    assert len(steps) == 6, sorted(tracking)
    for sp in steps:
        assert len(tracking[sp]) >= 10 and statistics.median(tracking[sp]) < 0.1, (sp, tracking[sp][:20])


def test_mavsdk_offboard_stop_and_action_hold_hold_altitude(sitl) -> None:
    """MAVSDK's canonical ending: `offboard.stop()` asks for HOLD (PX4 AUTO.LOITER); so does
    `action.hold()`. On the free rig, where the vehicle has a position source, HOLD holds the
    altitude it was entered at; then LAND brings it down and it disarms."""
    from fcemu.sim_bridge.airframe import load_airframe

    hover = load_airframe().hover_throttle()
    offboard_port = free_udp_port()
    s = sitl(rig="free", offboard=offboard_port)
    script = subprocess.run(
        [sys.executable, str(HOLD_PEER), f"udpin://127.0.0.1:{offboard_port}", str(hover), "4.0"],
        capture_output=True, text=True, timeout=140, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert script.returncode == 0, script.stdout[-2000:] + script.stderr[-3000:]
    summary = json.loads(script.stdout.strip().splitlines()[-1])
    assert summary["mode_offboard"] == "OFFBOARD" and summary["mode_offboard_again"] == "OFFBOARD", summary
    assert summary["mode_after_action_hold"] == "HOLD", summary
    assert summary["mode_after_offboard_stop"] == "HOLD", summary
    assert summary["disarmed"], summary
    for key in ("track_action_hold", "track_offboard_stop"):
        track = summary[key]
        assert len(track) > 40, (key, track)
        late = [z for t, z in track if t >= 1.5]  # once the climb it was entered with has stopped
        assert -min(z for _, z in track) > 0.5, (key, track)  # it was flying
        assert max(late) - min(late) < 0.3, (key, late)  # altitude held within 0.3 m
    s.stop()
    log = mavutil.mavlink_connection(str(s.tlog))
    modes = set()
    while (hb := log.recv_match(type="HEARTBEAT")) is not None:
        if hb.get_srcSystem() == 1 and hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED:
            modes.add(hb.custom_mode)
    assert (4 << 16) | (3 << 24) in modes, modes  # PX4's AUTO_LOITER encoding
