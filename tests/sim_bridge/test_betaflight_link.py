"""Betaflight SITL packets: layouts, axes and motor order as sitl.c / target.h read and write them."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from fcemu.sim_bridge.betaflight_link import (
    FDM_PACKET,
    MOTOR_PACKET,
    RC_PACKET,
    motor_pwm,
    pack_fdm,
    pack_rc,
    unpack_fdm,
    unpack_motors,
)


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
