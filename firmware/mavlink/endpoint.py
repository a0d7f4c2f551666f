"""One MAVLink link per peer: a UDP socket that sends to the peer (PX4's udpout) and parses
what comes back, with its own sequence numbers and, if required, MAVLink 2 signing.

Parsing, packing and signing are pymavlink's; the link only moves bytes and counts."""

from __future__ import annotations

import hashlib
import socket
import struct
import time
from pathlib import Path

from pymavlink.dialects.v20 import common as mavlink

from fcemu.firmware.mavlink.budget import InputBudget
from fcemu.firmware.mavlink.signing import SigningState, signing_now
from fcemu.firmware.mavlink.telemetry import Scheduler
from fcemu.firmware.mavlink.tlog import TlogWriter

SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)  # Linux: the socket's drop count with each datagram
ANCILLARY_SPACE = socket.CMSG_SPACE(4)


def load_signing_key(path: str | Path) -> bytes:
    """32 raw bytes, 64 hex digits, or a passphrase (SHA-256 of it, as MAVProxy's `signing setup`)."""
    raw = Path(path).read_bytes()
    if len(raw) == 32:
        return raw
    text = raw.decode("utf-8", errors="strict").strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text)
        except ValueError:
            pass
    if not text:
        raise ValueError(f"signing key file {path} is empty")
    return hashlib.sha256(text.encode()).digest()


class _Writer:
    """The file pymavlink's `MAVLink.send` writes to: the peer's UDP address, and the tlog."""

    def __init__(self, endpoint: Endpoint) -> None:
        self._ep = endpoint

    def write(self, buf: bytes) -> None:
        ep = self._ep
        try:
            ep.sock.sendto(buf, ep.address)
            ep.tx += 1
        except OSError:  # peer not listening yet (ECONNREFUSED on loopback) or buffer full
            ep.tx_errors += 1
        if ep.tlog is not None:
            ep.tlog.write(buf)


class Endpoint:
    def __init__(self, name: str, host: str, port: int, sysid: int, link_id: int,
                 signing: SigningState | None = None, tlog: TlogWriter | None = None,
                 scheduler: Scheduler | None = None) -> None:
        self.name = name
        self.scheduler = scheduler or Scheduler(has_position=False)  # this link's streams
        self.address = (host, port)
        self.tlog = tlog
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("0.0.0.0" if host not in ("127.0.0.1", "localhost") else "127.0.0.1", 0))
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)  # room for a burst
        self.sock.setblocking(False)
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
        except OSError:
            pass
        self.kernel_dropped = 0  # datagrams the kernel dropped with our receive buffer full
        self.muted = False  # the MAVLink signal failed by injection: nothing goes out
        self.mav = mavlink.MAVLink(_Writer(self), srcSystem=sysid, srcComponent=1)
        self.mav.robust_parsing = True
        self.tx = self.tx_errors = self.rx = self.bad = 0
        self.peer_seen: tuple[int, int] | None = None  # (sysid, compid) of the last HEARTBEAT
        self.budget = InputBudget()
        self.signing = signing
        self.signed = signing is not None
        if signing is not None:
            s = self.mav.signing
            s.secret_key = signing.key
            s.link_id = link_id
            s.timestamp = signing_now()
            s.sign_outgoing = True
            s.allow_unsigned_callback = lambda _mav, _msgid: False
            self.mav.check_signature = signing.check  # verifies before it remembers (see signing.py)

    def fileno(self) -> int:
        return self.sock.fileno()

    def readable(self, now: float) -> bool:
        """Whether to read this link now: not while it is over its input ceiling (`InputBudget`)."""
        return self.budget.open(now)

    def receive(self, now: float | None = None) -> list:
        """Frames waiting on the socket, parsed, within the link's input budget; bad ones come back
        as MAVLink_bad_data. A sender over its share has its datagrams dropped unparsed; a link over
        its ceiling is left to the kernel, which drops what its buffer cannot hold (counted too).
        `now`: the caller's time.monotonic() (read here when not given)."""
        if now is None:
            now = time.monotonic()
        out = []
        budget = self.budget
        for _ in range(256):
            if not budget.open(now):
                break
            try:
                data, ancillary, _, sender = self.sock.recvmsg(65536, ANCILLARY_SPACE)
            except OSError:  # nothing waiting (BlockingIOError), a refused send's ICMP, a closed socket
                break
            for level, kind, value in ancillary:
                if level == socket.SOL_SOCKET and kind == SO_RXQ_OVFL and len(value) >= 4:
                    self.kernel_dropped = struct.unpack_from("I", value)[0]
            if not budget.admit(sender, len(data)):
                continue
            self._restart_parser()
            try:
                msgs = self.mav.parse_buffer(data) or []
            except Exception:  # pymavlink raises on some corrupt input even when robust
                self.bad += 1
                continue
            for m in msgs:
                if m.get_type() == "BAD_DATA":
                    self.bad += 1
                    continue
                self.rx += 1
                if self.tlog is not None:
                    self.tlog.write(m.get_msgbuf())
                out.append(m)
        return out

    def _restart_parser(self) -> None:
        """Every UDP datagram starts afresh. A frame cut short at the end of the previous one will
        never complete (peers send whole frames per datagram), and if kept, its claimed length
        would swallow the start of this datagram: a valid command after a truncated frame."""
        mav = self.mav
        if mav.buf_len():
            self.bad += 1
        mav.buf = bytearray()
        mav.buf_index = 0
        mav.expected_length = mavlink.HEADER_LEN_V1 + 2

    def send(self, msg) -> None:
        if not self.muted:
            self.mav.send(msg)

    def close(self) -> None:
        self.sock.close()
