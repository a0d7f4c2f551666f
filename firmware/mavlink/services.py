"""The parameter protocol, and the answers of a vehicle with no files and no missions."""

from __future__ import annotations

import struct

from pymavlink.dialects.v20 import common as mavlink

from fcemu.firmware.mavlink.outputs import Checks, Link, Output, ParamChanged, ParamListRequested, Say, finite
from fcemu.firmware.params import CONTROLLERS, ParamTable

M = mavlink
FTP_HEADER = struct.Struct("<HBBBBBBI")  # seq, session, opcode, size, req_opcode, burst_complete, pad, offset
FTP_TERMINATE_SESSION, FTP_RESET_SESSIONS, FTP_ACK, FTP_NAK = 1, 2, 128, 129
FTP_LOOKUPS = (3, 4, 14, 16)  # ListDirectory, OpenFileRO, CalcFileCRC32, ListDirectoryWithTime
FTP_ERR_UNKNOWN_COMMAND, FTP_ERR_FILE_NOT_FOUND = 7, 10


class ParameterProtocol(Checks):
    def __init__(self, sysid: int, counters: dict[str, int], params: ParamTable,
                 controllers: list[str]) -> None:
        super().__init__(sysid, counters)
        self.params = params
        self.controllers = controllers

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
        if name == "CTRL_SEL" and finite(value) and 0 <= value < len(CONTROLLERS) \
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



class NoFilesNoMissions(Checks):
    """MAVLink FTP and the mission protocol, answered at once so clients do not wait out timeouts."""

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
