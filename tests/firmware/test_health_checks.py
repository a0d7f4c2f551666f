"""The health rules' pure checks (firmware/health_checks.py), one by one: healthy inputs give None,
each fault condition its named fault, at the rules' thresholds."""

from __future__ import annotations

import dataclasses
import math
import random

import pytest

from fcemu.firmware.health import HealthRules, LagFit
from fcemu.firmware.health_checks import (
    CRITICAL,
    GYRO_IMPLAUSIBLE,
    GYRO_STALE,
    GYRO_STUCK,
    ROTOR_IMPLAUSIBLE,
    ROTOR_LAGGING,
    ROTOR_LATE,
    ROTOR_LOSING_FRAMES,
    ROTOR_STALE,
    ROTOR_TOO_OLD,
    WARNING,
    Fault,
    explained_lag,
    gyro_implausible,
    gyro_plausible,
    gyro_stale,
    gyro_stuck,
    handover,
    pwm_moved,
    rotor_implausible,
    rotor_lagging,
    rotor_late,
    rotor_losing_frames,
    rotor_off_model,
    rotor_stale,
    rotor_too_old,
    torque_asked,
)

# A round top speed (1000 rad/s over 1000 µs of PWM) so the thresholds read plainly.
RULES = HealthRules(rotor_speed_max=1000.0, motor_tau_s=0.02, pwm_min=1000.0, pwm_max=2000.0)
MOTORS = range(4)


