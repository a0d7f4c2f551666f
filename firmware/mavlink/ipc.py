"""What the flight process and the MAVLink process say to each other.

Telemetry goes through a shared-memory latest-value slot (`SnapshotSlot`, a seqlock over a
memfd): the loop writes a fixed struct without a system call, the MAVLink process reads the
newest one when it gets round to it, and neither ever waits for the other. Events go over an
AF_UNIX SOCK_SEQPACKET socket pair, non-blocking on the flight side (a stalled MAVLink
process costs a dropped message, never a blocked tick), one typed message per datagram
(`encode` / `decode`):

  MAVLink → flight: Setpoint, Sticks, ArmRequest, ModeRequest, ParamSet, LinkStats, Ready,
  FailureRequest.
  Flight → MAVLink: Ack (to an ArmRequest or ModeRequest, by `req`), Text; and the snapshot.
"""

from __future__ import annotations

import mmap
import os
import pickle
import struct
from typing import NamedTuple

_FMT = struct.Struct("<qBIBBBB4f3f3f4f4f3ff3f3fBf3IQQ")


class Setpoint(NamedTuple):
    rates: tuple[float, float, float]  # FRD rad/s
    thrust: float  # 0..1


class Sticks(NamedTuple):
    roll: float  # -1..1
    pitch_up: float
    yaw: float
    throttle: float  # 0..1


class ArmRequest(NamedTuple):
    arm: bool
    force: bool
    req: int = 0  # matches the Ack; set by the MAVLink process when it sends the request


class ModeRequest(NamedTuple):
    main: int  # PX4 custom main mode
    sub: int
    req: int = 0


class ParamSet(NamedTuple):
    name: str
    value: float


class LinkStats(NamedTuple):
    counters: dict[str, int]


class Ready(NamedTuple):
    ports: dict[str, int]  # the MAVLink process's local UDP port per peer


class FailureRequest(NamedTuple):
    """MAV_CMD_INJECT_FAILURE for the twin: MAVLink FAILURE_UNIT, FAILURE_TYPE, instance (0: all)."""

    unit: int
    failure_type: int
    instance: int
    req: int = 0


class Ack(NamedTuple):
    req: int
    result: int  # MAV_RESULT
    text: str


class Text(NamedTuple):
    severity: int  # MAV_SEVERITY
    text: str


Message = (Setpoint | Sticks | ArmRequest | ModeRequest | ParamSet | LinkStats | Ready | Ack | Text
           | FailureRequest)
MESSAGES: tuple[type, ...] = (Setpoint, Sticks, ArmRequest, ModeRequest, ParamSet, LinkStats, Ready, Ack,
                              Text, FailureRequest)
_TAGS = {cls: tag for tag, cls in enumerate(MESSAGES)}
_ARITY = tuple(len(cls._fields) for cls in MESSAGES)
_build = tuple.__new__  # NamedTuple construction from a tuple of fields, without re-checking


def encode(message: Message) -> bytes:
    """(tag, fields), pickled: plain values only cross the socket, never a class reference."""
    return pickle.dumps((_TAGS[type(message)], tuple(message)), protocol=pickle.HIGHEST_PROTOCOL)


def decode(data: bytes) -> Message | None:
    """A received datagram as its message, or None if it is not one we understand."""
    try:
        tag, fields = pickle.loads(data)
    except Exception:
        return None
    if type(tag) is int and 0 <= tag < len(MESSAGES) and type(fields) is tuple and len(fields) == _ARITY[tag]:
        return _build(MESSAGES[tag], fields)
    return None


class Snapshot(NamedTuple):
    t_us: int  # the sensor frame's time (the twin's clock: skipped ticks do not advance it)
    armed: int
    custom_mode: int  # PX4 encoding
    landed_state: int  # MAV_LANDED_STATE
    failsafe: int
    controller: int  # index into params.CONTROLLERS
    armable: int
    q: tuple  # estimator attitude (w, x, y, z), FRD → NED
    gyro: tuple  # FRD rad/s
    accel: tuple  # FRD m/s²
    pwm: tuple
    rotor_speed: tuple
    setpoint: tuple  # FRD rad/s
    throttle: float
    position: tuple  # NED m, ground truth (free rig); zeros when has_position is 0
    velocity: tuple
    has_position: int
    vz_estimate: float
    faults: int  # controller faults replaced by the fallback
    rejected: int  # inputs the vehicle refused
    misses: int  # loop deadline misses
    ticks: int
    compute_us_max: int  # worst tick compute since the previous snapshot

    @classmethod
    def unpack(cls, data: bytes) -> Snapshot:
        v = _FMT.unpack(data)
        return cls(*v[:7], v[7:11], v[11:14], v[14:17], v[17:21], v[21:25], v[25:28], v[28], v[29:32],
                   v[32:35], *v[35:])


class SnapshotSlot:
    """One snapshot in shared memory behind a sequence counter (odd while being written)."""

    _SEQ = struct.Struct("<Q")

    def __init__(self, fd: int | None = None) -> None:
        if fd is None:
            fd = os.memfd_create("fcemu-telemetry", 0)
            os.ftruncate(fd, 8 + _FMT.size)
        self.fd = fd
        self._mem = mmap.mmap(fd, 8 + _FMT.size)
        self._seq = self._SEQ.unpack_from(self._mem, 0)[0]
        self._read_seq = -1

    def write(self, values: tuple) -> None:
        """`values`: the Snapshot's fields flattened in order (the tick's path builds no NamedTuple)."""
        mem, seq = self._mem, self._seq
        self._SEQ.pack_into(mem, 0, seq + 1)
        _FMT.pack_into(mem, 8, *values)
        self._seq = seq + 2
        self._SEQ.pack_into(mem, 0, seq + 2)

    def read(self) -> Snapshot | None:
        """The newest snapshot if there is one not read before, else None."""
        mem = self._mem
        for _ in range(100):
            before = self._SEQ.unpack_from(mem, 0)[0]
            if before == self._read_seq or before == 0:
                return None
            if before & 1:
                continue
            data = mem[8:]
            if self._SEQ.unpack_from(mem, 0)[0] == before:
                self._read_seq = before
                return Snapshot.unpack(data)
        return None

    def close(self) -> None:
        self._mem.close()
