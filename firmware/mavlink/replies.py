"""What the MAVLink process owes its peers besides telemetry: status texts (rate-limited where
they answer bad input) and the COMMAND_ACKs of requests the vehicle is deciding."""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import NamedTuple

from pymavlink.dialects.v20 import common as mavlink

from fcemu.firmware.mavlink import telemetry
from fcemu.firmware.mavlink.outputs import Link, command_ack

M = mavlink
TEXTS_PER_S_LIMITED = 5
REJECT_SUMMARY_EVERY_S = 5.0
ACK_TIMEOUT_S = 1.0
MAX_PENDING = 8


class StatusTexts:
    def __init__(self, links: Sequence[Link]) -> None:
        self.links = links
        self._said_once: set[str] = set()
        self._window = 0.0
        self._in_window = 0
        self._text_id = 0
        self._rejects_reported = 0
        self._last_summary = 0.0

    def say(self, severity: int, text: str, link: Link | None = None, once: bool = False,
            limited: bool = False) -> None:
        """To `link`, or to every link. `once`: never the same text twice. `limited`: one of many
        possible answers to bad input, at most TEXTS_PER_S_LIMITED a second (a flood gets the
        periodic "Input rejected" summary instead of a text per frame)."""
        if once:
            if text in self._said_once:
                return
            self._said_once.add(text)
        if limited:
            now = time.monotonic()
            if now - self._window >= 1.0:
                self._window, self._in_window = now, 0
            if self._in_window >= TEXTS_PER_S_LIMITED:
                return
            self._in_window += 1
        self._text_id = self._text_id % 0xFFFF + 1
        for e in [link] if link is not None else self.links:
            for message in telemetry.statustext(e.mav, severity, text, self._text_id):
                e.send(message)


    def report_rejects(self, stats: dict[str, int], now: float) -> None:
        """A summary of refused input, when there is more of it, at most every REJECT_SUMMARY_EVERY_S."""
        rejected = sum(stats[k] for k in ("rx_bad", "rx_rejected", "rx_foreign", "sig_rejected"))
        if rejected > self._rejects_reported and now - self._last_summary >= REJECT_SUMMARY_EVERY_S:
            self.say(4, f"Input rejected: bad {stats['rx_bad']} range {stats['rx_rejected']} "
                        f"foreign {stats['rx_foreign']} sig {stats['sig_rejected']}")
            self._rejects_reported, self._last_summary = rejected, now


class _Pending(NamedTuple):
    link: Link | None  # None: nothing to answer (SET_MODE)
    command: int
    origin: mavlink.MAVLink_message | None
    since: float


class PendingCommands:
    """Requests sent to the vehicle, by request id, until its Ack (or ACK_TIMEOUT_S) answers them."""

    def __init__(self) -> None:
        self._pending: dict[int, _Pending] = {}
        self._req = 0
        self.timed_out = 0

    def open(self, link: Link | None, command: int, origin: mavlink.MAVLink_message | None) -> int | None:
        """A request id for the vehicle, or None when too many are open (answered at once)."""
        if len(self._pending) >= MAX_PENDING:
            if link is not None and origin is not None:
                command_ack(link, origin, command, M.MAV_RESULT_TEMPORARILY_REJECTED)
            return None
        self._req += 1
        self._pending[self._req] = _Pending(link, command, origin, time.monotonic())
        return self._req

    def answer(self, req: int, result: int) -> None:
        p = self._pending.pop(req, None)
        if p is not None and p.link is not None and p.origin is not None:
            command_ack(p.link, p.origin, p.command, result)

    def expire(self, now: float) -> None:
        for req, p in list(self._pending.items()):
            if now - p.since > ACK_TIMEOUT_S:
                del self._pending[req]
                self.timed_out += 1
                if p.link is not None and p.origin is not None:
                    command_ack(p.link, p.origin, p.command, M.MAV_RESULT_TEMPORARILY_REJECTED)
