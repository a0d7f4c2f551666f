"""The MAVLink process's Station in-process: what reaches the flight process, and in what order."""

from __future__ import annotations

import math
import socket

import pytest
from pymavlink.dialects.v20 import common as M

from fcemu.firmware.mavlink import ipc
from fcemu.firmware.mavlink.bridge import MavlinkConfig, PeerConfig
from fcemu.firmware.mavlink.process import Station
from fcemu.firmware.params import ParamTable

NAN = math.nan


@pytest.fixture
def station():
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    ours.setblocking(False)
    config = MavlinkConfig(peers=[PeerConfig("gcs", "127.0.0.1", 9)], params_file=None)
    from dataclasses import asdict

    st = Station(asdict(config), dict(ParamTable().values), theirs, ipc.SnapshotSlot())
    gcs = M.MAVLink(None, srcSystem=255, srcComponent=190)
    yield st, ours, gcs
    st.close()
    ours.close()
    theirs.close()


def deliver(st: Station, gcs: M.MAVLink, *messages) -> None:
    """Through pymavlink's parser, as the endpoint would: packed, then parsed back."""
    ep = st.endpoints[0]
    for m in messages:
        for parsed in ep.mav.parse_buffer(m.pack(gcs)) or []:
            st.receive(ep, parsed)


def to_flight(sock: socket.socket) -> list[ipc.Message]:
    out = []
    while True:
        try:
            msg = ipc.decode(sock.recv(65536))
        except BlockingIOError:
            return out
        out.append(msg)


def test_sticks_received_before_an_arm_command_reach_the_vehicle_first(station) -> None:
    st, flight, gcs = station
    st._sp_sent = 1e18  # a setpoint just went out: without ordering, the sticks would wait behind the ARM
    deliver(st, gcs, gcs.manual_control_encode(1, 0, 0, 600, 0, 0),
            gcs.command_long_encode(1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
    assert [type(m) for m in to_flight(flight)] == [ipc.Sticks, ipc.ArmRequest]


def test_setpoints_before_a_mode_change_and_a_param_set_go_first(station) -> None:
    st, flight, gcs = station
    st._sp_sent = 1e18
    deliver(st, gcs, gcs.set_attitude_target_encode(0, 1, 1, 128, [1, 0, 0, 0], 0.1, 0, 0, 0.5),
            gcs.command_long_encode(1, 1, M.MAV_CMD_DO_SET_MODE, 0, 1, 6, 0, 0, 0, 0, 0))
    deliver(st, gcs, gcs.set_attitude_target_encode(0, 1, 1, 128, [1, 0, 0, 0], 0.2, 0, 0, 0.5),
            gcs.param_set_encode(1, 1, b"COM_OF_LOSS_T", 1.0, M.MAV_PARAM_TYPE_REAL32))
    sent = to_flight(flight)
    assert [type(m) for m in sent] == [ipc.Setpoint, ipc.ModeRequest, ipc.Setpoint, ipc.ParamSet]
    assert sent[0].rates[0] == pytest.approx(0.1) and sent[2].rates[0] == pytest.approx(0.2)
    assert sent[1] == ipc.ModeRequest(6, 0, req=1) and sent[3] == ipc.ParamSet("COM_OF_LOSS_T", 1.0)


def test_nan_means_unset_in_command_params_but_infinity_and_missing_values_are_refused(station) -> None:
    """MAVSDK sends NaN in every param a command does not use; those commands must still work."""
    st, flight, gcs = station
    arm = M.MAV_CMD_COMPONENT_ARM_DISARM
    deliver(st, gcs, gcs.command_long_encode(1, 1, arm, 0, 1, NAN, NAN, NAN, NAN, NAN, NAN))
    deliver(st, gcs, gcs.command_long_encode(1, 1, M.MAV_CMD_DO_SET_MODE, 0, 1, 5, NAN, NAN, NAN, NAN, NAN))
    assert [type(m) for m in to_flight(flight)] == [ipc.ArmRequest, ipc.ModeRequest]
    rejected = st.handlers.counters["rx_rejected"]
    deliver(st, gcs, gcs.command_long_encode(1, 1, arm, 0, NAN, 0, 0, 0, 0, 0, 0),
            gcs.command_long_encode(1, 1, arm, 0, 1, math.inf, 0, 0, 0, 0, 0),
            gcs.command_long_encode(1, 1, M.MAV_CMD_DO_SET_MODE, 0, 1, NAN, 0, 0, 0, 0, 0),
            gcs.command_long_encode(1, 1, M.MAV_CMD_DO_SET_MODE, 0, 1, 1e9, 0, 0, 0, 0, 0),
            gcs.command_long_encode(1, 1, M.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 30, NAN, 0, 0, 0, 0, 0))
    assert to_flight(flight) == []
    assert st.handlers.counters["rx_rejected"] == rejected + 5


def test_a_frame_cut_short_does_not_swallow_the_next_datagram() -> None:
    """UDP carries whole frames: each datagram is parsed afresh (found by the fuzz test)."""
    import time

    from fcemu.firmware.mavlink.endpoint import Endpoint

    ep = Endpoint("gcs", "127.0.0.1", 9, 1, 0)
    gcs = M.MAVLink(None, srcSystem=255, srcComponent=0)
    long_frame = gcs.statustext_encode(1, b"x" * 50, 0, 0).pack(gcs)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as peer:
        peer.sendto(long_frame[:20], ep.sock.getsockname())
        peer.sendto(gcs.param_request_list_encode(1, 1).pack(gcs), ep.sock.getsockname())
        time.sleep(0.05)
        received = [m.get_type() for m in ep.receive()]
    ep.close()
    assert received == ["PARAM_REQUEST_LIST"] and ep.bad == 1
