"""MAVLink message → vehicle command, without sockets: what the handlers return and reply."""

from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20 import common as M

from fcemu.firmware.mavlink import ipc, outputs
from fcemu.firmware.mavlink.handlers import Handlers
from fcemu.firmware.mavlink.telemetry import Scheduler
from fcemu.firmware.params import ParamTable

NAN = math.nan


class RecordingLink:
    """A link that keeps what would be sent (pymavlink encodes; nothing is written anywhere)."""

    def __init__(self) -> None:
        self.mav = M.MAVLink(None, srcSystem=1, srcComponent=1)
        self.scheduler = Scheduler(has_position=False)
        self.peer_seen: tuple[int, int] | None = None
        self.sent: list = []

    def send(self, msg) -> None:
        self.sent.append(msg)


@pytest.fixture
def setup():
    handlers = Handlers(1, ParamTable(), ["pid"], has_position=False, vehicle_time_us=lambda: 5_000)
    gcs = M.MAVLink(None, srcSystem=255, srcComponent=190)

    def handle(message) -> list:
        parsed = M.MAVLink(None).parse_buffer(message.pack(gcs))
        assert parsed and len(parsed) == 1
        return handlers.handle(link, parsed[0])

    link = RecordingLink()
    return handlers, link, gcs, handle


def test_setpoints_and_sticks_become_typed_messages(setup) -> None:
    handlers, link, gcs, handle = setup
    out = handle(gcs.set_attitude_target_encode(0, 1, 1, 128, [1, 0, 0, 0], 0.5, -0.25, 0.0, 0.6))
    assert out == [ipc.Setpoint((0.5, -0.25, 0.0), pytest.approx(0.6))]
    assert handle(gcs.manual_control_encode(1, 500, -1000, 250, 0, 0)) == [ipc.Sticks(-1.0, -0.5, 0.0, 0.25)]
    assert handle(gcs.set_attitude_target_encode(0, 1, 1, 128, [1, 0, 0, 0], 99.0, 0, 0, 0.5)) == []
    assert handle(gcs.set_attitude_target_encode(0, 7, 1, 128, [1, 0, 0, 0], 0, 0, 0, 0.5)) == []
    assert handlers.counters["rx_rejected"] == 1 and handlers.counters["rx_foreign"] == 1
    assert link.sent == []


def test_mode_and_arm_commands_are_forwarded_as_requests(setup) -> None:
    _, link, gcs, handle = setup
    # MAVSDK's offboard.stop() and action.hold(): DO_SET_MODE AUTO / LOITER, NaN in the unused params
    hold = gcs.command_long_encode(1, 1, M.MAV_CMD_DO_SET_MODE, 0, 1, 4, 3, NAN, NAN, NAN, NAN)
    [fwd] = handle(hold)
    assert fwd.request == ipc.ModeRequest(4, 3) and fwd.command == M.MAV_CMD_DO_SET_MODE
    assert fwd.origin.get_srcSystem() == 255
    [fwd] = handle(gcs.set_mode_encode(1, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, (4 << 16) | (3 << 24)))
    assert fwd.request == ipc.ModeRequest(4, 3) and fwd.origin is None  # SET_MODE has no ACK
    [fwd] = handle(gcs.command_long_encode(1, 1, M.MAV_CMD_NAV_LAND, 0, 0, 0, 0, 0, 0, 0, 0))
    assert fwd.request == ipc.ModeRequest(4, 6)
    [fwd] = handle(gcs.command_long_encode(1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 21196, 0, 0, 0, 0, 0))
    assert fwd.request == ipc.ArmRequest(False, True)
    assert link.sent == []  # the vehicle answers these
    assert handle(gcs.command_long_encode(1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 2, 0, 0, 0, 0, 0, 0)) == []
    assert link.sent[-1].get_type() == "COMMAND_ACK" and link.sent[-1].result == M.MAV_RESULT_DENIED


def test_parameters_and_requests(setup) -> None:
    handlers, link, gcs, handle = setup
    out = handle(gcs.param_set_encode(1, 1, b"COM_OF_LOSS_T", 1.5, M.MAV_PARAM_TYPE_REAL32))
    assert out == [outputs.ParamChanged("COM_OF_LOSS_T")] and handlers.params["COM_OF_LOSS_T"] == 1.5
    [say] = handle(gcs.param_set_encode(1, 1, b"NO_SUCH", 1.0, M.MAV_PARAM_TYPE_REAL32))
    assert isinstance(say, outputs.Say) and say.to_sender and say.limited
    [say] = handle(gcs.param_set_encode(1, 1, b"CTRL_SEL", 1, M.MAV_PARAM_TYPE_INT32))  # not loaded
    assert "not loaded" in say.text and link.sent[-1].get_type() == "PARAM_VALUE"
    out = handle(gcs.command_long_encode(1, 1, M.MAV_CMD_REQUEST_MESSAGE, 0,
                                         M.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0))
    assert out == [outputs.SendTelemetry(M.MAVLINK_MSG_ID_AUTOPILOT_VERSION)]
    assert link.sent[-1].get_type() == "COMMAND_ACK" and link.sent[-1].result == M.MAV_RESULT_ACCEPTED
    handle(gcs.timesync_encode(0, 42))
    assert link.sent[-1].tc1 == 5_000_000 and link.sent[-1].ts1 == 42
    assert handle(gcs.param_request_list_encode(1, 1)) == [outputs.ParamListRequested((255, 190))]
