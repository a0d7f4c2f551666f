"""The lockstep link: the twin behind `pwm_write` / `reset`, in-process or over UDP.

Over UDP the server owns the twin and each *new* PWM request advances it exactly one
step; the reply carries the resulting frame. The client is blocking and resends the
same request (same sequence number) until a reply with that number arrives, so a lost
request or a lost reply costs a retry, never a second step: the server answers a
repeat of the last applied request from its cache. A session belongs to the address
whose RESET opened it; another address can take it over only after BYE or after
`session_timeout` of silence. Sequence numbers only grow within a session.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from typing import Protocol

import numpy as np

from firmware.sensors import SensorFrame
from sim_bridge.protocol import (
    FRAME_MSG,
    HEADER,
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
    encode_bye,
    encode_error,
    encode_reset,
    frame_from_buffer,
)
from sim_bridge.twin import Twin, TwinState

log = logging.getLogger(__name__)

STATUS_INTERVAL_S = 2.0
_RIG_NAMES = {"rig": "ball-joint rig", "free": "free body"}
# Non-blocking receive attempts (~1 µs each) before a blocking one. Waking a sleeping
# process costs tens of µs on a VM, more than a whole lockstep round trip.
SPIN_TRIES = 40
_DONTWAIT = getattr(socket, "MSG_DONTWAIT", 0)
_TIMEVAL = struct.Struct("@ll")
_FRAME, _PWM, _FRAME_SIZE, _PWM_SIZE = int(MsgType.FRAME), int(MsgType.PWM), FRAME_MSG.size, PWM_MSG.size
PwmLike = np.ndarray | tuple[float, ...] | list[float]


class Transport(Protocol):
    """What the flight controller talks to: one step per `pwm_write`."""

    def pwm_write(self, pwm: PwmLike) -> SensorFrame: ...

    def reset(self, seed: int | None = None, state: TwinState | None = None) -> SensorFrame: ...

    def close(self) -> None: ...


class LinkError(RuntimeError):
    """The link can no longer promise lockstep; `reset()` starts over."""


class LinkTimeout(LinkError, TimeoutError):
    pass


class RemoteError(LinkError):
    """The server refused a request; `code` is a protocol ErrorCode."""

    def __init__(self, code: ErrorCode | int, text: str, seq: int) -> None:
        name = code.name if isinstance(code, ErrorCode) else str(code)
        super().__init__(f"twin server refused request {seq}: {name}: {text}")
        self.code, self.text, self.seq = code, text, seq


class AdaptiveSpin:
    """How many non-blocking receive tries (~1 µs each) to make before a blocking receive.

    On an idle VM, waking a sleeping process costs tens of µs, more than a whole
    lockstep round trip, so a short spin can double the rate; on a loaded machine a
    fixed spin steals the time slice the peer needs and cut the rate several-fold in
    our measurements. So: spin while spinning catches packets, halve the budget on
    every miss, and once it is zero try the full budget again every `probe_every` receives.
    """

    def __init__(self, full: int, probe_every: int = 256) -> None:
        self.full, self.budget, self.probe_every = full, full, probe_every
        self._until_probe = probe_every

    def hit(self) -> None:
        self.budget = self.full

    def miss(self) -> None:
        if self.budget:
            self.budget >>= 1
            return
        self._until_probe -= 1
        if self._until_probe <= 0:
            self._until_probe, self.budget = self.probe_every, self.full


class InProcessLink:
    """The twin called directly: the fast path, same interface as the UDP client."""

    def __init__(self, twin: Twin | None = None) -> None:
        self.twin = twin or Twin()

    def pwm_write(self, pwm: PwmLike) -> SensorFrame:
        return self.twin.step(pwm)  # type: ignore[arg-type]

    def reset(self, seed: int | None = None, state: TwinState | None = None) -> SensorFrame:
        return self.twin.reset(seed, state)

    def close(self) -> None:
        pass

    def __enter__(self) -> InProcessLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


BAD_PACKET_KINDS = ("malformed", "bad_version", "unknown_type", "unexpected_reply", "stale", "gap",
                    "foreign_peer", "no_session", "bad_argument", "internal_error")
_KIND_OF_CODE = {ErrorCode.MALFORMED: "malformed", ErrorCode.BAD_VERSION: "bad_version",
                 ErrorCode.UNKNOWN_TYPE: "unknown_type", ErrorCode.BAD_ARGUMENT: "bad_argument"}


class UdpTwinServer:
    """One twin served over UDP; `serve_forever()` in the foreground or `start()`/`stop()` in a thread."""

    def __init__(self, twin: Twin | None = None, host: str = "127.0.0.1", port: int = 0,
                 session_timeout: float = 2.0, spin: int = SPIN_TRIES) -> None:
        self.twin = twin or Twin()
        self.session_timeout = session_timeout
        self._spin = AdaptiveSpin(spin)
        self.counters: dict[str, int] = dict.fromkeys(
            ("received", "steps", "resets", "duplicates", "byes", "takeovers", "errors_sent",
             *BAD_PACKET_KINDS), 0)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind((host, port))
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
        self._sock.close()

    def __enter__(self) -> UdpTwinServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def serve_forever(self) -> None:
        buf, view, reply, counters = self._rx, memoryview(self._rx), self._reply, self.counters
        receive, sendto = self._receive, self._sock.sendto
        unpack_pwm, pack_frame, step = PWM_MSG.unpack_from, FRAME_MSG.pack_into, self.twin.step
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
            if n == _PWM_SIZE and addr == self._owner:
                magic, version, msg_type, _, seq, *pwm = unpack_pwm(buf)
                if (seq == self._last_seq + 1 and msg_type == _PWM and magic == MAGIC
                        and version == VERSION):
                    try:
                        frame = step(pwm)
                    except ValueError as exc:
                        self._bad("bad_argument", addr, str(exc), seq, ErrorCode.BAD_ARGUMENT)
                        continue
                    pack_frame(reply, 0, MAGIC, VERSION, _FRAME, 0, seq, frame.t_us,
                               *frame.gyro.tolist(), *frame.accel.tolist(), *frame.rotor_speed.tolist())
                    self._last_seq, self._last_request, self._owner_seen = seq, bytes(view[:n]), now
                    counters["steps"] += 1
                    sendto(reply, addr)
                    continue
            try:
                self._handle(view[:n], addr, now)
            except Exception as exc:  # a server bug must not take the simulator down mid-session
                log.exception("twin server: request from %s failed", addr)
                self._bad("internal_error", addr, f"internal error: {exc}", 0, ErrorCode.INTERNAL)

    def _receive(self) -> tuple[int, tuple[str, int]]:
        recvfrom_into, buf, spin = self._sock.recvfrom_into, self._rx, self._spin.budget
        for _ in range(spin):
            try:
                received = recvfrom_into(buf, 0, _DONTWAIT)
                self._spin.hit()
                return received
            except BlockingIOError:
                pass
        self._spin.miss()
        return recvfrom_into(buf)

    def _handle(self, data: memoryview, addr: tuple[str, int], now: float) -> None:
        try:
            msg = decode(data)
        except ProtocolError as exc:
            is_reply = exc.msg_type in (MsgType.FRAME, MsgType.ERROR)
            self._bad("unexpected_reply" if is_reply else _KIND_OF_CODE[exc.code], addr, str(exc),
                      exc.seq or 0, exc.code, answer=not is_reply)
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
            self._owner = None
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
                frame = self.twin.reset(msg.seed, msg.state)
                self.counters["resets"] += 1
        except ValueError as exc:
            self._bad("bad_argument", addr, str(exc), msg.seq, ErrorCode.BAD_ARGUMENT)
            return
        FRAME_MSG.pack_into(self._reply, 0, MAGIC, VERSION, MsgType.FRAME, 0, msg.seq, frame.t_us,
                            *frame.gyro.tolist(), *frame.accel.tolist(), *frame.rotor_speed.tolist())
        self._owner, self._owner_seen, self._last_seq, self._last_request = addr, now, msg.seq, request
        self._sock.sendto(self._reply, addr)

    def _bad(self, kind: str, addr: tuple[str, int], detail: str, seq: int, code: ErrorCode,
             answer: bool = True) -> None:
        self.counters[kind] += 1
        if answer:
            with contextlib.suppress(OSError):
                self._sock.sendto(encode_error(seq, code, detail), addr)
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
                f"repeats {c['duplicates']:,}  bad packets {self.bad_packets:,}")


class UdpTwinClient:
    """The blocking lockstep client: one `pwm_write` is one step of the remote twin.

    The socket is connected, so the kernel drops datagrams from any address but the
    server's. Replies with another sequence number (late or repeated answers to earlier
    requests) are discarded and counted.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 9002, timeout: float = 0.1,
                 retries: int = 20, spin: int = SPIN_TRIES) -> None:
        self.timeout, self.retries = timeout, retries
        self._spin = AdaptiveSpin(spin)
        self.counters: dict[str, int] = dict.fromkeys(
            ("requests", "retries", "discarded", "refused", "timeouts"), 0)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.connect((host, port))
        self._set_wait(timeout)
        self._server = f"{host}:{port}"
        self._tx = bytearray(PWM_MSG.size)
        self._rx = bytearray(MAX_DATAGRAM)
        # Sequence numbers start at the clock in µs, so a restarted client on a reused
        # port is still ahead of the session its predecessor left behind.
        self._seq = time.monotonic_ns() // 1000
        self._in_session = False

    def pwm_write(self, pwm: PwmLike) -> SensorFrame:
        if not self._in_session:
            raise LinkError(f"no lockstep session with {self._server}: call reset() first")
        seq = self._seq + 1
        values = pwm.tolist() if isinstance(pwm, np.ndarray) else pwm
        try:
            PWM_MSG.pack_into(self._tx, 0, MAGIC, VERSION, MsgType.PWM, 0, seq, *values)
        except (struct.error, TypeError) as exc:
            raise ValueError(f"pwm must be 4 values in µs, got {pwm!r}") from exc
        return self._exchange(self._tx, seq)

    def reset(self, seed: int | None = None, state: TwinState | None = None) -> SensorFrame:
        seq = self._seq + 1
        frame = self._exchange(encode_reset(seq, seed, state), seq)
        self._in_session = True
        return frame

    def close(self) -> None:
        if self._sock.fileno() < 0:
            return
        if self._in_session:
            with contextlib.suppress(OSError):
                self._sock.send(encode_bye(self._seq + 1))
        self._in_session = False
        self._sock.close()

    def __enter__(self) -> UdpTwinClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _exchange(self, request: bytes | bytearray, seq: int) -> SensorFrame:
        sock, rx, counters, receive = self._sock, self._rx, self.counters, self._receive
        expected = (MAGIC, VERSION, _FRAME, 0, seq)
        counters["requests"] += 1
        for attempt in range(self.retries + 1):
            if attempt:
                counters["retries"] += 1
            sock.send(request)
            deadline = time.monotonic() + self.timeout
            shortened = False
            while True:
                try:
                    n = receive()
                except BlockingIOError:  # SO_RCVTIMEO expired
                    break
                except ConnectionRefusedError:  # nobody listens (yet): wait out this attempt
                    counters["refused"] += 1
                    time.sleep(max(0.0, deadline - time.monotonic()))
                    break
                if n == _FRAME_SIZE and HEADER.unpack_from(rx) == expected:
                    self._seq = seq
                    if shortened:
                        self._set_wait(self.timeout)
                    return frame_from_buffer(rx)
                self._check_other_reply(memoryview(rx)[:n], seq)
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._set_wait(remaining)  # junk must not extend this attempt
                shortened = True
            if shortened:
                self._set_wait(self.timeout)
        counters["timeouts"] += 1
        self._in_session = False
        self._seq = seq  # it may have been applied: the next RESET must not reuse its number
        raise LinkTimeout(f"no reply from the twin server at {self._server} to request {seq} after "
                          f"{self.retries + 1} tries of {self.timeout * 1e3:.0f} ms; call reset() to resume")

    def _receive(self) -> int:
        recv_into, rx, spin = self._sock.recv_into, self._rx, self._spin.budget
        for _ in range(spin):
            try:
                n = recv_into(rx, 0, _DONTWAIT)
                self._spin.hit()
                return n
            except BlockingIOError:
                pass
        self._spin.miss()
        return recv_into(rx)  # blocks for at most SO_RCVTIMEO

    def _set_wait(self, seconds: float) -> None:
        # SO_RCVTIMEO on a blocking socket: one syscall per receive, where settimeout() adds a poll().
        usec = max(1, round(seconds * 1e6))
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, _TIMEVAL.pack(*divmod(usec, 1_000_000)))

    def _check_other_reply(self, data: memoryview, seq: int) -> None:
        """Raise for the server's refusal of this request; count and drop anything else."""
        try:
            msg = decode(data)
        except ProtocolError as exc:
            self.counters["discarded"] += 1
            log.debug("twin client: dropped a bad reply: %s", exc)
            return
        if msg.seq != seq or not isinstance(msg, Error):
            self.counters["discarded"] += 1
            return
        self._set_wait(self.timeout)
        if msg.code == ErrorCode.BAD_ARGUMENT:
            raise ValueError(f"the twin server refused the values: {msg.text}")
        if msg.code != ErrorCode.BUSY:
            self._in_session = False  # STALE/GAP/NO_SESSION: lockstep is lost
        raise RemoteError(msg.code, msg.text, seq)


