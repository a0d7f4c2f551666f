"""`fcemu twin serve`: one twin behind the lockstep UDP link (see `sim_bridge.link`).

Each *new* PWM request advances the twin exactly one step and the reply carries the
resulting frame; a repeat of the last applied request is answered from the cache and
never steps twice. Every bad packet is counted, logged at most once a second per kind,
and answered with an ERROR where an address is known.

Faults (`--fault`, sim_bridge/faults.py) act from the first frame of every session: each RESET
starts them over, so a session is the in-process twin with the same faults, ages included.
"""

from __future__ import annotations

import contextlib
import json
import logging
import select
import signal
import socket
import sys
import threading
import time
from collections.abc import Sequence

from fcemu.sim_bridge.fault_spec import session_faults
from fcemu.sim_bridge.faults import Fault
from fcemu.sim_bridge.link import _DONTWAIT, _PWM, _PWM_SIZE, SPIN_TRIES, AdaptiveSpin
from fcemu.sim_bridge.protocol import (
    FRAME_MSG,
    MAGIC,
    MAX_DATAGRAM,
    PWM_MSG,
    VERSION,
    Bye,
    Error,
    ErrorCode,
    Frame,
    MsgType,
    ProtocolError,
    Pwm,
    Reset,
    decode,
    encode_error,
    pack_frame_into,
)
from fcemu.sim_bridge.sender_guard import (
    PEER_QUEUES,
    MutedQueues,
    SenderBudget,
    peer_queue,
    reuse_port_socket,
)
from fcemu.sim_bridge.twin import Twin

log = logging.getLogger(__name__)

STATUS_INTERVAL_S = 2.0
PUBLIC_DRAIN = 1024  # at most this many shared-queue packets are read first when a session starts
_RIG_NAMES = {"rig": "ball-joint rig", "free": "free body"}

BAD_PACKET_KINDS = ("malformed", "bad_version", "unknown_type", "unexpected_reply", "stale", "gap",
                    "foreign_peer", "no_session", "bad_argument", "internal_error")
_KIND_OF_CODE = {ErrorCode.MALFORMED: "malformed", ErrorCode.BAD_VERSION: "bad_version",
                 ErrorCode.UNKNOWN_TYPE: "unknown_type", ErrorCode.BAD_ARGUMENT: "bad_argument"}


