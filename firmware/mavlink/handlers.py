"""What the vehicle does with each MAVLink message it receives (in the MAVLink process).

Input is checked here before anything reaches the flight process: messages for another
system or component, non-finite or out-of-range values are refused and counted. Arming and
mode changes are decided by the vehicle in the flight process; their COMMAND_ACK goes out
when its answer comes back (`Station.on_ack`).
"""

from __future__ import annotations

import math
import struct
from typing import TYPE_CHECKING

from pymavlink.dialects.v20 import common as mavlink

from firmware.mavlink import telemetry
from firmware.params import CONTROLLERS, REAL32
from firmware.vehicle import FORCE_ARM_MAGIC

if TYPE_CHECKING:
    from firmware.mavlink.endpoint import Endpoint
    from firmware.mavlink.process import Station

M = mavlink
MAX_RATE = 35.0  # rad/s (2000 deg/s, Betaflight's ceiling)
IGNORE_ATTITUDE = 128
IGNORE_THRUST = 64
RC_IGNORE = (0, 65535)
QUIET = frozenset({"COMMAND_ACK", "REQUEST_DATA_STREAM", "SYSTEM_TIME", "PING", "RADIO_STATUS",
                   "PARAM_EXT_REQUEST_LIST", "MISSION_SET_CURRENT", "GPS_RTCM_DATA", "LOG_REQUEST_LIST"})
ACKED_IN_FLIGHT = (M.MAV_CMD_COMPONENT_ARM_DISARM, M.MAV_CMD_DO_SET_MODE, M.MAV_CMD_NAV_LAND)



FTP_HEADER = struct.Struct("<HBBBBBBI")  # seq, session, opcode, size, req_opcode, burst_complete, pad, offset
FTP_TERMINATE_SESSION, FTP_RESET_SESSIONS, FTP_ACK, FTP_NAK = 1, 2, 128, 129
FTP_LOOKUPS = (3, 4, 14, 16)  # ListDirectory, OpenFileRO, CalcFileCRC32, ListDirectoryWithTime
FTP_ERR_UNKNOWN_COMMAND, FTP_ERR_FILE_NOT_FOUND = 7, 10


def _finite(*values: float) -> bool:
    return all(isinstance(v, int | float) and math.isfinite(v) for v in values)


