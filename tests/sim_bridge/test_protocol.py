"""The lockstep wire format: round trips, a pinned layout, and every way a datagram can be wrong."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from fcemu.firmware.sensors import SensorFrame
from fcemu.sim_bridge.protocol import (
    HEADER,
    MAGIC,
    MAX_ERROR_TEXT,
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
    encode_frame,
    encode_pwm,
    encode_reset,
    peek_header,
)
from fcemu.sim_bridge.twin import TwinState

pytestmark = pytest.mark.timeout(30)


def awkward_frame() -> SensorFrame:
    """Values a lossy encoding would change: -0.0, subnormals, huge, many significant digits."""
    return SensorFrame(
        123_456_789_000,
        np.array([-0.0, 5e-324, 1.0 / 3.0]),
        np.array([-9.81, 1e308, -math.pi]),
        np.array([0.0, 819.7059278907151, 1100.0, np.nextafter(1.0, 2.0)]),
    )


def test_pwm_round_trip() -> None:
    pwm = (1000.0, 1745.1872071733774, 2000.0, 1000.0000000000001)
    assert decode(encode_pwm(2**63 + 5, np.array(pwm))) == Pwm(2**63 + 5, pwm)


def test_frame_round_trip_is_bit_identical() -> None:
    frame = awkward_frame()
    msg = decode(encode_frame(42, frame))
    assert isinstance(msg, Frame) and msg.seq == 42
    assert msg.frame.t_us == frame.t_us
    for got, sent in zip(msg.frame[1:4], frame[1:4], strict=True):
        assert got.dtype == np.float64
        assert got.tobytes() == sent.tobytes()


AGES = {
    "none": (None, None),
    "gyro only": (123_456_788_000, None),
    "rotors only": (None, np.array([0, -1, 2**63 - 1, -(2**63)], dtype=np.int64)),
    "both": (-5, np.array([123_456_789_000, 123_456_700_000, 0, 1], dtype=np.int64)),
}


@pytest.mark.parametrize("ages", list(AGES))
def test_frame_round_trip_carries_the_ages(ages: str) -> None:
    gyro_t, rotor_t = AGES[ages]
    frame = awkward_frame()._replace(gyro_t_us=gyro_t, rotor_speed_t_us=rotor_t)
    got = decode(encode_frame(42, frame)).frame
    assert got.gyro_t_us == gyro_t and type(got.gyro_t_us) is type(gyro_t)
    if rotor_t is None:
        assert got.rotor_speed_t_us is None
    else:
        assert got.rotor_speed_t_us.dtype == np.int64 and got.rotor_speed_t_us.tobytes() == rotor_t.tobytes()
    assert got.gyro_age_us() == frame.gyro_age_us()
    assert got.rotor_speed_age_us().tobytes() == frame.rotor_speed_age_us().tobytes()


def test_frame_with_unknown_flags_is_refused() -> None:
    packet = bytearray(encode_frame(3, awkward_frame()))
    packet[104] |= 0x04
    with pytest.raises(ProtocolError, match="flags") as info:
        decode(bytes(packet))
    assert info.value.code == ErrorCode.MALFORMED and info.value.seq == 3


@pytest.mark.parametrize("seed", [None, 0, 7, -1, 2**63 - 1, -(2**63)])
def test_reset_round_trip_seed(seed: int | None) -> None:
    assert decode(encode_reset(9, seed)) == Reset(9, seed, None)


@pytest.mark.parametrize("position", [None, (0.0, 0.0, -2.0)])
def test_reset_round_trip_state(position: tuple[float, float, float] | None) -> None:
    state = TwinState(attitude=(0.9, 0.1, -0.2, 0.3), body_rates=(1.0, -2.0, 3.5),
                      rotor_speed=(100.0, 200.0, 300.0, 400.0), position=position,
                      velocity=(0.5, -0.5, 0.25))
    assert decode(encode_reset(10, 3, state)) == Reset(10, 3, state)


def test_reset_refuses_a_seed_wider_than_64_bits() -> None:
    with pytest.raises(ValueError, match="64 bits"):
        encode_reset(1, 2**63)


def test_bye_and_error_round_trip() -> None:
    assert decode(encode_bye(77)) == Bye(77)
    assert decode(encode_error(5, ErrorCode.BUSY, "owned by 127.0.0.1:4000 — busy")) == Error(
        5, ErrorCode.BUSY, "owned by 127.0.0.1:4000 — busy")


def test_error_text_is_capped_and_unknown_codes_survive() -> None:
    msg = decode(encode_error(1, 999, "x" * 1000))
    assert isinstance(msg, Error)
    assert msg.code == 999 and len(msg.text) == MAX_ERROR_TEXT


def test_layout_is_pinned() -> None:
    """Changing these bytes is a protocol change: bump VERSION."""
    assert VERSION == 2 and HEADER.size == 16
    packet = encode_pwm(0x0102030405060708, [1000, 1500, 2000, 1250])
    assert packet[:16] == b"FCTW\x02\x01\x00\x00" + bytes.fromhex("0807060504030201")
    assert struct.unpack("<4d", packet[16:]) == (1000.0, 1500.0, 2000.0, 1250.0)
    sizes = {t: len(p) for t, p in [(MsgType.PWM, packet), (MsgType.RESET, encode_reset(1)),
                                    (MsgType.BYE, encode_bye(1)),
                                    (MsgType.FRAME, encode_frame(1, awkward_frame()))]}
    assert sizes == {MsgType.PWM: 48, MsgType.RESET: 168, MsgType.BYE: 16, MsgType.FRAME: 152}
    aged = awkward_frame()._replace(gyro_t_us=7, rotor_speed_t_us=np.array([1, 2, 3, 4], dtype=np.int64))
    frame = encode_frame(1, aged)  # t_us, 10 floats, then flags, padding and the five times
    assert struct.unpack("<q", frame[16:24]) == (123_456_789_000,)
    assert frame[104:112] == b"\x03" + bytes(7)
    assert struct.unpack("<5q", frame[112:]) == (7, 1, 2, 3, 4)
    assert encode_frame(1, awkward_frame())[104:] == bytes(48)


def test_an_error_can_be_written_in_another_version() -> None:
    """ERROR's layout is the same in every version: a request of another version is refused in it."""
    packet = encode_error(3, ErrorCode.BAD_VERSION, "protocol version 1, this end speaks 2", version=1)
    assert packet[4] == 1
    assert decode(packet[:4] + bytes([VERSION]) + packet[5:]) == Error(
        3, ErrorCode.BAD_VERSION, "protocol version 1, this end speaks 2")


