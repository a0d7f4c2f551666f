"""RatePID term by term, in the spirit of Betaflight's pid_unittest.cc."""

from __future__ import annotations

import math

import pytest

from fcemu.firmware.pid import GAIN_SCALE, PIDGains, RatePID

DT = 0.001
ZERO = (0.0, 0.0, 0.0)


def bare(**changes) -> PIDGains:
    """No filters, relax, FF or limits unless a test asks for them."""
    base = dict(kp=ZERO, ki=ZERO, kd=ZERO, kff=ZERO, iterm_limit=(100.0,) * 3, pidsum_limit=(100.0,) * 3,
                gyro_lowpass_hz=0.0, dterm_lowpass_hz=0.0, ff_lowpass_hz=0.0, iterm_relax="off")
    base.update(changes)
    return PIDGains(**base)


def test_gain_scale_is_gymfc_degrees_over_pid_mixer_scaling():
    # GymFC: PID on deg/s, sum / 1000 into the mixer. Kp = 1 at 1 deg/s of error is 0.001.
    pid = RatePID(bare(kp=(1.0, 1.0, 1.0)), DT)
    out = pid.update([math.radians(1.0), 0.0, -math.radians(2.0)], ZERO)
    assert out == pytest.approx([0.001, 0.0, -0.002], rel=1e-12)
    assert pytest.approx(180 / math.pi / 1000) == GAIN_SCALE


def test_p_term_exact():
    pid = RatePID(bare(kp=(2.0, 10.0, 4.0)), DT)
    out = pid.update([1.0, 2.0, 3.0], [0.5, 0.0, -1.0])
    assert out == pytest.approx([2.0 * 0.5 * GAIN_SCALE, 10.0 * 2.0 * GAIN_SCALE, 4.0 * 4.0 * GAIN_SCALE],
                                rel=1e-12)
    assert pid.terms["p"] == pytest.approx(out)
    assert pid.terms["i"] == [0.0, 0.0, 0.0]


def test_i_term_accumulates_error_times_dt():
    pid = RatePID(bare(ki=(10.0, 20.0, 50.0)), DT)
    for n in range(1, 101):
        out = pid.update([1.0, -0.5, 0.2], ZERO)
        expected = [10.0 * 1.0 * n * DT * GAIN_SCALE, -20.0 * 0.5 * n * DT * GAIN_SCALE,
                    50.0 * 0.2 * n * DT * GAIN_SCALE]
        assert out == pytest.approx(expected, rel=1e-9)


def test_i_term_clamped_at_iterm_limit_and_recovers_at_once():
    pid = RatePID(bare(ki=(100.0, 100.0, 100.0), iterm_limit=(0.1, 0.2, 0.3)), DT)
    for _ in range(2000):
        pid.update([5.0, -5.0, 5.0], ZERO)
    assert pid.terms["i"] == pytest.approx([0.1, -0.2, 0.3])
    out = pid.update([-1.0, 1.0, -1.0], ZERO)  # no stored windup beyond the limit
    step = 100.0 * DT * GAIN_SCALE
    assert out == pytest.approx([0.1 - step, -0.2 + step, 0.3 - step], rel=1e-9)


def test_d_spikes_on_gyro_step_but_not_on_setpoint_step():
    kd = 0.005
    pid = RatePID(bare(kd=(kd, kd, kd)), DT)
    pid.update(ZERO, ZERO)
    out = pid.update(ZERO, [1.0, 0.0, -2.0])  # the craft's rate jumps
    assert out == pytest.approx([-kd * 1.0 / DT * GAIN_SCALE, 0.0, kd * 2.0 / DT * GAIN_SCALE], rel=1e-9)
    assert pid.update(ZERO, [1.0, 0.0, -2.0]) == pytest.approx([0.0, 0.0, 0.0], abs=1e-12)

    pid.reset()
    pid.update(ZERO, ZERO)
    out = pid.update([3.0, -3.0, 3.0], ZERO)  # the pilot's setpoint jumps: D on measurement ignores it
    assert pid.terms["d"] == [0.0, 0.0, 0.0]
    assert out == [0.0, 0.0, 0.0]


def test_d_term_lowpass_spreads_the_spike():
    kd = 0.005
    pid = RatePID(bare(kd=(kd, kd, kd), dterm_lowpass_hz=50.0), DT)
    pid.update(ZERO, ZERO)
    spike = [pid.update(ZERO, [1.0, 1.0, 1.0])[0] for _ in range(200)]
    raw = -kd / DT * GAIN_SCALE
    assert 0.5 * raw < spike[0] < 0.0  # a smaller first kick...
    assert sum(spike) == pytest.approx(raw, rel=1e-3)  # ...with the same area
    assert spike[-1] == pytest.approx(0.0, abs=1e-6)


