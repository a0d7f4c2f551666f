"""The cross-check's open-loop replay (no SITL needed: it replays recorded traces)."""

from __future__ import annotations

import numpy as np
import pytest

from fcemu.evaluation.betaflight_crosscheck import axis_mix, first_answer_tick, fly_fcemu, replay_residual
from fcemu.firmware.mixer import QuadXMixer

THROTTLE = 0.745
IDLE_US = 1055.0


@pytest.fixture(scope="module")
def flown():
    commands = np.array([[2.0, -1.0, 1.5], [-3.0, 2.5, -2.0]])
    return fly_fcemu("pid:betaflight", commands, THROTTLE, 250)


def test_axis_mix_recovers_each_axis_demand_from_the_four_motors():
    mixer = QuadXMixer("betaflight", idle=0.055)
    pwm = np.array(mixer.mix([0.1, -0.05, 0.02], 0.6))
    assert axis_mix(pwm) == pytest.approx(np.array([0.1, -0.05, 0.02]) * mixer.out_range)


def test_first_answer_tick_skips_ticks_at_idle():
    pwm = np.full((5, 4), IDLE_US)
    pwm[2:, 1] = 1300.0
    assert first_answer_tick(pwm, IDLE_US) == 2
    assert first_answer_tick(np.full((5, 4), 1400.0), IDLE_US) == 0


def test_replaying_a_controller_on_its_own_traces_leaves_no_residual(flown):
    same = replay_residual(flown, "pid:betaflight", THROTTLE, IDLE_US)
    assert same["rms_us"] == {"roll": 0.0, "pitch": 0.0, "yaw": 0.0}
    other = replay_residual(flown, "pid:iris", THROTTLE, IDLE_US)
    assert min(other["rms_us"].values()) > 20.0
    assert min(other["median_episode_rms_us"].values()) > 20.0
