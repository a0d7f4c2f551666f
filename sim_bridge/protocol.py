"""The lockstep link's wire format: small, versioned, struct-packed, little-endian.

Every datagram starts with the same 16-byte header::

    magic "FCTW" | version u8 | type u8 | reserved u16 (0) | seq u64

Requests (client -> server) are PWM, RESET and BYE; replies (server -> client) are
FRAME and ERROR. A reply carries the sequence number of the request it answers. Each
message type has a fixed length except ERROR (a short UTF-8 text at the end). All
floats are float64, so a frame that crossed the link is bit-identical to the one the
twin returned in-process.

A FRAME carries each input's sample time (version 2): after the frame's time and its ten
floats, a flags byte (bit 0: the gyro's time follows, bit 1: each motor's) and five int64
times, zero where their flag is clear. A flag, not a sentinel time, says "no time" (the
SensorFrame's None: sampled at the frame's time), so every int64 stays a valid time.

ERROR has the same layout in every version, so a request of another version is refused with
BAD_VERSION in the requester's own version: each end can read why the other refused it.

Every path packs and unpacks through the functions here: `pack_pwm_into` and
`pack_frame_into` write a message into a reused buffer (the link's hot paths),
`encode_*` return new bytes, `frame_from_buffer` and `decode` read.
"""

from __future__ import annotations

import math
import struct
from enum import IntEnum
from typing import NamedTuple

import numpy as np

from fcemu.firmware.sensors import SensorFrame
from fcemu.sim_bridge.twin import TwinState

MAGIC = b"FCTW"
VERSION = 2


class MsgType(IntEnum):
    PWM = 0x01
    RESET = 0x02
    BYE = 0x03
    FRAME = 0x81
    ERROR = 0x82


REQUEST_TYPES = frozenset({MsgType.PWM, MsgType.RESET, MsgType.BYE})


class ErrorCode(IntEnum):
    MALFORMED = 1  # truncated, wrong length, not our magic, garbage
    BAD_VERSION = 2
    UNKNOWN_TYPE = 3
    STALE_SEQ = 4  # older than the last applied request, or its seq reused with other content
    SEQ_GAP = 5  # skips ahead: a request in between was never applied
    BUSY = 6  # another client owns the session
    NO_SESSION = 7  # PWM before any RESET
    BAD_ARGUMENT = 8  # the twin refused the values (non-finite PWM, bad initial state)
    INTERNAL = 9  # the server failed on this request; reset() before going on


HEADER = struct.Struct("<4sBBHQ")
PWM_MSG = struct.Struct("<4sBBHQ4d")
BYE_MSG = HEADER
FRAME_MSG = struct.Struct("<4sBBHQq10dB7xq4q")
# flags: bit 0 a seed follows, bit 1 an initial state follows, bit 2 the state has a position
RESET_MSG = struct.Struct("<4sBBHQB7xq17d")
ERROR_HEAD = struct.Struct("<4sBBHQHB")
_T_US = struct.Struct("<q")
MAX_ERROR_TEXT = 200
MAX_DATAGRAM = 512  # larger than any valid message, so an oversized one shows up as wrong length

_FIXED_SIZE = {
    MsgType.PWM: PWM_MSG.size,
    MsgType.RESET: RESET_MSG.size,
    MsgType.BYE: BYE_MSG.size,
    MsgType.FRAME: FRAME_MSG.size,
}
_HAS_SEED, _HAS_STATE, _HAS_POSITION = 1, 2, 4
_HAS_GYRO_T, _HAS_ROTOR_T = 1, 2  # FRAME's flags
_FLAGS_AT = HEADER.size + 88  # after t_us and the ten floats
_GYRO_T_AT, _ROTOR_T_AT = _FLAGS_AT + 8, _FLAGS_AT + 16
_NO_ROTOR_T = (0, 0, 0, 0)
_PWM_TYPE, _FRAME_TYPE = int(MsgType.PWM), int(MsgType.FRAME)  # plain ints pack faster than enums
_INT64 = (-(2**63), 2**63 - 1)