def test_feedforward_on_setpoint_ramp_and_none_on_constant_setpoint():
    kff = 0.02
    pid = RatePID(bare(kff=(kff, kff, 0.0)), DT)
    slope = 50.0  # rad/s²
    outs = [pid.update([slope * n * DT, -slope * n * DT, slope * n * DT], ZERO) for n in range(1, 20)]
    for out in outs:
        assert out == pytest.approx([kff * slope * GAIN_SCALE, -kff * slope * GAIN_SCALE, 0.0], rel=1e-9)
    hold = pid.update([slope * 19 * DT] * 3, ZERO)
    assert hold[0] == pytest.approx(0.0, abs=1e-12)


def test_feedforward_lowpass_keeps_the_kick_area():
    kff = 0.02
    pid = RatePID(bare(kff=(kff, kff, kff), ff_lowpass_hz=30.0), DT)
    kick = [pid.update([2.0, 0.0, 0.0], ZERO)[0] for _ in range(500)]
    assert kick[0] < kff * 2.0 / DT * GAIN_SCALE
    assert sum(kick) * DT == pytest.approx(kff * 2.0 * GAIN_SCALE, rel=1e-3)


def test_iterm_relax_holds_i_while_the_setpoint_moves_fast():
    gains = bare(ki=(50.0, 50.0, 50.0), iterm_relax="rp", iterm_relax_cutoff_hz=15.0,
                 iterm_relax_threshold=math.radians(40.0))
    relaxed, plain = RatePID(gains, DT), RatePID(gains.with_(iterm_relax="off"), DT)
    for _ in range(5):
        relaxed.update([3.0, 3.0, 3.0], ZERO)
        plain.update([3.0, 3.0, 3.0], ZERO)
    i_relaxed, i_plain = relaxed.terms["i"], plain.terms["i"]
    assert i_relaxed[0] == 0.0 and i_relaxed[1] == 0.0  # roll and pitch held: hpf > threshold
    assert i_relaxed[2] == pytest.approx(i_plain[2])  # "rp": yaw not relaxed
    assert i_plain[0] > 0.0
    for _ in range(1000):  # the setpoint settles, the high-pass decays, I integrates again
        relaxed.update([3.0, 3.0, 3.0], ZERO)
    assert relaxed.terms["i"][0] > 0.5 * 50.0 * 3.0 * 1.0 * GAIN_SCALE


def test_iterm_relax_factor_matches_betaflight_formula():
    threshold = math.radians(40.0)
    gains = bare(ki=(1.0, 1.0, 1.0), iterm_relax="rpy", iterm_relax_cutoff_hz=15.0,
                 iterm_relax_threshold=threshold)
    pid = RatePID(gains, DT)
    sp = 0.2  # a small step: the factor stays between 0 and 1
    pid.update([sp, 0.0, 0.0], ZERO)
    k = DT / (1 / (2 * math.pi * 15.0) + DT)
    factor = 1 - abs(sp - k * sp) / threshold
    assert pid.terms["i"][0] == pytest.approx(1.0 * DT * sp * factor * GAIN_SCALE, rel=1e-9)


def test_iterm_relax_inc_lets_i_shrink():
    gains = bare(ki=(50.0, 50.0, 50.0), iterm_relax="rp_inc")
    pid = RatePID(gains, DT)
    for _ in range(1000):
        pid.update([1.0, 0.0, 0.0], ZERO)
    before = pid.terms["i"][0]
    pid.update([-3.0, 0.0, 0.0], ZERO)  # a fast stick move against the stored I
    assert pid.terms["i"][0] < before
    plain = RatePID(gains.with_(iterm_relax="rp"), DT)
    for _ in range(1000):
        plain.update([1.0, 0.0, 0.0], ZERO)
    before = plain.terms["i"][0]
    plain.update([-3.0, 0.0, 0.0], ZERO)
    assert plain.terms["i"][0] == before


def test_pidsum_limit():
    pid = RatePID(bare(kp=(100.0, 100.0, 100.0), pidsum_limit=(0.5, 0.5, 0.4)), DT)
    assert pid.update([5.0, -5.0, 5.0], ZERO) == [0.5, -0.5, 0.4]
    assert pid.update([0.01, 0.0, -0.01], ZERO) == pytest.approx([100 * 0.01 * GAIN_SCALE, 0.0,
                                                                  -100 * 0.01 * GAIN_SCALE])