def serve_command(args) -> int:
    """`fcemu twin serve`: the twin as a UDP lockstep simulator, in the foreground."""
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)
    twin = Twin(args.airframe, rig=args.rig)
    server = UdpTwinServer(twin, args.host, args.port)
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
        print(f"fcemu twin serve: {twin.airframe.name}, {_RIG_NAMES.get(args.rig, args.rig)}, lockstep on "
              f"udp://{host}:{port}", flush=True)
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        done.set()
        server.stop()
    if not args.quiet:
        c = server.counters
        print(f"fcemu twin serve: stopped after {c['steps']:,} steps, {c['resets']:,} resets, "
              f"{server.bad_packets:,} bad packets", file=sys.stderr)
    return 0


def spawn_server(rig: str = "rig", airframe: str = "iris", host: str = "127.0.0.1",
                 startup_timeout: float = 30.0) -> tuple[subprocess.Popen, tuple[str, int]]:
    """Start `fcemu twin serve` on a free port in another process; returns it and its address."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "fcemu", "twin", "serve", "--host", host, "--port", "0", "--rig", rig,
         "--airframe", airframe, "--quiet"],
        stdout=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)
    timer = threading.Timer(startup_timeout, proc.kill)  # a server that never prints must not hang us
    timer.start()
    try:
        line = proc.stdout.readline() if proc.stdout else ""
    finally:
        timer.cancel()
    if "udp://" not in line:
        proc.kill()
        proc.wait()
        raise LinkError(f"fcemu twin serve did not start (exit code {proc.returncode}): {line!r}")
    address = line.rsplit("udp://", 1)[1].strip()
    bound_host, port = address.rsplit(":", 1)
    return proc, (bound_host, int(port))