class UdpTwinServer:
    """One twin served over UDP; `serve_forever()` in the foreground or `start()`/`stop()` in a thread."""

    def __init__(self, twin: Twin | None = None, host: str = "127.0.0.1", port: int = 0,
                 session_timeout: float = 2.0, spin: int = SPIN_TRIES, faults: Sequence[Fault] = ()) -> None:
        self.twin = twin or Twin()
        self.faults = tuple(faults)  # injected afresh at every RESET (`session_faults`)
        self.session_timeout = session_timeout
        self._spin = AdaptiveSpin(spin)
        self.counters: dict[str, int] = dict.fromkeys(
            ("received", "steps", "resets", "duplicates", "byes", "takeovers", "errors_sent", "shed",
             "muted_senders", "revoked", *BAD_PACKET_KINDS), 0)
        self.budget = SenderBudget()
        if PEER_QUEUES:  # SO_REUSEPORT would share a taken port; a plain bind refuses it
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
                probe.bind((host, port))
                port = probe.getsockname()[1]
        self._sock = reuse_port_socket()
        self._sock.bind((host, port))
        self._muted_queues = MutedQueues(self._sock.getsockname(), self.budget.mute_s)
        self._owner_sock: socket.socket | None = None
        self._public_first = 0
        self._poll = select.poll()
        self._poll.register(self._sock, select.POLLIN)
        self._rx = bytearray(MAX_DATAGRAM)
        self._reply = bytearray(FRAME_MSG.size)  # the last applied request's reply, resent for repeats
        self._owner: tuple[str, int] | None = None
        self._owner_seen = 0.0
        self._last_seq = -1
        self._last_request = b""
        self._stopping = False
        self._thread: threading.Thread | None = None
        self._next_log: dict[str, float] = {}
        self._status_mark = (time.monotonic(), 0)

    @property
    def address(self) -> tuple[str, int]:
        return self._sock.getsockname()

    @property
    def bad_packets(self) -> int:
        return sum(self.counters[k] for k in BAD_PACKET_KINDS)

    def start(self) -> UdpTwinServer:
        self._thread = threading.Thread(target=self.serve_forever, name="twin-server", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stopping = True
        host, port = self.address
        with contextlib.suppress(OSError), socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as wake:
            wake.sendto(b"", ("127.0.0.1" if host in ("0.0.0.0", "") else host, port))
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._set_owner(None)
        self._muted_queues.close()
        self._sock.close()

    def __enter__(self) -> UdpTwinServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def serve_forever(self) -> None:
        buf, view, reply, counters = self._rx, memoryview(self._rx), self._reply, self.counters
        receive, sendto = self._receive, self._sock.sendto
        unpack_pwm, pack_frame, step = PWM_MSG.unpack_from, pack_frame_into, self.twin.step
        monotonic = time.monotonic
        while not self._stopping:
            try:
                n, addr = receive()
            except (ConnectionResetError, InterruptedError):
                continue
            except OSError:
                if self._stopping:
                    break
                raise
            if self._stopping:
                break
            counters["received"] += 1
            now = monotonic()
            if now >= self._muted_queues.due:
                self._muted_queues.review(now)
            if n == _PWM_SIZE and addr == self._owner:
                magic, version, msg_type, _, seq, *pwm = unpack_pwm(buf)
                if (seq == self._last_seq + 1 and msg_type == _PWM and magic == MAGIC
                        and version == VERSION):
                    try:
                        frame = step(pwm)
                    except ValueError as exc:
                        self._bad("bad_argument", addr, str(exc), seq, ErrorCode.BAD_ARGUMENT)
                        continue
                    pack_frame(reply, seq, frame)
                    self._last_seq, self._last_request, self._owner_seen = seq, bytes(view[:n]), now
                    counters["steps"] += 1
                    sendto(reply, addr)
                    continue
            if self.budget.muted(addr, now):
                counters["shed"] += 1
                continue
            if not self.budget.spend(addr, now):
                counters["shed"] += 1
                self._mute(addr)
                self._muted_queues.hold(addr, now)
                continue
            try:
                self._handle(view[:n], addr, now)
            except Exception as exc:  # a server bug must not take the simulator down mid-session
                log.exception("twin server: request from %s failed", addr)
                self._bad("internal_error", addr, f"internal error: {exc}", 0, ErrorCode.INTERNAL)

    def _mute(self, addr: tuple[str, int]) -> None:
        self.counters["muted_senders"] += 1
        revoked = addr == self._owner
        if revoked:  # a session is not held by flooding it
            self._set_owner(None)
            self.counters["revoked"] += 1
        now = time.monotonic()
        if revoked or now >= self._next_log.get("muted", 0.0):  # many senders: one line a second
            self._next_log["muted"] = now + 1.0
            log.warning("twin server: %s:%d sent more than %.0f requests/s outside lockstep; ignored until "
                        "quiet for %.0f s%s (%d senders muted so far)", *addr, self.budget.rate_hz,
                        self.budget.mute_s, ", its session ended" if revoked else "",
                        self.counters["muted_senders"])

    def _receive(self) -> tuple[int, tuple[str, int]]:
        owner, rx, public, addr = self._owner_sock, self._rx, self._sock, self._owner
        while self._public_first > 0:  # what the owner sent before it had its own queue comes first
            self._public_first -= 1
            try:
                return public.recvfrom_into(rx, 0, _DONTWAIT)
            except BlockingIOError:
                self._public_first = 0
        while True:  # the owner's queue first, then one packet from everyone else, then again
            for _ in range(max(1, self._spin.budget)):
                if owner is not None:
                    try:
                        n = owner.recv_into(rx, 0, _DONTWAIT)
                        self._spin.hit()
                        return n, addr  # type: ignore[return-value]
                    except (BlockingIOError, ConnectionRefusedError):  # refused: ICMP from the owner's port
                        pass
                try:
                    received = public.recvfrom_into(rx, 0, _DONTWAIT)
                    if owner is None:
                        self._spin.hit()
                    return received
                except BlockingIOError:
                    pass
            self._spin.miss()
            self._poll.poll(self._muted_queues.wait_ms(time.monotonic()))
            if self._muted_queues:
                self._muted_queues.review(time.monotonic())

    def _set_owner(self, addr: tuple[str, int] | None) -> None:
        """Give the session to `addr` (None: to nobody), with a receive queue of its own."""
        if self._owner_sock is not None:
            with contextlib.suppress(ValueError, KeyError):  # closed, or never registered, as it stopped
                self._poll.unregister(self._owner_sock)
            self._owner_sock.close()
            self._owner_sock = None
        self._owner = addr
        if addr is None or not PEER_QUEUES:
            return
        try:
            sock = peer_queue(self._sock.getsockname(), addr)
        except OSError as exc:  # the shared queue still works, only without the isolation
            log.warning("twin server: no separate queue for %s:%d (%s)", *addr, exc)
            return
        self._owner_sock = sock
        self._poll.register(sock, select.POLLIN)
        self._public_first = PUBLIC_DRAIN

    def _handle(self, data: memoryview, addr: tuple[str, int], now: float) -> None:
        try:
            msg = decode(data)
        except ProtocolError as exc:
            is_reply = exc.msg_type in (MsgType.FRAME, MsgType.ERROR)
            # Refused in the requester's own version, whose ERROR layout is ours: it can read why.
            version = data[4] if exc.code == ErrorCode.BAD_VERSION else VERSION
            self._bad("unexpected_reply" if is_reply else _KIND_OF_CODE[exc.code], addr, str(exc),
                      exc.seq or 0, exc.code, answer=not is_reply, version=version)
            return
        if isinstance(msg, Frame | Error):  # never answer a reply: two servers would ping-pong forever
            self._bad("unexpected_reply", addr, f"{type(msg).__name__} sent to the server", msg.seq,
                      ErrorCode.UNKNOWN_TYPE, answer=False)
            return
        if addr != self._owner:
            self._handle_newcomer(msg, data, addr, now)
            return
        self._owner_seen = now
        if msg.seq == self._last_seq and data == self._last_request:
            self.counters["duplicates"] += 1
            self._sock.sendto(self._reply, addr)
        elif msg.seq <= self._last_seq:
            self._bad("stale", addr, f"seq {msg.seq} is not after the last applied {self._last_seq}",
                      msg.seq, ErrorCode.STALE_SEQ)
        elif isinstance(msg, Pwm) and msg.seq != self._last_seq + 1:
            self._bad("gap", addr, f"seq {msg.seq} skips ahead of {self._last_seq + 1}", msg.seq,
                      ErrorCode.SEQ_GAP)
        elif isinstance(msg, Bye):
            self.counters["byes"] += 1
            self._set_owner(None)
        else:
            self._apply(msg, bytes(data), addr, now)

    def _handle_newcomer(self, msg: Pwm | Reset | Bye, data: memoryview, addr: tuple[str, int],
                         now: float) -> None:
        if self._owner is not None and now - self._owner_seen < self.session_timeout:
            self._bad("foreign_peer", addr, f"the session belongs to {self._owner[0]}:{self._owner[1]}",
                      msg.seq, ErrorCode.BUSY, answer=not isinstance(msg, Bye))
        elif isinstance(msg, Reset):
            if self._owner is not None:
                self.counters["takeovers"] += 1
                log.info("twin server: %s:%d takes over the idle session of %s:%d", *addr, *self._owner)
            self._apply(msg, bytes(data), addr, now)
        elif isinstance(msg, Pwm):
            self._bad("no_session", addr, "no session: send RESET first", msg.seq, ErrorCode.NO_SESSION)

    def _apply(self, msg: Pwm | Reset, request: bytes, addr: tuple[str, int], now: float) -> None:
        try:
            if isinstance(msg, Pwm):
                frame = self.twin.step(msg.pwm)  # type: ignore[arg-type]
                self.counters["steps"] += 1
            else:
                if self.faults:
                    self.twin.faults = session_faults(self.twin, self.faults, msg.seed)
                frame = self.twin.reset(msg.seed, msg.state)
                self.counters["resets"] += 1
        except ValueError as exc:
            self._bad("bad_argument", addr, str(exc), msg.seq, ErrorCode.BAD_ARGUMENT)
            return
        pack_frame_into(self._reply, msg.seq, frame)
        if addr != self._owner:
            self._set_owner(addr)
        self._owner_seen, self._last_seq, self._last_request = now, msg.seq, request
        self._sock.sendto(self._reply, addr)

    def _bad(self, kind: str, addr: tuple[str, int], detail: str, seq: int, code: ErrorCode,
             answer: bool = True, version: int = VERSION) -> None:
        self.counters[kind] += 1
        if answer:
            with contextlib.suppress(OSError):
                self._sock.sendto(encode_error(seq, code, detail, version), addr)
                self.counters["errors_sent"] += 1
        now = time.monotonic()
        if now >= self._next_log.get(kind, 0.0):  # at most one line per kind per second
            self._next_log[kind] = now + 1.0
            log.warning("twin server: %s packet from %s:%d: %s (%d so far)", kind, addr[0], addr[1],
                        detail, self.counters[kind])

    def status_line(self) -> str:
        now, steps = time.monotonic(), self.counters["steps"]
        then, steps_then = self._status_mark
        self._status_mark = (now, steps)
        rate = (steps - steps_then) / (now - then) if now > then else 0.0
        c = self.counters
        return (f"steps {steps:,}  steps/s {rate:,.0f}  resets {c['resets']:,}  "
                f"repeats {c['duplicates']:,}  bad packets {self.bad_packets:,}  shed {c['shed']:,}")


def serve_command(args) -> int:
    """`fcemu twin serve`: the twin as a UDP lockstep simulator, in the foreground."""
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)
    twin = Twin(args.airframe, rig=args.rig)
    faults = args.fault or []
    as_json = getattr(args, "json", False)
    server = UdpTwinServer(twin, args.host, args.port, faults=faults)
    host, port = server.address
    done = threading.Event()
    if not args.quiet:
        def report() -> None:
            while not done.wait(STATUS_INTERVAL_S):
                print(server.status_line(), file=sys.stderr, flush=True)
        threading.Thread(target=report, name="twin-status", daemon=True).start()

    def on_sigterm(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, on_sigterm)
    try:
        # The line `spawn_server` waits for: printed only once SIGTERM stops us cleanly.
        injected = "".join(f"{f.describe()}, " for f in faults)
        print(f"fcemu twin serve: {twin.airframe.name}, {_RIG_NAMES.get(args.rig, args.rig)}, {injected}"
              f"lockstep on udp://{host}:{port}", flush=True, file=sys.stderr if as_json else sys.stdout)
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        done.set()
        server.stop()
    c = server.counters
    if as_json:
        print(json.dumps({"airframe": twin.airframe.name, "rig": args.rig, "address": f"udp://{host}:{port}",
                          "faults": [f.describe() for f in faults], "steps": c["steps"],
                          "resets": c["resets"], "bad_packets": server.bad_packets}), flush=True)
    elif not args.quiet:
        print(f"fcemu twin serve: stopped after {c['steps']:,} steps, {c['resets']:,} resets, "
              f"{server.bad_packets:,} bad packets", file=sys.stderr)
    return 0
