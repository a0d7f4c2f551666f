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
from collections.abc import Callable

from pymavlink.dialects.v20 import common as mavlink

from fcemu.firmware.mavlink import ipc, telemetry
from fcemu.firmware.mavlink.outputs import (
    COUNTERS,
    NOTHING,
    Checks,
    Forward,
    Link,
    MavlinkSignal,
    Output,
    Say,
    SendTelemetry,
    command_ack,
    finite,
)
from fcemu.firmware.mavlink.services import NoFilesNoMissions, ParameterProtocol
from fcemu.firmware.params import ParamTable
from fcemu.firmware.vehicle import FORCE_ARM_MAGIC, LAND, SETPOINT_RATE_MAX

M = mavlink
IGNORE_ATTITUDE = 128
IGNORE_THRUST = 64
RC_IGNORE = (0, 65535)
QUIET = frozenset({"COMMAND_ACK", "REQUEST_DATA_STREAM", "SYSTEM_TIME", "PING", "RADIO_STATUS",
                   "PARAM_EXT_REQUEST_LIST", "MISSION_SET_CURRENT", "GPS_RTCM_DATA", "LOG_REQUEST_LIST"})


class Handlers(Checks):
    """Every message type this vehicle handles, by `on_<type>` method of one of its groups."""

    def __init__(self, sysid: int, params: ParamTable, controllers: list[str], has_position: bool,
                 vehicle_time_us: Callable[[], int]) -> None:
        super().__init__(sysid, dict.fromkeys(COUNTERS, 0))
        self.has_position = has_position
        self.vehicle_time_us = vehicle_time_us
        self.parameters = ParameterProtocol(sysid, self.counters, params, controllers)
        self._groups = (self, self.parameters, NoFilesNoMissions(sysid, self.counters))
        self._thrust = 0.0

    @property
    def params(self) -> ParamTable:
        return self.parameters.params

    def send_param(self, link: Link, name: str) -> None:
        self.parameters.send_param(link, name)

    def handle(self, link: Link, msg: mavlink.MAVLink_message) -> list[Output]:
        kind = msg.get_type()
        name = "on_" + kind.lower()
        fn = next((getattr(g, name) for g in self._groups if hasattr(g, name)), None)
        if fn is None:
            if kind not in QUIET:
                self._count("rx_unhandled")
            return NOTHING
        try:
            return fn(link, msg) or NOTHING
        except (TypeError, ValueError, OverflowError, UnicodeError, IndexError, KeyError):
            self._count("rx_rejected")
            return NOTHING

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
        too_fast = max(abs(r) for r in rates) > SETPOINT_RATE_MAX
        if not finite(*rates, thrust) or too_fast or not 0.0 <= thrust <= 1.0:
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
        if cmd == M.MAV_CMD_INJECT_FAILURE:
            return self._inject_failure(link, msg, p)
        if cmd == M.MAV_CMD_GET_MESSAGE_INTERVAL:
            msgid = int(p[0]) if p[0] is not None and 0 <= p[0] < 1 << 24 else 0
            command_ack(link, msg, cmd, M.MAV_RESULT_ACCEPTED)
            return link.send(link.mav.message_interval_encode(msgid, link.scheduler.interval(msgid)))
        self._count("rx_unsupported")
        return command_ack(link, msg, cmd, M.MAV_RESULT_UNSUPPORTED)

    def _inject_failure(self, link: Link, msg, p: tuple) -> list[Output] | None:
        """PX4's rule: refused unless SYS_FAILURE_EN is 1. The MAVLink signal is this process's; every
        other unit goes to the flight process, whose twin decides (sim_bridge/faults.py)."""
        cmd = M.MAV_CMD_INJECT_FAILURE
        if self.params["SYS_FAILURE_EN"] != 1:
            self._deny(link, msg, cmd)
            return [Say(4, "Failure injection disabled (SYS_FAILURE_EN 0)", to_sender=True, limited=True)]
        unit, kind, instance = p[0], p[1], 0.0 if p[2] is None else p[2]
        if unit is None or kind is None or not (0 <= unit < 256 and 0 <= kind < 256 and 0 <= instance < 256):
            return self._deny(link, msg, cmd)
        unit, kind, instance = round(unit), round(kind), round(instance)
        if unit == M.FAILURE_UNIT_SYSTEM_MAVLINK_SIGNAL:
            if kind not in (M.FAILURE_TYPE_OK, M.FAILURE_TYPE_OFF):
                return command_ack(link, msg, cmd, M.MAV_RESULT_UNSUPPORTED)
            command_ack(link, msg, cmd, M.MAV_RESULT_ACCEPTED)
            on = kind == M.FAILURE_TYPE_OK
            return [Say(4, f"Failure injected: MAVLink signal {'ok' if on else 'off'}"), MavlinkSignal(on)]
        return [Forward(ipc.FailureRequest(unit, kind, instance), cmd, msg)]

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


    def on_timesync(self, link: Link, msg) -> None:
        if msg.tc1 == 0:
            link.send(link.mav.timesync_encode(self.vehicle_time_us() * 1000, msg.ts1))
