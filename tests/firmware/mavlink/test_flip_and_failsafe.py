"""The offboard-loss failsafe acts (the bundled pymavlink script's take-off, flip and landing is
tests/test_examples.py's flight; `fcemu demo` itself, tests/test_wheel.py's)."""

from __future__ import annotations

import time

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as M

from tests.firmware.mavlink.conftest import connect, wait_for


def px4_mode(hb) -> str:
    return mavutil.interpret_px4_mode(hb.base_mode, hb.custom_mode)


def latest(conn, kind: str):
    """The newest `kind` after reading everything queued (streams pile up while a test sends)."""
    while conn.recv_msg() is not None:
        pass
    return conn.messages[kind]


@pytest.mark.timeout(90)
def test_offboard_setpoint_loss_lands_and_disarms(sitl) -> None:
    """Documented action: LAND within COM_OF_LOSS_T (hold FS_HOLD_T, descend), then disarm."""
    s = sitl(speed="realtime")
    off = connect(s.offboard_port)
    off.mav.param_set_send(1, 1, b"COM_OF_LOSS_T", 0.5, M.MAV_PARAM_TYPE_REAL32)
    off.mav.param_set_send(1, 1, b"FS_HOLD_T", 0.5, M.MAV_PARAM_TYPE_REAL32)

    def stream(seconds: float, thrust: float, until_height: float | None = None) -> None:
        """`thrust` for `seconds`, or until the vehicle is `until_height` up (a real-time SITL on a busy
        machine climbs late)."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            off.mav.set_attitude_target_send(0, 1, 1, 128, [1, 0, 0, 0], 0, 0, 0, thrust)
            time.sleep(0.01)
            if until_height is not None and "LOCAL_POSITION_NED" in off.messages \
                    and -latest(off, "LOCAL_POSITION_NED").z > until_height:
                return

    stream(0.3, 0.0)
    off.set_mode_px4("OFFBOARD", None, None)
    assert wait_for(off, "COMMAND_ACK", lambda m: m.command == M.MAV_CMD_DO_SET_MODE).result == 0
    off.mav.command_long_send(1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    assert wait_for(off, "COMMAND_ACK", lambda m: m.command == M.MAV_CMD_COMPONENT_ARM_DISARM).result == 0
    # Climb: some 2 m up once the failsafe has stopped it, a short LAND. Up to 10 s: the climb took
    # 3 s and more where the SITL shared a loaded machine, 0.5 s on an idle one.
    stream(10.0, 0.82, until_height=0.6)
    assert -latest(off, "LOCAL_POSITION_NED").z > 0.5
    stopped = time.monotonic()
    text = wait_for(off, "STATUSTEXT", lambda m: "Failsafe" in m.text, timeout=3.0).text
    assert "offboard setpoint loss" in text and time.monotonic() - stopped < 0.5 + 0.3
    hb = wait_for(off, "HEARTBEAT", lambda m: px4_mode(m) == "LAND", timeout=3.0)
    assert hb.system_status == M.MAV_STATE_CRITICAL
    # it comes down under control and disarms on touchdown
    wait_for(off, "HEARTBEAT", lambda m: not m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED, timeout=30)
    time.sleep(0.2)
    pos, att = latest(off, "LOCAL_POSITION_NED"), off.messages["ATTITUDE"]
    assert -pos.z < 0.3 and abs(att.roll) < 0.3 and abs(att.pitch) < 0.3
