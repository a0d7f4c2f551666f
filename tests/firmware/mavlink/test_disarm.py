"""A disarm request in flight is refused unless forced (PX4's rule), on the free rig at 3 m."""

from __future__ import annotations

import time

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as M

from tests.firmware.mavlink.conftest import connect, wait_for

pytestmark = pytest.mark.timeout(120)
ARM = M.MAV_CMD_COMPONENT_ARM_DISARM
FORCE = 21196
ALTITUDE = 3.0


class Hover:
    """An altitude hold in the peer, from LOCAL_POSITION_NED: MANUAL_CONTROL throttle at 50 Hz,
    sticks centred (STABILIZED keeps the vehicle level itself)."""

    def __init__(self, conn, hover: float) -> None:
        self.conn, self.hover = conn, hover
        self.z_sp = 0.0
        self.acks: list = []
        self.texts: list[str] = []

    def fly(self, seconds: float, climb_to: float | None = None) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            while (m := self.conn.recv_msg()) is not None:
                if m.get_type() == "COMMAND_ACK":
                    self.acks.append(m)
                elif m.get_type() == "STATUSTEXT":
                    self.texts.append(m.text)
            if climb_to is not None:
                self.z_sp = max(-climb_to, self.z_sp - 0.02 * 1.0)  # 1 m/s
            pos = self.conn.messages.get("LOCAL_POSITION_NED")
            thrust = 0.0
            if self.z_sp < 0.0 and pos is not None:
                thrust = min(max(self.hover + 0.15 * (pos.z - self.z_sp) + 0.2 * pos.vz, 0.3), 0.95)
            self.conn.mav.manual_control_send(1, 0, 0, round(thrust * 1000), 0, 0)
            time.sleep(0.02)

    def command(self, *params: float):
        p = [*params, 0, 0, 0, 0, 0, 0, 0][:7]
        self.acks.clear()
        self.conn.mav.command_long_send(1, 1, ARM, 0, *p)
        end = time.monotonic() + 5
        while time.monotonic() < end:
            self.fly(0.05)
            for ack in self.acks:
                if ack.command == ARM:
                    return ack
        raise AssertionError("no COMMAND_ACK")

    def state(self):
        hb = wait_for(self.conn, "HEARTBEAT", lambda m: m.get_srcSystem() == 1, timeout=3)
        return hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED, mavutil.interpret_px4_mode(hb.base_mode,
                                                                                          hb.custom_mode)


def test_disarm_in_flight_is_refused_unless_forced(sitl) -> None:
    s = sitl(rig="free")
    off = connect(s.offboard_port, source_system=245, source_component=190)
    for _ in range(10):  # a GCS asks again when an answer does not come (a busy machine)
        off.mav.param_request_read_send(1, 1, b"MPC_THR_HOVER", -1)
        try:
            value = wait_for(off, "PARAM_VALUE", lambda m: m.param_id == "MPC_THR_HOVER", timeout=2.0)
            break
        except TimeoutError:
            continue
    else:
        raise AssertionError("MPC_THR_HOVER never answered")
    hover = Hover(off, value.param_value)
    off.mav.param_set_send(1, 1, b"COM_RC_LOSS_T", 2.0, M.MAV_PARAM_TYPE_REAL32)  # a busy test process
    hover.fly(0.3)
    assert hover.command(1).result == M.MAV_RESULT_ACCEPTED
    for _ in range(30):
        hover.fly(0.5, climb_to=ALTITUDE)
        if abs(-off.messages["LOCAL_POSITION_NED"].z - ALTITUDE) < 0.3:
            break
    hover.fly(1.0, climb_to=ALTITUDE)
    assert -off.messages["LOCAL_POSITION_NED"].z == pytest.approx(ALTITUDE, abs=0.5)
    assert hover.state() == (M.MAV_MODE_FLAG_SAFETY_ARMED, "STABILIZED")

    hover.texts.clear()
    ack = hover.command(0, 0)
    assert ack.result in (M.MAV_RESULT_TEMPORARILY_REJECTED, M.MAV_RESULT_DENIED)
    hover.fly(1.0)
    assert any("not landed" in t for t in hover.texts), hover.texts
    assert hover.state() == (M.MAV_MODE_FLAG_SAFETY_ARMED, "STABILIZED")
    assert -off.messages["LOCAL_POSITION_NED"].z > ALTITUDE - 0.5  # still flying

    assert hover.command(0, FORCE).result == M.MAV_RESULT_ACCEPTED
    assert not hover.state()[0]
    out = s.stop()
    assert "Traceback" not in out, out[-3000:]