def test_the_faults_say_what_the_monitor_declares() -> None:
    assert (CRITICAL, WARNING) == (2, 4)  # MAV_SEVERITY_CRITICAL, MAV_SEVERITY_WARNING
    assert GYRO_STALE == Fault("gyro_failed", "gyro stale", CRITICAL, "Gyro stale: rate feedback lost")
    assert (GYRO_IMPLAUSIBLE.name, GYRO_STUCK.name) == ("gyro implausible", "gyro stuck")
    assert ROTOR_TOO_OLD[2] == Fault("handover", "rotor speed 3 too old", WARNING,
                                     "Policy hands over to PID: rotor speed 3 too old")
    assert handover("gyro stuck").text == "Policy hands over to PID: gyro stuck"
    assert ROTOR_LATE[0] == Fault("esc_late", "rotor speed 1 late", WARNING,
                                  "Rotor speed 1 late: read ahead by the model")
    for per_motor in (ROTOR_TOO_OLD, ROTOR_LOSING_FRAMES, ROTOR_LAGGING, ROTOR_STALE, ROTOR_IMPLAUSIBLE,
                      ROTOR_LATE):
        assert [f.name.split()[2] for f in per_motor] == ["1", "2", "3", "4"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        GYRO_STALE.text = "changed"  # type: ignore[misc]


# ---- the gyro ----
def test_gyro_stale_past_its_max_age() -> None:
    assert gyro_stale(50_000, 50_000, RULES) is None
    assert gyro_stale(50_000, 40_000, RULES) is None  # exactly NN_GYRO_MAX_AGE (10 ms) old
    assert gyro_stale(50_000, 39_999, RULES) is GYRO_STALE


def test_gyro_plausible_within_its_range_and_jump() -> None:
    last = [0.5, -0.25, 0.25]
    tick = 0.001
    assert gyro_plausible([0.25, -0.5, 0.0], last, tick, RULES)
    assert gyro_plausible([30.0, 0.0, 0.0], None, tick, RULES)  # nothing to jump from
    assert gyro_plausible([0.5, -5.25, 0.25], last, tick, RULES)  # 5000 rad/s² for one tick exactly
    assert not gyro_plausible([0.5, -0.25, 5.5], last, tick, RULES)
    assert gyro_plausible([0.5, -0.25, 5.5], last, 2 * tick, RULES)  # the same turn over two ticks
    assert not gyro_plausible([40.5, -0.25, 0.25], last, 4 * tick, RULES)
    for axis in range(3):  # past full scale
        past = [math.radians(2001.0) if a == axis else 0.0 for a in range(3)]
        assert not gyro_plausible(past, None, tick, RULES)
    assert gyro_plausible([math.radians(-2000.0)] * 3, None, tick, RULES)
    for bad in (math.nan, math.inf, -math.inf):
        assert not gyro_plausible([0.1, bad, 0.3], last, tick, RULES)
        assert not gyro_plausible([0.1, bad, 0.3], None, tick, RULES)


def test_gyro_implausible_at_its_fail_score() -> None:
    assert gyro_implausible(0.0, RULES) is None
    assert gyro_implausible(19.75, RULES) is None
    assert gyro_implausible(20.0, RULES) is GYRO_IMPLAUSIBLE


def test_gyro_stuck_only_counts_under_a_torque() -> None:
    assert not torque_asked([1500.0] * 4, RULES)
    assert not torque_asked([1500.0, 1520.0, 1510.0, 1500.0], RULES)  # a spread of exactly 20 µs
    assert torque_asked([1500.0, 1520.5, 1510.0, 1500.0], RULES)
    assert gyro_stuck(0, RULES) is None
    assert gyro_stuck(49, RULES) is None
    assert gyro_stuck(50, RULES) is GYRO_STUCK


# ---- each motor's rotor speed ----
@pytest.mark.parametrize("i", MOTORS)
def test_rotor_too_old_past_its_max_age(i: int) -> None:
    assert rotor_too_old(i, 100_000, 100_000, RULES) is None
    assert rotor_too_old(i, 100_000, 80_000, RULES) is None  # exactly NN_ESC_MAX_AGE (20 ms) old
    assert rotor_too_old(i, 100_000, 79_999, RULES) is ROTOR_TOO_OLD[i]


@pytest.mark.parametrize("i", MOTORS)
def test_rotor_losing_frames_past_its_loss_rate(i: int) -> None:
    assert rotor_losing_frames(i, 0.0, RULES) is None
    assert rotor_losing_frames(i, 0.2, RULES) is None
    assert rotor_losing_frames(i, 0.21, RULES) is ROTOR_LOSING_FRAMES[i]


@pytest.mark.parametrize("i", MOTORS)
def test_rotor_stale_while_its_pwm_moved(i: int) -> None:
    assert not pwm_moved(1505.0, 1500.0, RULES)  # exactly `stale_pwm_us`
    assert pwm_moved(1494.5, 1500.0, RULES)
    assert rotor_stale(i, 19, RULES) is None
    assert rotor_stale(i, 20, RULES) is ROTOR_STALE[i]


@pytest.mark.parametrize("i", MOTORS)
def test_rotor_implausible_far_from_the_model(i: int) -> None:
    assert not rotor_off_model(800.0, 500.0, RULES)  # exactly `rotor_tolerance` × the top speed
    assert rotor_off_model(801.0, 500.0, RULES)
    assert rotor_off_model(199.0, 500.0, RULES)
    assert rotor_implausible(i, 9.75, RULES) is None
    assert rotor_implausible(i, 10.0, RULES) is ROTOR_IMPLAUSIBLE[i]


@pytest.mark.parametrize("i", MOTORS)
def test_rotor_late_and_lagging(i: int) -> None:
    assert rotor_late(i, 0, RULES) is None
    assert rotor_late(i, 9, RULES) is None
    assert rotor_late(i, 10, RULES) is ROTOR_LATE[i]
    assert rotor_lagging(i, 20.0, 20) is None
    assert rotor_lagging(i, 20.5, 20) is ROTOR_LAGGING[i]


# ---- the lag fit ----
BASE = 6  # ticks: `esc_lag_base_s` at 1 kHz
KEEP = math.exp(-0.001 / RULES.esc_lag_window_s)
FIT = LagFit(RULES, 0.001)


def _model(k: int, amplitude: float = 200.0) -> float:
    return 500.0 + amplitude * math.sin(2.0 * math.pi * k / 100.0)


def _sums(delay: int, gain: float = 1.0, amplitude: float = 200.0, noise: float = 0.0) -> list[float]:
    """The decaying sums the monitor keeps, of a rotor read `delay` ticks late, scaled by `gain`, with
    `noise` rad/s RMS on it."""
    sums, rng = [0.0] * 6, random.Random(0)
    for k in range(BASE, 300):
        m = _model(k, amplitude)
        w = gain * _model(k - delay, amplitude) + noise * rng.gauss(0.0, 1.0)
        dm = (m - _model(k - BASE, amplitude)) / BASE
        miss = m - w
        for j, term in enumerate((dm * dm, dm * m, m * m, miss * dm, miss * m, miss * miss)):
            sums[j] = sums[j] * KEEP + term
    return sums


def test_explained_lag_finds_a_late_reading_and_nothing_else() -> None:
    lag = explained_lag(_sums(5), FIT.motion, FIT.misfit, RULES)
    assert lag is not None and 4.0 < lag < 6.0 and lag > FIT.limit
    pipeline = explained_lag(_sums(2), FIT.motion, FIT.misfit, RULES)  # an ESC pipeline: under the limit
    assert pipeline is not None and 1.5 < pipeline < 2.5 and pipeline < FIT.limit
    assert explained_lag(_sums(0), FIT.motion, FIT.misfit, RULES) is None  # nothing left for a lag to explain
    assert explained_lag(_sums(0, gain=0.75), FIT.motion, FIT.misfit, RULES) is None  # short of its command
    late_and_short = _sums(5, gain=0.8)  # the delay would explain it, but a gain error of 0.2 says no
    assert explained_lag(late_and_short, FIT.motion, FIT.misfit, RULES) is None
    loose = dataclasses.replace(RULES, esc_lag_gain_max=0.3)
    assert explained_lag(late_and_short, FIT.motion, FIT.misfit, loose) is not None
    assert explained_lag(_sums(5, amplitude=0.0), FIT.motion, FIT.misfit, RULES) is None  # a still rotor
    late = _sums(5)
    assert explained_lag(late, late[0] * 1.01, FIT.misfit, RULES) is None  # moving too little to judge
    assert explained_lag(late, FIT.motion, late[5] * 1.01, RULES) is None  # too small a misfit to judge
    noisy = _sums(0, noise=30.0)  # a misfit the delay does not explain
    assert noisy[5] > FIT.misfit and explained_lag(noisy, FIT.motion, FIT.misfit, RULES) is None
    anything_explains = dataclasses.replace(RULES, esc_lag_explains=0.0)
    assert explained_lag(noisy, FIT.motion, FIT.misfit, anything_explains) is not None
    assert explained_lag([0.0] * 6, FIT.motion, FIT.misfit, RULES) is None


def test_the_lag_fit_counts_the_ticks_it_is_late() -> None:
    late, on_time = LagFit(RULES, 0.001), LagFit(RULES, 0.001)
    overs = []
    for k in range(BASE, 300):
        m = _model(k)
        dm = (m - _model(k - BASE)) / BASE
        late.add(_model(k - 5), m, dm)
        on_time.add(m, m, dm)
        overs.append(late.over)
    assert rotor_late(0, late.over, RULES) is ROTOR_LATE[0] and 4.0 < late.lag < 6.0
    assert overs[-1] == len(overs) - overs.count(0) and overs.count(0) < 50  # counted up, tick after tick
    assert on_time.over == 0 and on_time.lag == 0.0
