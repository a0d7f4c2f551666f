"""What the flight process and the MAVLink process say to each other.

Telemetry goes through a shared-memory latest-value slot (`SnapshotSlot`, a seqlock over a
memfd): the loop writes a fixed struct without a system call, the MAVLink process reads the
newest one when it gets round to it, and neither ever waits for the other. Events go over an
AF_UNIX SOCK_SEQPACKET socket pair, non-blocking on the flight side (a stalled MAVLink
process costs a dropped message, never a blocked tick); they are small pickled tuples.

MAVLink → flight: ("sp", (p, q, r), thrust), ("sticks", roll, pitch_up, yaw, throttle),
("arm", req, arm, force), ("mode", req, main, sub), ("param", name, value), ("stats", dict).
Flight → MAVLink: snapshot, ("ack", req, result, text), ("text", severity, text).
"""

from __future__ import annotations

import mmap
import os
import pickle
import struct
from typing import NamedTuple

SNAPSHOT_TAG = b"T"
_FMT = struct.Struct("<qBIBBBB4f3f3f4f4f3ff3f3fBf3IQQ")


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

    def pack(self) -> bytes:
        return SNAPSHOT_TAG + _FMT.pack(self.t_us, self.armed, self.custom_mode, self.landed_state,
                                        self.failsafe, self.controller, self.armable, *self.q, *self.gyro,
                                        *self.accel, *self.pwm, *self.rotor_speed, *self.setpoint,
                                        self.throttle, *self.position, *self.velocity, self.has_position,
                                        self.vz_estimate, self.faults, self.rejected, self.misses,
                                        self.ticks, self.compute_us_max)

    @classmethod
    def unpack(cls, data: bytes) -> Snapshot:
        v = _FMT.unpack_from(data, 1)
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
                return Snapshot.unpack(SNAPSHOT_TAG + data)
        return None

    def close(self) -> None:
        self._mem.close()


def pack_snapshot(values: tuple) -> bytes:
    """The tick's fast path: the flat field tuple in `_FMT` order, no NamedTuple built."""
    return SNAPSHOT_TAG + _FMT.pack(*values)


def encode(message: tuple) -> bytes:
    return pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)


def decode(data: bytes) -> tuple | Snapshot | None:
    """A received datagram, or None if it is not one we understand."""
    if not data:
        return None
    if data[:1] == SNAPSHOT_TAG:
        return Snapshot.unpack(data) if len(data) == 1 + _FMT.size else None
    try:
        message = pickle.loads(data)
    except Exception:
        return None
    return message if isinstance(message, tuple) and message else None