class Handlers:
    def __init__(self, station: Station) -> None:
        self.st = station
        self.sysid = station.sysid
        self._thrust = 0.0

    def handle(self, ep: Endpoint, msg) -> None:
        kind = msg.get_type()
        fn = getattr(self, "on_" + kind.lower(), None)
        if fn is None:
            if kind not in QUIET:
                self.st.count("rx_unhandled")
            return
        try:
            fn(ep, msg)
        except (TypeError, ValueError, OverflowError, UnicodeError, IndexError, KeyError):
            self.st.count("rx_rejected")

    def _for_us(self, msg, component: bool = True) -> bool:
        ok = msg.target_system in (0, self.sysid) and (
            not component or getattr(msg, "target_component", 0) in (0, 1))
        if not ok:
            self.st.count("rx_foreign")
        return ok

    def _reject(self) -> None:
        self.st.count("rx_rejected")

    # ---- presence ----
    def on_heartbeat(self, ep: Endpoint, msg) -> None:
        ep.peer_seen = (msg.get_srcSystem(), msg.get_srcComponent())

    # ---- setpoints ----
    def on_set_attitude_target(self, ep: Endpoint, msg) -> None:
        if not self._for_us(msg):
            return
        mask = msg.type_mask
        if not mask & IGNORE_ATTITUDE:
            self.st.count("rx_unsupported")
            self.st.say(4, "Attitude setpoints unsupported: send body rates", once=True)
            return
        rates = tuple(0.0 if mask & bit else v for bit, v in
                      ((1, msg.body_roll_rate), (2, msg.body_pitch_rate), (4, msg.body_yaw_rate)))
        thrust = self._thrust if mask & IGNORE_THRUST else msg.thrust
        if not _finite(*rates, thrust) or max(abs(r) for r in rates) > MAX_RATE or not 0.0 <= thrust <= 1.0:
            return self._reject()
        self._thrust = thrust
        self.st.setpoint(("sp", rates, float(thrust)))

    def on_manual_control(self, ep: Endpoint, msg) -> None:
        if msg.target not in (0, self.sysid):
            self.st.count("rx_foreign")
            return
        x, y, z, r = msg.x, msg.y, msg.z, msg.r
        if max(abs(x), abs(y), abs(r)) > 1000 or not 0 <= z <= 1000:
            return self._reject()
        # MANUAL_CONTROL: x = pitch (forward +, i.e. nose down), y = roll, z = thrust, r = yaw.
        self.st.setpoint(("sticks", y / 1000.0, -x / 1000.0, r / 1000.0, z / 1000.0))

    def on_rc_channels_override(self, ep: Endpoint, msg) -> None:
        if not self._for_us(msg):
            return
        raw = (msg.chan1_raw, msg.chan2_raw, msg.chan3_raw, msg.chan4_raw)
        if any(c in RC_IGNORE for c in raw):
            return self.st.count("rx_unhandled")
        if any(not 800 <= c <= 2200 for c in raw):
            return self._reject()
        c = [min(max(v, 1000), 2000) for v in raw]
        # AETR: ch1 roll, ch2 pitch (high = stick forward = nose down), ch3 throttle, ch4 yaw.
        self.st.setpoint(("sticks", (c[0] - 1500) / 500, -(c[1] - 1500) / 500, (c[3] - 1500) / 500,
                          (c[2] - 1000) / 1000))

    # ---- modes and commands ----
    def on_set_mode(self, ep: Endpoint, msg) -> None:
        if msg.target_system != self.sysid:
            self.st.count("rx_foreign")
            return
        if not msg.base_mode & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return self._reject()
        main, sub = (msg.custom_mode >> 16) & 0xFF, (msg.custom_mode >> 24) & 0xFF
        self.st.forward_command(None, ("mode", main, sub), M.MAVLINK_MSG_ID_SET_MODE, msg)

    def on_command_long(self, ep: Endpoint, msg) -> None:
        self._command(ep, msg, (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6,
                                msg.param7))

    def on_command_int(self, ep: Endpoint, msg) -> None:
        self._command(ep, msg, (msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y, msg.z))

    def _command(self, ep: Endpoint, msg, raw: tuple) -> None:
        if not self._for_us(msg):
            return
        cmd = msg.command
        ack = self.st.ack
        # NaN is MAVLink's "unset" (MAVSDK sends it in every param a command does not use):
        # it becomes None here and is refused only where the command needs the value.
        # Infinity is never valid.
        if not all(isinstance(v, int | float) and not math.isinf(v) for v in raw):
            self._reject()
            return ack(ep, msg, cmd, M.MAV_RESULT_DENIED)
        p = tuple(None if math.isnan(v) else v for v in raw)
        if cmd == M.MAV_CMD_COMPONENT_ARM_DISARM:
            if p[0] not in (0.0, 1.0):
                self._reject()
                return ack(ep, msg, cmd, M.MAV_RESULT_DENIED)
            force = p[1] is not None and abs(p[1]) < 1 << 31 and int(p[1]) == FORCE_ARM_MAGIC
            return self.st.forward_command(ep, ("arm", p[0] == 1.0, force), cmd, msg)
        if cmd == M.MAV_CMD_DO_SET_MODE:
            base, main, sub = p[0], p[1], 0.0 if p[2] is None else p[2]
            if base is None or main is None or not int(base) & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED \
                    or not (0 <= main < 256 and 0 <= sub < 256):
                self._reject()
                return ack(ep, msg, cmd, M.MAV_RESULT_DENIED)
            return self.st.forward_command(ep, ("mode", int(main), int(sub)), cmd, msg)
        if cmd == M.MAV_CMD_NAV_LAND:
            return self.st.forward_command(ep, ("mode", 4, 6), cmd, msg)
        if cmd in (M.MAV_CMD_REQUEST_MESSAGE, M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES):
            if cmd == M.MAV_CMD_REQUEST_MESSAGE and (p[0] is None or not 0 <= p[0] < 1 << 24):
                self._reject()
                return ack(ep, msg, cmd, M.MAV_RESULT_DENIED)
            msgid = M.MAVLINK_MSG_ID_AUTOPILOT_VERSION if cmd != M.MAV_CMD_REQUEST_MESSAGE else int(p[0])
            if msgid not in telemetry.REQUESTABLE and msgid != M.MAVLINK_MSG_ID_MESSAGE_INTERVAL:
                self.st.count("rx_unsupported")
                return ack(ep, msg, cmd, M.MAV_RESULT_UNSUPPORTED)
            if msgid == M.MAVLINK_MSG_ID_LOCAL_POSITION_NED and not self.st.has_position:
                return ack(ep, msg, cmd, M.MAV_RESULT_UNSUPPORTED)
            ack(ep, msg, cmd, M.MAV_RESULT_ACCEPTED)
            return self.st.send_one(ep, msgid)
        if cmd == M.MAV_CMD_SET_MESSAGE_INTERVAL:
            if p[0] is None or p[1] is None:
                self._reject()
                return ack(ep, msg, cmd, M.MAV_RESULT_DENIED)
            ok = self.st.scheduler(ep).set_interval(int(p[0]), p[1]) if 0 <= p[0] < 1 << 24 else False
            if not ok:
                self.st.count("rx_unsupported")
            return ack(ep, msg, cmd, M.MAV_RESULT_ACCEPTED if ok else M.MAV_RESULT_UNSUPPORTED)
        if cmd == M.MAV_CMD_GET_MESSAGE_INTERVAL:
            msgid = int(p[0]) if p[0] is not None and 0 <= p[0] < 1 << 24 else 0
            ack(ep, msg, cmd, M.MAV_RESULT_ACCEPTED)
            return ep.send(ep.mav.message_interval_encode(msgid, self.st.scheduler(ep).interval(msgid)))
        self.st.count("rx_unsupported")
        ack(ep, msg, cmd, M.MAV_RESULT_UNSUPPORTED)

    # ---- parameters ----
    def on_param_request_list(self, ep: Endpoint, msg) -> None:
        if self._for_us(msg):  # streamed within the link's budget (Station.param_streams)
            self.st.param_streams.request(ep, (msg.get_srcSystem(), msg.get_srcComponent()))

    def on_param_request_read(self, ep: Endpoint, msg) -> None:
        if not self._for_us(msg):
            return
        names = self.st.params.names
        if msg.param_index >= 0:
            if msg.param_index >= len(names):
                return self._reject()
            return self.st.send_param(ep, names[msg.param_index], msg.param_index)
        name = msg.param_id.rstrip("\x00")
        if name not in self.st.params.specs:
            return self._reject()
        self.st.send_param(ep, name, names.index(name))

    def on_param_set(self, ep: Endpoint, msg) -> None:
        if not self._for_us(msg):
            return
        table = self.st.params
        name = msg.param_id.rstrip("\x00")
        if name not in table.specs:
            self._reject()
            return self.st.say(4, f"Unknown parameter {name[:30]}", ep=ep, limited=True)
        value = table.decode_wire(name, msg.param_value, msg.param_type)
        problem = ""
        if name == "CTRL_SEL" and _finite(value) and 0 <= value < len(CONTROLLERS) \
                and CONTROLLERS[int(value)] not in self.st.controllers:
            problem = f"CTRL_SEL: {CONTROLLERS[int(value)]} controller not loaded"
        problem = problem or table.set(name, value)
        if problem:
            self._reject()
            self.st.send_param(ep, name, table.index(name))
            return self.st.say(4, f"Param rejected: {problem}", ep=ep, limited=True)
        self.st.param_changed(name)

    def on_param_ext_request_read(self, ep: Endpoint, msg) -> None:
        self.st.count("rx_unsupported")

    # ---- MAVLink FTP (none) ----
    def on_file_transfer_protocol(self, ep: Endpoint, msg) -> None:
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
        self.st.count("rx_unsupported")
        body = FTP_HEADER.pack((seq + 1) & 0xFFFF, session, reply, size, opcode, 0, 0, 0) + bytes([data])
        ep.send(ep.mav.file_transfer_protocol_encode(0, msg.get_srcSystem(), msg.get_srcComponent(),
                                                     list(body.ljust(251, b"\0"))))

    # ---- mission (none) and time ----
    def on_mission_request_list(self, ep: Endpoint, msg) -> None:
        if self._for_us(msg):
            src = (msg.get_srcSystem(), msg.get_srcComponent())
            ep.send(ep.mav.mission_count_encode(*src, 0, msg.mission_type))

    def on_mission_count(self, ep: Endpoint, msg) -> None:
        if self._for_us(msg):
            result = M.MAV_MISSION_ACCEPTED if msg.count == 0 else M.MAV_MISSION_UNSUPPORTED
            ep.send(ep.mav.mission_ack_encode(msg.get_srcSystem(), msg.get_srcComponent(), result,
                                              msg.mission_type))

    def on_mission_clear_all(self, ep: Endpoint, msg) -> None:
        if self._for_us(msg):
            ep.send(ep.mav.mission_ack_encode(msg.get_srcSystem(), msg.get_srcComponent(),
                                              M.MAV_MISSION_ACCEPTED, msg.mission_type))

    def on_timesync(self, ep: Endpoint, msg) -> None:
        if msg.tc1 == 0:
            ep.send(ep.mav.timesync_encode(self.st.time_ns(), msg.ts1))


PARAM_TYPE_DEFAULT = REAL32
