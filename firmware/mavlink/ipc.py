"""What the flight process and the MAVLink process say to each other.

Telemetry goes through a shared-memory latest-value slot (`SnapshotSlot`, a seqlock over a
memfd): the loop writes a fixed struct without a system call, the MAVLink process reads the
newest one when it gets round to it, and neither ever waits for the other. The struct is
`Snapshot`'s fields in order, each packed by the struct code declared beside it. Events go
over an AF_UNIX SOCK_SEQPACKET socket pair, non-blocking on the flight side (a stalled
MAVLink process costs a dropped message, never a blocked tick), one typed message per
datagram (`encode` / `decode`): JSON `[name, {field: value}]`, each field checked against
the message's declared type on both sides, so a frame that is not one of them is refused
(`FrameError`), never acted on:

  MAVLink → flight: Setpoint, Sticks, ArmRequest, ModeRequest, ParamSet, LinkStats, Ready,
  FailureRequest.
  Flight → MAVLink: Ack (to an ArmRequest or ModeRequest, by `req`), Text; and the snapshot.
"""

from __future__ import annotations

import json
import mmap
import os
import struct
from collections.abc import Callable
from itertools import accumulate
from typing import Annotated, Any, NamedTuple, get_args, get_origin, get_type_hints


class FrameError(ValueError):
    """A datagram that is not a valid message, or a message whose fields do not fit its declaration."""


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
Check = Callable[[Any], Any]
_SCALARS: dict[Any, tuple[frozenset[type], str]] = {
    float: (frozenset((float, int)), "a number"), int: (frozenset((int,)), "an int"),
    bool: (frozenset((bool,)), "a bool"), str: (frozenset((str,)), "a string")}


def _checker(hint: Any, where: str) -> Check:
    """A function that returns a JSON value as the declared type `hint` holds it, or raises FrameError."""
    origin, args = get_origin(hint), get_args(hint)
    if hint in _SCALARS:
        types, what = _SCALARS[hint]

        def check(v: Any) -> Any:
            if type(v) not in types:
                raise FrameError(f"{where}: expected {what}, got {v!r:.80}")
            return v
        return check
    if origin is tuple and len(set(args)) == 1 and args[0] in _SCALARS:
        types, what = _SCALARS[args[0]]
        size = len(args)

        def check_tuple(v: Any) -> tuple:
            if type(v) not in (list, tuple) or len(v) != size or not all(type(x) in types for x in v):
                raise FrameError(f"{where}: expected {size} values, each {what}, got {v!r:.80}")
            return tuple(v)
        return check_tuple
    if origin is dict and args[0] is str and args[1] in _SCALARS:
        types, what = _SCALARS[args[1]]

        def check_dict(v: Any) -> dict:
            if type(v) is not dict or not all(type(k) is str and type(x) in types for k, x in v.items()):
                raise FrameError(f"{where}: expected names each with {what}, got {v!r:.80}")
            return v
        return check_dict
    raise TypeError(f"{where}: {hint} cannot cross the socket")


# Each message's fields by name in order, each with the check its declared type makes.
_FIELDS: dict[str, tuple[type, dict[str, Check]]] = {
    cls.__name__: (cls, {name: _checker(hint, f"{cls.__name__}.{name}")
                         for name, hint in get_type_hints(cls).items()})
    for cls in MESSAGES}


def _checked(name: str, values: dict[str, Any]) -> list[Any]:
    """The named fields' values in declared order, each checked against its declared type."""
    checks = _FIELDS[name][1]
    if values.keys() != checks.keys():
        missing, extra = sorted(checks.keys() - values.keys()), sorted(values.keys() - checks.keys())
        raise FrameError(f"{name}: fields missing {missing}, unknown {extra}")
    return [check(values[key]) for key, check in checks.items()]


def encode(message: Message) -> bytes:
    """The message as JSON `[name, {field: value}]`; FrameError if a field is not of its declared type."""
    name = type(message).__name__
    if type(message) not in MESSAGES:
        raise FrameError(f"{name} is not a message")
    fields = message._asdict()
    _checked(name, fields)
    return json.dumps([name, fields], separators=(",", ":")).encode()


