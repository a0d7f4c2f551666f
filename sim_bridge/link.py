"""The lockstep link: the twin behind `pwm_write` / `reset`, in-process or over UDP.

Over UDP the server (`sim_bridge.twin_server`) owns the twin and each *new* PWM request
advances it exactly one step; the reply carries the resulting frame. The client is blocking and resends the
same request (same sequence number) until a reply with that number arrives, so a lost
request or a lost reply costs a retry, never a second step: the server answers a
repeat of the last applied request from its cache. A session belongs to the address
whose RESET opened it; another address can take it over only after BYE or after
`session_timeout` of silence. Sequence numbers only grow within a session.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Protocol, TypeVar

import numpy as np

from fcemu.firmware.sensors import SensorFrame
from fcemu.sim_bridge.airframe import DEFAULT_AIRFRAME
from fcemu.sim_bridge.protocol import (
    FRAME_MSG,
    HEADER,
    MAGIC,
    MAX_DATAGRAM,
    PWM_MSG,
    VERSION,
    Error,
    ErrorCode,
    MsgType,
    ProtocolError,
    decode,
    encode_bye,
    encode_reset,
    frame_from_buffer,
    pack_pwm_into,
)
from fcemu.sim_bridge.twin import Twin, TwinState

log = logging.getLogger(__name__)
R = TypeVar("R")

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

    def receive(self, recv_into: Callable[..., R], buffer: bytearray) -> R:
        """`recv_into(buffer)` (or `recvfrom_into`): spin non-blocking within the budget, then block."""
        for _ in range(self.budget):
            try:
                received = recv_into(buffer, 0, _DONTWAIT)
                self.hit()
                return received
            except BlockingIOError:
                pass
        self.miss()
        return recv_into(buffer)  # blocks for at most the socket's timeout


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
        pack_pwm_into(self._tx, seq, pwm)
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
                    try:
                        return frame_from_buffer(rx)
                    except ProtocolError as exc:  # applied, yet unreadable: lockstep is lost
                        self._in_session = False
                        raise LinkError(f"the twin server at {self._server} answered request {seq} "
                                        f"with a frame this client cannot read: {exc}") from None
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
        return self._spin.receive(self._sock.recv_into, self._rx)  # blocks for at most SO_RCVTIMEO

    def _set_wait(self, seconds: float) -> None:
        # SO_RCVTIMEO on a blocking socket: one syscall per receive, where settimeout() adds a poll().
        usec = max(1, round(seconds * 1e6))
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, _TIMEVAL.pack(*divmod(usec, 1_000_000)))

    def _check_other_reply(self, data: memoryview, seq: int) -> None:
        """Raise for the server's refusal of this request; count and drop anything else."""
        try:
            msg = decode(data)
        except ProtocolError as exc:
            if exc.code == ErrorCode.BAD_VERSION and exc.msg_type == MsgType.ERROR and exc.seq == seq:
                self._in_session = False  # a server of another version refused this request
                raise LinkError(f"the twin server at {self._server} speaks protocol version {data[4]}, "
                                f"this client {VERSION}: run the same fcemu version on both ends") from None
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


def spawn_server(rig: str = "rig", airframe: str = DEFAULT_AIRFRAME, host: str = "127.0.0.1",
                 startup_timeout: float = 30.0,
                 faults: Sequence[str] = ()) -> tuple[subprocess.Popen, tuple[str, int]]:
    """Start `fcemu twin serve` on a free port in another process, with `faults` (--fault SPECs);
    returns it and its address."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "fcemu", "twin", "serve", "--host", host, "--port", "0", "--rig", rig,
         "--airframe", airframe, "--quiet", *(f"--fault={spec}" for spec in faults)],
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
