"""What handling a MAVLink message can produce, and the checks every handler shares.

A handler replies on the sending `Link` itself when the reply concerns only that link; all
else it returns as `Output`s for the MAVLink process (`Station`) to carry out.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Protocol

from pymavlink.dialects.v20 import common as mavlink

from fcemu.firmware.mavlink import ipc, telemetry

M = mavlink
COUNTERS = ("rx_rejected", "rx_foreign", "rx_unsupported", "rx_unhandled")


class Link(Protocol):
    """One peer's link as the handlers see it (firmware/mavlink/endpoint.py)."""

    mav: mavlink.MAVLink
    scheduler: telemetry.Scheduler
    peer_seen: tuple[int, int] | None

    def send(self, msg: mavlink.MAVLink_message) -> None: ...


class Forward(NamedTuple):
    """A request for the vehicle; `origin` (the message) is answered with a COMMAND_ACK once the
    vehicle replies, unless it is None (SET_MODE has no ACK)."""

    request: ipc.ArmRequest | ipc.ModeRequest | ipc.FailureRequest
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


class MavlinkSignal(NamedTuple):
    """FAILURE_UNIT_SYSTEM_MAVLINK_SIGNAL: `on` False stops every link sending and receiving."""

    on: bool


Output = (ipc.Setpoint | ipc.Sticks | Forward | ParamChanged | ParamListRequested | Say | SendTelemetry
          | MavlinkSignal)
NOTHING: list[Output] = []



def finite(*values: float) -> bool:
    return all(isinstance(v, int | float) and math.isfinite(v) for v in values)


def command_ack(link: Link, msg: mavlink.MAVLink_message, command: int, result: int) -> None:
    link.send(link.mav.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))



class Checks:
    """Addressing and input checks, counted in `counters` (shared by every handler group)."""

    def __init__(self, sysid: int, counters: dict[str, int]) -> None:
        self.sysid = sysid
        self.counters = counters

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