def decode(data: bytes) -> Message:
    """A received datagram as its message; FrameError, naming what is wrong, if it is not one."""
    try:
        frame = json.loads(data)
    except (ValueError, RecursionError) as exc:
        raise FrameError(f"not a message frame ({len(data)} bytes): {exc}") from None
    if type(frame) is not list or len(frame) != 2 or type(frame[1]) is not dict:
        raise FrameError(f"not a message frame: {frame!r:.80}")
    name, values = frame
    if type(name) is not str or name not in _FIELDS:
        raise FrameError(f"unknown message {name!r:.40}")
    return tuple.__new__(_FIELDS[name][0], _checked(name, values))


def _layout(cls: type) -> tuple[tuple[str, str, int], ...]:
    """Per field of a packed record in order: its name, its struct code and how many values it holds."""
    hints = get_type_hints(cls, include_extras=True)
    out = []
    for name in cls._fields:
        code = hints[name].__metadata__[0]
        count = int(code[:-1] or 1)
        if (count > 1) != (get_origin(get_args(hints[name])[0]) is tuple):
            raise TypeError(f"{cls.__name__}.{name}: {count} values must be declared as a tuple")
        out.append((name, code, count))
    return tuple(out)


class Snapshot(NamedTuple):
    """The vehicle's state for telemetry; each field's struct code lays it out in `SnapshotSlot`."""

    t_us: Annotated[int, "q"]  # the sensor frame's time (the twin's clock: skipped ticks do not advance it)
    armed: Annotated[int, "B"]
    custom_mode: Annotated[int, "I"]  # PX4 encoding
    landed_state: Annotated[int, "B"]  # MAV_LANDED_STATE
    failsafe: Annotated[int, "B"]
    controller: Annotated[int, "B"]  # index into params.CONTROLLERS
    armable: Annotated[int, "B"]
    q: Annotated[tuple[float, ...], "4f"]  # estimator attitude (w, x, y, z), FRD → NED
    gyro: Annotated[tuple[float, ...], "3f"]  # FRD rad/s
    accel: Annotated[tuple[float, ...], "3f"]  # FRD m/s²
    pwm: Annotated[tuple[float, ...], "4f"]
    rotor_speed: Annotated[tuple[float, ...], "4f"]
    setpoint: Annotated[tuple[float, ...], "3f"]  # FRD rad/s
    throttle: Annotated[float, "f"]
    position: Annotated[tuple[float, ...], "3f"]  # NED m, ground truth (free rig); zeros without it
    velocity: Annotated[tuple[float, ...], "3f"]
    has_position: Annotated[int, "B"]
    vz_estimate: Annotated[float, "f"]
    faults: Annotated[int, "I"]  # controller faults replaced by the fallback
    rejected: Annotated[int, "I"]  # inputs the vehicle refused
    misses: Annotated[int, "I"]  # loop deadline misses
    ticks: Annotated[int, "Q"]
    compute_us_max: Annotated[int, "Q"]  # worst tick compute since the previous snapshot

    def pack(self) -> tuple:
        """The fields' values flattened in the slot's order."""
        flat: list = []
        for (name, _, count), value in zip(SNAPSHOT_LAYOUT, self, strict=True):
            if count == 1:
                flat.append(value)
            elif len(value) == count:
                flat.extend(value)
            else:
                raise ValueError(f"Snapshot.{name}: {count} values, got {len(value)}")
        return tuple(flat)

    @classmethod
    def unpack(cls, data: bytes) -> Snapshot:
        values = _FMT.unpack(data)
        return tuple.__new__(cls, [values[i] if count == 1 else values[i:i + count] for i, count in _SPANS])


SNAPSHOT_LAYOUT = _layout(Snapshot)
_FMT = struct.Struct("<" + "".join(code for _, code, _ in SNAPSHOT_LAYOUT))
_COUNTS = [count for *_, count in SNAPSHOT_LAYOUT]
_SPANS = tuple(zip(accumulate(_COUNTS, initial=0), _COUNTS, strict=False))  # (first value, count) per field


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

    def write(self, snapshot: Snapshot) -> None:
        mem, seq = self._mem, self._seq
        values = snapshot.pack()
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