def test_iterm_windup_stops_accumulation_when_the_mixer_saturates():
    gains = bare(ki=(10.0, 10.0, 10.0), iterm_windup=0.8)
    pid = RatePID(gains, DT)
    pid.update([1.0, 1.0, 1.0], ZERO, mix_range=1.2)
    assert pid.terms["i"] == [0.0, 0.0, 0.0]
    pid.update([1.0, 1.0, 1.0], ZERO, mix_range=0.9)  # half way between 0.8 and 1.0
    assert pid.terms["i"][0] == pytest.approx(0.5 * 10.0 * DT * GAIN_SCALE)
    pid.update([1.0, 1.0, 1.0], ZERO, mix_range=0.5)
    assert pid.terms["i"][0] == pytest.approx(1.5 * 10.0 * DT * GAIN_SCALE)


def test_gyro_lowpass_comes_before_p_and_d():
    gains = bare(kp=(1.0, 1.0, 1.0), gyro_lowpass_hz=50.0)
    pid = RatePID(gains, DT)
    pid.update(ZERO, ZERO)
    out = pid.update(ZERO, [1.0, 1.0, 1.0])
    k = DT / (1 / (2 * math.pi * 50.0) + DT)
    assert out[0] == pytest.approx(-k * GAIN_SCALE)


def test_reset_clears_state_and_arming_while_rotating_gives_no_d_kick():
    pid = RatePID(bare(ki=(10.0, 10.0, 10.0), kd=(0.01, 0.01, 0.01), dterm_lowpass_hz=80.0,
                       gyro_lowpass_hz=100.0), DT)
    for _ in range(100):
        pid.update([1.0, 1.0, 1.0], ZERO)
    pid.reset()
    out = pid.update(ZERO, [2.0, 2.0, 2.0])  # armed while turning at 2 rad/s
    assert pid.terms["d"] == [0.0, 0.0, 0.0]
    assert pid.terms["i"][0] == pytest.approx(-10.0 * 2.0 * DT * GAIN_SCALE)
    assert out[0] == pytest.approx(pid.terms["i"][0])


def test_take_over_mid_step_starts_from_p_alone_without_a_feedforward_or_d_kick():
    gains = bare(kp=(40.0, 40.0, 40.0), ki=(10.0, 10.0, 10.0), kd=(0.01, 0.01, 0.01), kff=(0.02, 0.02, 0.02),
                 dterm_lowpass_hz=80.0, gyro_lowpass_hz=100.0, iterm_relax="rp")
    pid = RatePID(gains, DT)
    for _ in range(100):
        pid.update([1.0, 1.0, 1.0], ZERO)
    sp, gyro = [3.0, -2.0, 1.0], [2.5, -1.0, 0.0]  # another controller flew to here, mid-step
    pid.take_over(sp, gyro)
    out = pid.update(sp, gyro)
    assert pid.terms["d"] == [0.0, 0.0, 0.0] and pid.terms["f"] == [0.0, 0.0, 0.0]
    p = [40.0 * GAIN_SCALE * (s - g) for s, g in zip(sp, gyro, strict=True)]
    assert out == pytest.approx([pi + ii for pi, ii in zip(p, pid.terms["i"], strict=True)], rel=1e-12)
    assert max(map(abs, pid.terms["i"])) < 1e-3  # what it integrated before is gone
    pid.reset()
    kicked = pid.update(sp, gyro)  # from reset, the setpoint seems to jump from 0: a feedforward kick
    assert abs(pid.terms["f"][0]) > 1.0 and kicked != out


def test_set_gains_keeps_i_and_set_dt_keeps_integral_units():
    pid = RatePID(bare(ki=(10.0, 10.0, 10.0)), DT)
    for _ in range(100):
        pid.update([1.0, 0.0, 0.0], ZERO)
    i_before = pid.terms["i"][0]
    pid.set_gains(bare(ki=(10.0, 10.0, 10.0), kp=(1.0, 1.0, 1.0)))
    pid.update(ZERO, ZERO)
    assert pid.terms["i"][0] == pytest.approx(i_before)
    fast = RatePID(bare(ki=(10.0, 10.0, 10.0)), DT)
    fast.set_dt(DT / 8)
    for _ in range(800):
        fast.update([1.0, 0.0, 0.0], ZERO)
    assert fast.terms["i"][0] == pytest.approx(i_before, rel=1e-9)  # the same 0.1 s of error


def test_gains_validation_and_round_trip():
    with pytest.raises(ValueError, match="one value per axis"):
        PIDGains(kp=(1.0, 2.0), ki=ZERO, kd=ZERO)
    with pytest.raises(ValueError, match="iterm_relax"):
        bare(iterm_relax="sometimes")
    with pytest.raises(ValueError, match="unknown PID settings"):
        PIDGains.from_dict({"kp": [1, 1, 1], "ki": [0, 0, 0], "kd": [0, 0, 0], "kq": 3})
    g = bare(kp=(1.0, 2.0, 3.0), kff=0.5)
    assert g.kff == (0.5, 0.5, 0.5)
    assert PIDGains.from_dict(g.to_dict()) == g
