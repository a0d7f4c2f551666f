"""MAVLink message → what the vehicle should do: pure translation, no sockets.

`Handlers.handle(link, msg)` checks a received message and returns what it asks for, as
`Output`s the MAVLink process (`Station`) carries out: setpoints and requests for the flight
process (typed `ipc` messages), parameter changes, texts, telemetry to send. Replies that
only concern the sending link (COMMAND_ACK for what is decided here, PARAM_VALUE,
MISSION_COUNT, FTP NAKs, TIMESYNC) go straight out on `link`. Messages for another system or
component, non-finite or out-of-range values are refused and counted in `counters`. Arming
and mode changes are decided by the vehicle in the flight process; their COMMAND_ACK goes
out when its answer comes back.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from typing import NamedTuple, Protocol

from pymavlink.dialects.v20 import common as mavlink

from firmware.mavlink import ipc, telemetry
from firmware.params import CONTROLLERS, ParamTable
from firmware.vehicle import FORCE_ARM_MAGIC, LAND

M = mavlink
MAX_RATE = 35.0  # rad/s (2000 deg/s, Betaflight's ceiling)
IGNORE_ATTITUDE = 128
IGNORE_THRUST = 64
RC_IGNORE = (0, 65535)
QUIET = frozenset({"COMMAND_ACK", "REQUEST_DATA_STREAM", "SYSTEM_TIME", "PING", "RADIO_STATUS",
                   "PARAM_EXT_REQUEST_LIST", "MISSION_SET_CURRENT", "GPS_RTCM_DATA", "LOG_REQUEST_LIST"})
COUNTERS = ("rx_rejected", "rx_foreign", "rx_unsupported", "rx_unhandled")

FTP_HEADER = struct.Struct("<HBBBBBBI")  # seq, session, opcode, size, req_opcode, burst_complete, pad, offset
FTP_TERMINATE_SESSION, FTP_RESET_SESSIONS, FTP_ACK, FTP_NAK = 1, 2, 128, 129
FTP_LOOKUPS = (3, 4, 14, 16)  # ListDirectory, OpenFileRO, CalcFileCRC32, ListDirectoryWithTime
FTP_ERR_UNKNOWN_COMMAND, FTP_ERR_FILE_NOT_FOUND = 7, 10


class Link(Protocol):
    """One peer's link as the handlers see it (firmware/mavlink/endpoint.py)."""

    mav: mavlink.MAVLink
    scheduler: telemetry.Scheduler
    peer_seen: tuple[int, int] | None

    def send(self, msg: mavlink.MAVLink_message) -> None: ...


class Forward(NamedTuple):
    """A request for the vehicle; `origin` (the message) is answered with a COMMAND_ACK once the
    vehicle replies, unless it is None (SET_MODE has no ACK)."""

    request: ipc.ArmRequest | ipc.ModeRequest
    command: int
    origin: mavlink.MAVLink_message | None


class ParamChanged(NamedTuple):
    name: str


class ParamListRequested(NamedTuple):
    requester: tuple[int, int]


class Say(NamedTuple):
    severity: int
    text: str
    to_sender: bool = False  # only the link it came from (else every link)
    once: bool = False
    limited: bool = False  # one of many possible answers to bad input: rate-limited


class SendTelemetry(NamedTuple):
    msgid: int


Output = ipc.Setpoint | ipc.Sticks | Forward | ParamChanged | ParamListRequested | Say | SendTelemetry
NOTHING: list[Output] = []


def _finite(*values: float) -> bool:
    return all(isinstance(v, int | float) and math.isfinite(v) for v in values)


def command_ack(link: Link, msg: mavlink.MAVLink_message, command: int, result: int) -> None:
    link.send(link.mav.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))


