"""Betaflight SITL packets: layouts, axes and motor order as sitl.c / target.h read and write them."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from fcemu.sim_bridge.betaflight_link import (
    FDM_PACKET,
    MOTOR_PACKET,
    RC_PACKET,
    gyro_sample,
    motor_pwm,
    pack_fdm,
    pack_rc,
    telemetry_frames,
    unpack_fdm,
    unpack_motors,
)
from fcemu.sim_bridge.faults import Fault, FaultInjector
from fcemu.sim_bridge.twin import Twin


def test_packet_sizes_match_the_c_structs():
    assert FDM_PACKET.size == 18 * 8  # fdm_packet: 18 doubles
    assert RC_PACKET.size == 8 + 16 * 2  # rc_packet: double + uint16[16]
    assert MOTOR_PACKET.size == 4 * 4  # servo_packet: float[4]


def test_fdm_carries_frd_gyro_as_is_and_the_accelerometer_so_sitl_reads_flu():
    f = np.array([0.5, -1.0, -9.81])  # FRD specific force
    data = pack_fdm(1.25, [0.1, 0.2, 0.3], f, [1.0, 0.0, 0.0, 0.0])
    fields = unpack_fdm(data)
    assert fields["timestamp"] == 1.25
    assert fields["gyro"] == pytest.approx((0.1, 0.2, 0.3))
    # sitl.c negates all three; Betaflight's sensor frame is FLU (as its gyro: x, -y, -z)
    sitl_reads = -np.array(fields["accel"])
    assert sitl_reads == pytest.approx([f[0], -f[1], -f[2]])
    assert sitl_reads[2] > 0  # level at rest: +1 g on Betaflight's z
    assert fields["quat"] == (1.0, 0.0, 0.0, 0.0)


def test_motor_packet_is_reordered_from_arducopter_to_betaflight_order():
    # sitl.c: motor_speed[3] = motor 1, [0] = motor 2, [1] = motor 3, [2] = motor 4
    data = struct.pack("<4f", 0.2, 0.3, 0.4, 0.1)
    assert unpack_motors(data) == pytest.approx((0.1, 0.2, 0.3, 0.4))
    assert motor_pwm([0.0, 0.055, 1.0, 1.5]).tolist() == pytest.approx([1000.0, 1055.0, 2000.0, 2000.0])
    with pytest.raises(ValueError, match="16 bytes"):
        unpack_motors(b"\x00" * 12)


def test_rc_packet_pads_with_switch_low_and_rejects_too_many_channels():
    ts, *ch = RC_PACKET.unpack(pack_rc(0.5, [1500, 1600, 1000, 1400, 1900]))
    assert ts == 0.5 and ch[:5] == [1500, 1600, 1000, 1400, 1900] and ch[5:] == [1000] * 11
    with pytest.raises(ValueError, match="at most 16"):
        pack_rc(0.0, [1500] * 17)


def _telemetry_sent(fault: Fault, ticks: int = 300) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """What the twin read and what the link sends each tick, hovering with `fault` on the ESC telemetry."""
    twin = Twin(rig="rig")
    twin.reset()
    twin.faults = FaultInjector(twin.dt, twin.airframe.motor.max_rotor_speed, seed=3)
    twin.faults.inject(fault)
    read, sent, last = [], [], None
    for _ in range(ticks):
        frame = twin.step(np.full(4, 1500.0))
        read.append(frame.rotor_speed)
        sent.append(telemetry_frames(frame, last))
        last = frame.rotor_speed_t_us
    return read, sent


def test_a_lost_rotor_speed_frame_goes_out_as_nan_and_a_new_one_as_read():
    read, sent = _telemetry_sent(Fault("esc-telemetry", "intermittent", 0, 0.05))
    lost = np.array([np.isnan(s).all() for s in sent[1:]])
    assert 0.02 < lost.mean() < 0.1  # 5 % of the frames, the four motors' together
    assert all(np.array_equal(s, r) for s, r, gone in zip(sent[1:], read[1:], lost, strict=True) if not gone)


def test_a_stopped_motor_telemetry_is_lost_every_tick_and_the_others_are_not():
    _, sent = _telemetry_sent(Fault("esc-telemetry", "off", 2), ticks=50)
    assert all(np.isnan(s[1]) and np.isfinite(s[[0, 2, 3]]).all() for s in sent)


def test_delayed_rotor_speed_frames_go_out_as_valid_once_the_delay_line_is_full():
    _, sent = _telemetry_sent(Fault("esc-telemetry", "delayed", 0, 0.005), ticks=50)
    assert all(np.isfinite(s).all() for s in sent[6:])


def test_without_sample_times_every_frame_is_new():
    frame = Twin(rig="rig").reset()
    assert frame.rotor_speed_t_us is None
    assert np.array_equal(telemetry_frames(frame, np.zeros(4, dtype=np.int64)), frame.rotor_speed)


def test_a_lost_gyro_sample_goes_out_as_nan_and_a_new_one_as_read():
    twin = Twin(rig="rig")
    twin.reset()
    twin.faults = FaultInjector(twin.dt, twin.airframe.motor.max_rotor_speed, seed=3)
    twin.faults.inject(Fault("gyro", "intermittent", 0, 0.2))
    last, lost = None, 0
    for _ in range(200):
        frame = twin.step(np.full(4, 1500.0))
        sent = gyro_sample(frame, last)
        new = last is None or frame.gyro_t_us > last
        assert np.isnan(sent).all() if not new else np.array_equal(sent, frame.gyro)
        lost += not new
        last = frame.gyro_t_us
    assert 20 < lost < 60  # a fifth of 200
