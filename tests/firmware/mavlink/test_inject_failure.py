"""MAV_CMD_INJECT_FAILURE as PX4 takes it: refused unless SYS_FAILURE_EN is 1; the MAVLink signal is the
MAVLink process's, every other unit goes to the flight process (whose twin decides); and for real
against `fcemu sitl`: a motor's telemetry stuck under the policy hands it over to the PID, said once."""

from __future__ import annotations

import math
import time

import pytest
from pymavlink.dialects.v20 import common as M

from fcemu.firmware.mavlink import ipc, outputs
from fcemu.firmware.mavlink.handlers import Handlers
from fcemu.firmware.params import ParamTable
from tests.firmware.mavlink.conftest import connect, wait_for
from tests.firmware.mavlink.test_handlers import RecordingLink

NAN = math.nan
INJECT = M.MAV_CMD_INJECT_FAILURE


def _setup(enabled: bool):
    params = ParamTable()
    params.set("SYS_FAILURE_EN", int(enabled))
    handlers = Handlers(1, params, ["pid", "neural"], has_position=False, vehicle_time_us=lambda: 0)
    gcs = M.MAVLink(None, srcSystem=255, srcComponent=190)
    link = RecordingLink()

    def inject(unit: float, kind: float, instance: float = NAN) -> list:
        msg = gcs.command_long_encode(1, 1, INJECT, 0, unit, kind, instance, NAN, NAN, NAN, NAN)
        return handlers.handle(link, M.MAVLink(None).parse_buffer(msg.pack(gcs))[0])

    return link, inject


def test_refused_unless_sys_failure_en_is_1() -> None:
    assert ParamTable()["SYS_FAILURE_EN"] == 0
    link, inject = _setup(enabled=False)
    out = inject(M.FAILURE_UNIT_SENSOR_GYRO, M.FAILURE_TYPE_OFF)
    assert [m.result for m in link.sent] == [M.MAV_RESULT_DENIED]
    assert any(isinstance(o, outputs.Say) and "SYS_FAILURE_EN" in o.text for o in out)


def test_twin_units_are_forwarded_and_the_signal_is_handled_here() -> None:
    link, inject = _setup(enabled=True)
    out = inject(M.FAILURE_UNIT_SYSTEM_MOTOR, M.FAILURE_TYPE_STUCK, 2)
    assert len(out) == 1 and out[0].request == ipc.FailureRequest(101, 2, 2) and out[0].command == INJECT
    assert link.sent == []  # acknowledged when the flight process answers
    out = inject(M.FAILURE_UNIT_SYSTEM_MAVLINK_SIGNAL, M.FAILURE_TYPE_OFF)
    assert outputs.MavlinkSignal(False) in out
    assert link.sent[-1].result == M.MAV_RESULT_ACCEPTED
    inject(M.FAILURE_UNIT_SYSTEM_MAVLINK_SIGNAL, M.FAILURE_TYPE_GARBAGE)
    assert link.sent[-1].result == M.MAV_RESULT_UNSUPPORTED
    assert inject(NAN, M.FAILURE_TYPE_OFF) == [] and link.sent[-1].result == M.MAV_RESULT_DENIED
    ipc_round_trip = ipc.decode(ipc.encode(ipc.FailureRequest(0, 2, 0, 7)))
    assert ipc_round_trip == ipc.FailureRequest(0, 2, 0, 7)


def _ack(conn, unit: int, kind: int, instance: int = 0, texts: list[str] | None = None) -> int:
    """Send the command; its COMMAND_ACK's result (STATUSTEXTs meanwhile go into `texts`)."""
    conn.mav.command_long_send(1, 1, INJECT, 0, unit, kind, instance, 0, 0, 0, 0)
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline:
        m = conn.recv_match(type=["COMMAND_ACK", "STATUSTEXT"], blocking=True, timeout=0.1)
        if m is not None and m.get_type() == "STATUSTEXT" and texts is not None:
            texts.append(m.text)
        elif m is not None and m.get_type() == "COMMAND_ACK" and m.command == INJECT:
            return m.result
    raise TimeoutError("no COMMAND_ACK to MAV_CMD_INJECT_FAILURE")


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_sitl_injects_in_the_twin_and_the_policy_hands_over(sitl) -> None:
    from fcemu.firmware.controllers import DEFAULT_POLICY

    s = sitl(rig="rig", controller=str(DEFAULT_POLICY))
    off = connect(s.offboard_port)
    assert _ack(off, M.FAILURE_UNIT_SENSOR_GYRO, M.FAILURE_TYPE_OFF) == M.MAV_RESULT_DENIED
    off.mav.param_set_send(1, 1, b"SYS_FAILURE_EN", 1, M.MAV_PARAM_TYPE_INT32)
    wait_for(off, "PARAM_VALUE", lambda m: m.param_id == "SYS_FAILURE_EN")
    assert _ack(off, M.FAILURE_UNIT_SENSOR_GPS, M.FAILURE_TYPE_OFF) == M.MAV_RESULT_UNSUPPORTED

    texts: list[str] = []

    def stream(seconds: float, rates=(0.0, 0.0, 0.0)) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            off.mav.set_attitude_target_send(0, 1, 1, 128, [1, 0, 0, 0], *rates, 0.7)
            time.sleep(0.01)
            while (m := off.recv_match(type="STATUSTEXT")) is not None:
                texts.append(m.text)

    stream(0.3)
    off.set_mode_px4("OFFBOARD", None, None)
    off.mav.command_long_send(1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    assert wait_for(off, "COMMAND_ACK", lambda m: m.command == M.MAV_CMD_COMPONENT_ARM_DISARM).result == 0
    stream(0.5, (1.0, 0.0, 0.0))
    assert not any("hands over" in t for t in texts), texts
    assert _ack(off, M.FAILURE_UNIT_SYSTEM_MOTOR, M.FAILURE_TYPE_STUCK, 1, texts) == M.MAV_RESULT_ACCEPTED
    end = time.monotonic() + 5.0
    while time.monotonic() < end and not any("hands over" in t for t in texts):
        stream(0.05, (1.0, 0.0, 0.0) if int(time.monotonic() * 4) % 2 else (-1.0, 0.0, 0.0))
    assert any("esc-telemetry 1 stuck" in t for t in texts), texts
    # a reading stuck while the motor's command moves: stale (bit-identical) or lagging (the fitted delay)
    handovers = [t for t in texts if t.startswith("Policy hands over to PID")]
    assert len(handovers) == 1 and handovers[0] in (f"Policy hands over to PID: rotor speed 1 {why}"
                                                    for why in ("stale", "lagging")), texts
    hb = wait_for(off, "HEARTBEAT", timeout=3.0)
    assert hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED

    # the MAVLink signal: off, nothing comes; OK (the one message heard meanwhile) brings it back
    assert _ack(off, M.FAILURE_UNIT_SYSTEM_MAVLINK_SIGNAL, M.FAILURE_TYPE_OFF) == M.MAV_RESULT_ACCEPTED
    time.sleep(0.3)
    while off.recv_msg() is not None:
        pass
    assert off.recv_match(type="HEARTBEAT", blocking=True, timeout=2.5) is None
    assert _ack(off, M.FAILURE_UNIT_SYSTEM_MAVLINK_SIGNAL, M.FAILURE_TYPE_OK) == M.MAV_RESULT_ACCEPTED
    assert wait_for(off, "HEARTBEAT", timeout=3.0) is not None