class ProtocolError(ValueError):
    """A datagram that is not a valid message; `code` says why, `seq` is set when the header parsed."""

    def __init__(self, code: ErrorCode, message: str, seq: int | None = None,
                 msg_type: int | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.seq = seq
        self.msg_type = msg_type


class Pwm(NamedTuple):
    seq: int
    pwm: tuple[float, float, float, float]


class Reset(NamedTuple):
    seq: int
    seed: int | None
    state: TwinState | None


class Bye(NamedTuple):
    seq: int


class Frame(NamedTuple):
    seq: int
    frame: SensorFrame


class Error(NamedTuple):
    seq: int
    code: ErrorCode | int
    text: str


Message = Pwm | Reset | Bye | Frame | Error


def pack_pwm_into(buffer: bytearray, seq: int, pwm: np.ndarray | tuple[float, ...] | list[float]) -> None:
    """A PWM request in `buffer`; ValueError unless `pwm` is 4 numbers."""
    values = pwm.tolist() if isinstance(pwm, np.ndarray) else pwm
    try:
        PWM_MSG.pack_into(buffer, 0, MAGIC, VERSION, _PWM_TYPE, 0, seq, *values)
    except (struct.error, TypeError) as exc:
        raise ValueError(f"pwm must be 4 values in µs, got {pwm!r}") from exc


def encode_pwm(seq: int, pwm: np.ndarray | tuple[float, ...] | list[float]) -> bytes:
    buffer = bytearray(PWM_MSG.size)
    pack_pwm_into(buffer, seq, pwm)
    return bytes(buffer)


def encode_bye(seq: int) -> bytes:
    return BYE_MSG.pack(MAGIC, VERSION, MsgType.BYE, 0, seq)


def encode_reset(seq: int, seed: int | None = None, state: TwinState | None = None) -> bytes:
    flags = 0
    if seed is not None:
        seed = int(seed)
        if not _INT64[0] <= seed <= _INT64[1]:
            raise ValueError(f"seed {seed} does not fit in 64 bits")
        flags |= _HAS_SEED
    values = [0.0] * 17
    if state is not None:
        flags |= _HAS_STATE
        position = state.position
        if position is not None:
            flags |= _HAS_POSITION
        values = [float(v) for v in (*state.attitude, *state.body_rates, *state.rotor_speed,
                                      *(position or (0.0, 0.0, 0.0)), *state.velocity)]
        if len(values) != 17:
            raise ValueError(f"initial state has the wrong number of values: {state!r}")
    return RESET_MSG.pack(MAGIC, VERSION, MsgType.RESET, 0, seq, flags, seed or 0, *values)


def pack_frame_into(buffer: bytearray, seq: int, frame: SensorFrame) -> None:
    """The FRAME reply to request `seq` in `buffer` (at least FRAME_MSG.size bytes)."""
    gyro_t, rotor_t = frame.gyro_t_us, frame.rotor_speed_t_us
    flags = (gyro_t is not None) | (rotor_t is not None) << 1
    FRAME_MSG.pack_into(buffer, 0, MAGIC, VERSION, _FRAME_TYPE, 0, seq, frame.t_us, *frame.gyro.tolist(),
                        *frame.accel.tolist(), *frame.rotor_speed.tolist(), flags, gyro_t or 0,
                        *(_NO_ROTOR_T if rotor_t is None else rotor_t.tolist()))


def encode_frame(seq: int, frame: SensorFrame) -> bytes:
    buffer = bytearray(FRAME_MSG.size)
    pack_frame_into(buffer, seq, frame)
    return bytes(buffer)


def encode_error(seq: int, code: ErrorCode | int, text: str, version: int = VERSION) -> bytes:
    """An ERROR; `version` other than ours only to refuse a request of that version (module docstring)."""
    raw = text.encode("utf-8", "replace")[:MAX_ERROR_TEXT]
    return ERROR_HEAD.pack(MAGIC, version, MsgType.ERROR, 0, seq, int(code), len(raw)) + raw


def frame_from_buffer(buffer: bytes | bytearray | memoryview) -> SensorFrame:
    """The SensorFrame in a FRAME message already checked to be one (header not re-validated);
    ProtocolError for flags this version does not know."""
    t_us = _T_US.unpack_from(buffer, HEADER.size)[0]
    values = np.frombuffer(buffer, "<f8", 10, HEADER.size + 8).copy()
    flags = buffer[_FLAGS_AT]
    if not flags:
        return SensorFrame(t_us, values[0:3], values[3:6], values[6:10])
    if flags & ~(_HAS_GYRO_T | _HAS_ROTOR_T):
        raise ProtocolError(ErrorCode.MALFORMED, f"FRAME with unknown flags 0x{flags:02x}",
                            HEADER.unpack_from(buffer)[4], MsgType.FRAME)
    gyro_t = _T_US.unpack_from(buffer, _GYRO_T_AT)[0] if flags & _HAS_GYRO_T else None
    rotor_t = np.frombuffer(buffer, "<i8", 4, _ROTOR_T_AT).astype(np.int64) if flags & _HAS_ROTOR_T else None
    return SensorFrame(t_us, values[0:3], values[3:6], values[6:10], gyro_t, rotor_t)


def peek_header(data: bytes | bytearray | memoryview) -> tuple[int, int]:
    """(type, seq) of a datagram whose header is valid; ProtocolError otherwise."""
    if len(data) < HEADER.size:
        raise ProtocolError(ErrorCode.MALFORMED, f"truncated: {len(data)} bytes, a header is {HEADER.size}")
    magic, version, msg_type, _, seq = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise ProtocolError(ErrorCode.MALFORMED, f"not an fcemu twin packet (magic {bytes(magic)!r})")
    if version != VERSION:
        raise ProtocolError(ErrorCode.BAD_VERSION,
                            f"protocol version {version}, this end speaks {VERSION}", seq, msg_type)
    if msg_type not in _FIXED_SIZE and msg_type != MsgType.ERROR:
        raise ProtocolError(ErrorCode.UNKNOWN_TYPE, f"unknown message type 0x{msg_type:02x}", seq, msg_type)
    return msg_type, seq


def decode(data: bytes | bytearray | memoryview) -> Message:
    """Parse one datagram; raises ProtocolError for anything but a complete, valid message."""
    msg_type, seq = peek_header(data)
    expected = _FIXED_SIZE.get(MsgType(msg_type))
    if expected is not None and len(data) != expected:
        raise ProtocolError(ErrorCode.MALFORMED, f"{MsgType(msg_type).name} of {len(data)} bytes, "
                            f"expected {expected}", seq, msg_type)
    if msg_type == MsgType.PWM:
        return Pwm(seq, PWM_MSG.unpack_from(data)[5:])
    if msg_type == MsgType.FRAME:
        return Frame(seq, frame_from_buffer(data))
    if msg_type == MsgType.BYE:
        return Bye(seq)
    if msg_type == MsgType.RESET:
        return _decode_reset(data, seq)
    return _decode_error(data, seq)


def _decode_reset(data: bytes | bytearray | memoryview, seq: int) -> Reset:
    fields = RESET_MSG.unpack_from(data)
    flags, seed, v = fields[5], fields[6], fields[7:]
    if flags & ~(_HAS_SEED | _HAS_STATE | _HAS_POSITION):
        raise ProtocolError(ErrorCode.MALFORMED, f"RESET with unknown flags 0x{flags:02x}", seq,
                            MsgType.RESET)
    state = None
    if flags & _HAS_STATE:
        if not all(math.isfinite(x) for x in v):
            raise ProtocolError(ErrorCode.BAD_ARGUMENT, "RESET initial state is not finite", seq,
                                MsgType.RESET)
        state = TwinState(attitude=v[0:4], body_rates=v[4:7], rotor_speed=v[7:11],
                          position=v[11:14] if flags & _HAS_POSITION else None, velocity=v[14:17])
    return Reset(seq, seed if flags & _HAS_SEED else None, state)


def _decode_error(data: bytes | bytearray | memoryview, seq: int) -> Error:
    if len(data) < ERROR_HEAD.size:
        raise ProtocolError(ErrorCode.MALFORMED, f"ERROR of {len(data)} bytes is truncated", seq,
                            MsgType.ERROR)
    code, length = ERROR_HEAD.unpack_from(data)[5:]
    if len(data) != ERROR_HEAD.size + length:
        raise ProtocolError(ErrorCode.MALFORMED, f"ERROR of {len(data)} bytes, its text says "
                            f"{ERROR_HEAD.size + length}", seq, MsgType.ERROR)
    text = bytes(data[ERROR_HEAD.size:]).decode("utf-8", "replace")
    try:
        code = ErrorCode(code)
    except ValueError:
        pass  # a newer server's code: keep the number
    return Error(seq, code, text)