VALID = [encode_pwm(3, [1500] * 4), encode_reset(3, 1, TwinState()), encode_bye(3),
         encode_frame(3, awkward_frame()), encode_error(3, ErrorCode.STALE_SEQ, "old")]


@pytest.mark.parametrize("packet", VALID, ids=["pwm", "reset", "bye", "frame", "error"])
def test_every_truncation_is_refused(packet: bytes) -> None:
    for length in range(len(packet)):
        with pytest.raises(ProtocolError) as info:
            decode(packet[:length])
        assert info.value.code == ErrorCode.MALFORMED


@pytest.mark.parametrize("packet", VALID, ids=["pwm", "reset", "bye", "frame", "error"])
def test_an_extra_byte_is_refused(packet: bytes) -> None:
    with pytest.raises(ProtocolError) as info:
        decode(packet + b"\x00")
    assert info.value.code == ErrorCode.MALFORMED
    assert info.value.seq == 3


def test_foreign_magic_is_refused() -> None:
    packet = b"MAV2" + encode_pwm(3, [1500] * 4)[4:]
    with pytest.raises(ProtocolError, match="not an fcemu twin packet") as info:
        decode(packet)
    assert info.value.code == ErrorCode.MALFORMED and info.value.seq is None


def test_other_version_is_refused_with_its_seq() -> None:
    packet = MAGIC + bytes([VERSION + 1]) + encode_pwm(3, [1500] * 4)[5:]
    with pytest.raises(ProtocolError) as info:
        decode(packet)
    assert info.value.code == ErrorCode.BAD_VERSION and info.value.seq == 3


def test_unknown_type_is_refused() -> None:
    packet = HEADER.pack(MAGIC, VERSION, 0x7F, 0, 3) + bytes(32)
    with pytest.raises(ProtocolError) as info:
        decode(packet)
    assert info.value.code == ErrorCode.UNKNOWN_TYPE and info.value.msg_type == 0x7F


def test_reset_with_unknown_flags_or_non_finite_state_is_refused() -> None:
    packet = bytearray(encode_reset(3, 1))
    packet[16] |= 0x80
    with pytest.raises(ProtocolError, match="flags"):
        decode(bytes(packet))
    bad_state = TwinState(body_rates=(float("nan"), 0.0, 0.0))
    with pytest.raises(ProtocolError) as info:
        decode(encode_reset(3, None, bad_state))
    assert info.value.code == ErrorCode.BAD_ARGUMENT


def test_error_whose_length_disagrees_with_its_text_is_refused() -> None:
    with pytest.raises(ProtocolError, match="text says"):
        decode(encode_error(3, ErrorCode.BUSY, "busy")[:-1])


def test_garbage_only_ever_raises_protocol_error() -> None:
    rng = np.random.default_rng(0)
    for length in rng.integers(0, 300, size=2000):
        data = rng.bytes(int(length))
        if rng.random() < 0.5:  # a plausible header makes the decoder go further
            data = MAGIC + bytes([VERSION, int(rng.choice([1, 2, 3, 0x81, 0x82]))]) + data[6:]
        try:
            decode(data)
        except ProtocolError:
            pass


def test_peek_header_reads_type_and_seq() -> None:
    assert peek_header(encode_bye(12)) == (MsgType.BYE, 12)