class Handlers:
    def __init__(self, sysid: int, params: ParamTable, controllers: list[str], has_position: bool,
                 vehicle_time_us: Callable[[], int]) -> None:
        self.sysid = sysid
        self.params = params
        self.controllers = controllers
        self.has_position = has_position
        self.vehicle_time_us = vehicle_time_us
        self.counters = dict.fromkeys(COUNTERS, 0)
        self._thrust = 0.0

    def handle(self, link: Link, msg: mavlink.MAVLink_message) -> list[Output]:
        kind = msg.get_type()
        fn = getattr(self, "on_" + kind.lower(), None)
        if fn is None:
            if kind not in QUIET:
                self._count("rx_unhandled")
            return NOTHING
        try:
            return fn(link, msg) or NOTHING
        except (TypeError, ValueError, OverflowError, UnicodeError, IndexError, KeyError):
            self._count("rx_rejected")
            return NOTHING

    def _count(self, what: str) -> None:
        self.counters[what] += 1

    def _for_us(self, msg, component: bool = True) -> bool:
        ok = msg.target_system in (0, self.sysid) and (
            not component or getattr(msg, "target_component", 0) in (0, 1))
        if not ok:
            self._count("rx_foreign")
        return ok

    def _reject(self) -> None:
        self._count("rx_rejected")

    def _deny(self, link: Link, msg, cmd: int) -> None:
        self._reject()
        command_ack(link, msg, cmd, M.MAV_RESULT_DENIED)

    # ---- presence ----
    def on_heartbeat(self, link: Link, msg) -> None:
        link.peer_seen = (msg.get_srcSystem(), msg.get_srcComponent())

    # ---- setpoints ----
    def on_set_attitude_target(self, link: Link, msg) -> list[Output] | None:
        if not self._for_us(msg):
            return None
        mask = msg.type_mask
        if not mask & IGNORE_ATTITUDE:
            self._count("rx_unsupported")
            return [Say(4, "Attitude setpoints unsupported: send body rates", once=True)]
        rates = tuple(0.0 if mask & bit else v for bit, v in
                      ((1, msg.body_roll_rate), (2, msg.body_pitch_rate), (4, msg.body_yaw_rate)))
        thrust = self._thrust if mask & IGNORE_THRUST else msg.thrust
        if not _finite(*rates, thrust) or max(abs(r) for r in rates) > MAX_RATE or not 0.0 <= thrust <= 1.0:
            return self._reject()
        self._thrust = thrust
        return [ipc.Setpoint(rates, float(thrust))]

    def on_manual_control(self, link: Link, msg) -> list[Output] | None:
        if msg.target not in (0, self.sysid):
            return self._count("rx_foreign")
        x, y, z, r = msg.x, msg.y, msg.z, msg.r
        if max(abs(x), abs(y), abs(r)) > 1000 or not 0 <= z <= 1000:
            return self._reject()
        # MANUAL_CONTROL: x = pitch (forward +, i.e. nose down), y = roll, z = thrust, r = yaw.
        return [ipc.Sticks(y / 1000.0, -x / 1000.0, r / 1000.0, z / 1000.0)]

    def on_rc_channels_override(self, link: Link, msg) -> list[Output] | None:
        if not self._for_us(msg):
            return None
        raw = (msg.chan1_raw, msg.chan2_raw, msg.chan3_raw, msg.chan4_raw)
        if any(c in RC_IGNORE for c in raw):
            return self._count("rx_unhandled")
        if any(not 800 <= c <= 2200 for c in raw):
            return self._reject()
        c = [min(max(v, 1000), 2000) for v in raw]
        # AETR: ch1 roll, ch2 pitch (high = stick forward = nose down), ch3 throttle, ch4 yaw.
        return [ipc.Sticks((c[0] - 1500) / 500, -(c[1] - 1500) / 500, (c[3] - 1500) / 500,
                           (c[2] - 1000) / 1000)]

    # ---- modes and commands ----
    def on_set_mode(self, link: Link, msg) -> list[Output] | None:
        if msg.target_system != self.sysid:
            return self._count("rx_foreign")
        if not msg.base_mode & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return self._reject()
        main, sub = (msg.custom_mode >> 16) & 0xFF, (msg.custom_mode >> 24) & 0xFF
        return [Forward(ipc.ModeRequest(main, sub), M.MAVLINK_MSG_ID_SET_MODE, None)]

    def on_command_long(self, link: Link, msg) -> list[Output] | None:
        return self._command(link, msg, (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5,
                                         msg.param6, msg.param7))

    def on_command_int(self, link: Link, msg) -> list[Output] | None:
        return self._command(link, msg, (msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y, msg.z))

    def _command(self, link: Link, msg, raw: tuple) -> list[Output] | None:
        if not self._for_us(msg):
            return None
        cmd = msg.command
        # NaN is MAVLink's "unset" (MAVSDK sends it in every param a command does not use):
        # it becomes None here and is refused only where the command needs the value.
        # Infinity is never valid.
        if not all(isinstance(v, int | float) and not math.isinf(v) for v in raw):
            return self._deny(link, msg, cmd)
        p = tuple(None if math.isnan(v) else v for v in raw)
        if cmd == M.MAV_CMD_COMPONENT_ARM_DISARM:
            if p[0] not in (0.0, 1.0):
                return self._deny(link, msg, cmd)
            force = p[1] is not None and abs(p[1]) < 1 << 31 and int(p[1]) == FORCE_ARM_MAGIC
            return [Forward(ipc.ArmRequest(p[0] == 1.0, force), cmd, msg)]
        if cmd == M.MAV_CMD_DO_SET_MODE:
            base, main, sub = p[0], p[1], 0.0 if p[2] is None else p[2]
            if base is None or main is None or not int(base) & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED \
                    or not (0 <= main < 256 and 0 <= sub < 256):
                return self._deny(link, msg, cmd)
            return [Forward(ipc.ModeRequest(int(main), int(sub)), cmd, msg)]
        if cmd == M.MAV_CMD_NAV_LAND:
            return [Forward(ipc.ModeRequest(*LAND), cmd, msg)]
        if cmd in (M.MAV_CMD_REQUEST_MESSAGE, M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES):
            return self._request_message(link, msg, cmd, p[0])
        if cmd == M.MAV_CMD_SET_MESSAGE_INTERVAL:
            if p[0] is None or p[1] is None:
                return self._deny(link, msg, cmd)
            ok = link.scheduler.set_interval(int(p[0]), p[1]) if 0 <= p[0] < 1 << 24 else False
            if not ok:
                self._count("rx_unsupported")
            return command_ack(link, msg, cmd, M.MAV_RESULT_ACCEPTED if ok else M.MAV_RESULT_UNSUPPORTED)
        if cmd == M.MAV_CMD_GET_MESSAGE_INTERVAL:
            msgid = int(p[0]) if p[0] is not None and 0 <= p[0] < 1 << 24 else 0
            command_ack(link, msg, cmd, M.MAV_RESULT_ACCEPTED)
            return link.send(link.mav.message_interval_encode(msgid, link.scheduler.interval(msgid)))
        self._count("rx_unsupported")
        return command_ack(link, msg, cmd, M.MAV_RESULT_UNSUPPORTED)

    def _request_message(self, link: Link, msg, cmd: int, param1: float | None) -> list[Output] | None:
        if cmd == M.MAV_CMD_REQUEST_MESSAGE and (param1 is None or not 0 <= param1 < 1 << 24):
            return self._deny(link, msg, cmd)
        msgid = M.MAVLINK_MSG_ID_AUTOPILOT_VERSION if cmd != M.MAV_CMD_REQUEST_MESSAGE else int(param1)
        if msgid not in telemetry.REQUESTABLE and msgid != M.MAVLINK_MSG_ID_MESSAGE_INTERVAL:
            self._count("rx_unsupported")
            return command_ack(link, msg, cmd, M.MAV_RESULT_UNSUPPORTED)
        if msgid == M.MAVLINK_MSG_ID_LOCAL_POSITION_NED and not self.has_position:
            return command_ack(link, msg, cmd, M.MAV_RESULT_UNSUPPORTED)
        command_ack(link, msg, cmd, M.MAV_RESULT_ACCEPTED)
        return [SendTelemetry(msgid)]

    # ---- parameters ----
    def send_param(self, link: Link, name: str) -> None:
        table = self.params
        link.send(link.mav.param_value_encode(name.encode(), table.encode_wire(name), table.specs[name].kind,
                                              len(table), table.index(name)))

    def on_param_request_list(self, link: Link, msg) -> list[Output] | None:
        if self._for_us(msg):  # streamed within the link's budget by the Station
            return [ParamListRequested((msg.get_srcSystem(), msg.get_srcComponent()))]
        return None

    def on_param_request_read(self, link: Link, msg) -> None:
        if not self._for_us(msg):
            return None
        names = self.params.names
        if msg.param_index >= 0:
            if msg.param_index >= len(names):
                return self._reject()
            return self.send_param(link, names[msg.param_index])
        name = msg.param_id.rstrip("\x00")
        if name not in self.params.specs:
            return self._reject()
        return self.send_param(link, name)

    def on_param_set(self, link: Link, msg) -> list[Output] | None:
        if not self._for_us(msg):
            return None
        table = self.params
        name = msg.param_id.rstrip("\x00")
        if name not in table.specs:
            self._reject()
            return [Say(4, f"Unknown parameter {name[:30]}", to_sender=True, limited=True)]
        value = table.decode_wire(name, msg.param_value, msg.param_type)
        problem = ""
        if name == "CTRL_SEL" and _finite(value) and 0 <= value < len(CONTROLLERS) \
                and CONTROLLERS[int(value)] not in self.controllers:
            problem = f"CTRL_SEL: {CONTROLLERS[int(value)]} controller not loaded"
        problem = problem or table.set(name, value)
        if problem:
            self._reject()
            self.send_param(link, name)
            return [Say(4, f"Param rejected: {problem}", to_sender=True, limited=True)]
        return [ParamChanged(name)]

    def on_param_ext_request_read(self, link: Link, msg) -> None:
        self._count("rx_unsupported")

    # ---- MAVLink FTP (none) ----
    def on_file_transfer_protocol(self, link: Link, msg) -> None:
        """No file system: each request is answered at once (NAK, or ACK to end a session), so
        clients fall back without waiting out their timeouts (MAVProxy's parameter download)."""
        if not self._for_us(msg):
            return
        seq, session, opcode, *_ = FTP_HEADER.unpack_from(bytes(msg.payload))
        if opcode in (FTP_TERMINATE_SESSION, FTP_RESET_SESSIONS):
            reply, size, data = FTP_ACK, 0, 0
        else:
            reply, size = FTP_NAK, 1
            data = FTP_ERR_FILE_NOT_FOUND if opcode in FTP_LOOKUPS else FTP_ERR_UNKNOWN_COMMAND
        self._count("rx_unsupported")
        body = FTP_HEADER.pack((seq + 1) & 0xFFFF, session, reply, size, opcode, 0, 0, 0) + bytes([data])
        link.send(link.mav.file_transfer_protocol_encode(0, msg.get_srcSystem(), msg.get_srcComponent(),
                                                         list(body.ljust(251, b"\0"))))

    # ---- mission (none) and time ----
    def on_mission_request_list(self, link: Link, msg) -> None:
        if self._for_us(msg):
            src = (msg.get_srcSystem(), msg.get_srcComponent())
            link.send(link.mav.mission_count_encode(*src, 0, msg.mission_type))

    def on_mission_count(self, link: Link, msg) -> None:
        if self._for_us(msg):
            result = M.MAV_MISSION_ACCEPTED if msg.count == 0 else M.MAV_MISSION_UNSUPPORTED
            link.send(link.mav.mission_ack_encode(msg.get_srcSystem(), msg.get_srcComponent(), result,
                                                  msg.mission_type))

    def on_mission_clear_all(self, link: Link, msg) -> None:
        if self._for_us(msg):
            link.send(link.mav.mission_ack_encode(msg.get_srcSystem(), msg.get_srcComponent(),
                                                  M.MAV_MISSION_ACCEPTED, msg.mission_type))

    def on_timesync(self, link: Link, msg) -> None:
        if msg.tc1 == 0:
            link.send(link.mav.timesync_encode(self.vehicle_time_us() * 1000, msg.ts1))
