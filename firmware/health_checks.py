"""The health rules and their judgments (firmware/health.py) as pure functions: each takes the sample, the
previous values or counts it needs and the rules, and returns the named `Fault` it finds, or None.

Nothing here keeps state or says anything: `HealthMonitor` keeps the last samples, the counts and
the lag fit, calls these each tick, and acts on what they return (declares it, hands the policy
over, fails the gyro). The faults are module constants, one per motor for the rotor-speed rules,
so that a healthy tick builds none.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from fcemu.firmware.airframe_spec import AirframeSpec

CRITICAL, WARNING = 2, 4  # MAV_SEVERITY

# What `HealthMonitor.detected` records a fault under: each is declared once per arming.
GYRO_FAILED, HANDOVER, ESC_LATE = "gyro_failed", "handover", "esc_late"


@dataclass(frozen=True)
class HealthRules:
    """The thresholds; the motors' (top speed, PWM range, speed model) come from `for_airframe`."""

    rotor_speed_max: float = field(kw_only=True)  # rad/s at pwm_max
    motor_tau_s: float = field(kw_only=True)  # the speed model's time constant (both directions)
    motor_tau_up_s: float | None = field(default=None, kw_only=True)  # spinning up; None: motor_tau_s
    motor_tau_down_s: float | None = field(default=None, kw_only=True)  # spinning down; None: motor_tau_s
    pwm_min: float = field(kw_only=True)
    pwm_max: float = field(kw_only=True)
    gyro_range: float = math.radians(2000.0)  # rad/s
    # No airframe turns its rate faster (5 rad/s in a 1 kHz tick); a sample farther from the last
    # good one than this allows over the time since the previous frame's sample is implausible.
    gyro_accel_max: float = 5000.0  # rad/s²
    gyro_fail_score: float = 20.0
    gyro_stuck_ticks: int = 50
    torque_spread_us: float = 20.0  # max − min PWM of the four motors
    recovery: float = 0.25  # score taken off per good sample
    rotor_tolerance: float = 0.3  # × rotor_speed_max
    rotor_fail_score: float = 10.0
    rotor_stale_ticks: int = 20
    stale_pwm_us: float = 5.0
    # NN_GYRO_MAX_AGE: PX4's mc_nn_control refuses a gyro sample older than 10 ms; a rate loop on
    # older feedback rings (a 5 ms delay already costs the PID 8× its Error, docs/results/faults.md).
    gyro_max_age_s: float = 0.010
    # NN_ESC_MAX_AGE: about one motor time constant (the Iris's spin-up 12.5 ms, spin-down 25 ms):
    # a held reading older than that says little of the rotor now.
    esc_max_age_s: float = 0.020
    # NN_ESC_LOSS_MAX over NN_ESC_LOSS_WIN: bidirectional DShot loses a fraction of a percent to a
    # few percent of frames in normal flight; a fifth of them lost over 100 ms is a failing link.
    esc_loss_max: float = 0.2
    esc_loss_window_s: float = 0.1
    # NN_ESC_MAX_LAG: telemetry that fits the commanded speed best more than 3 ms late is late
    # beyond the ESC's own pipeline (1-2 ticks on a real board, iris_realistic.json) and is brought
    # forward by the model; fitted over the last 50 ms, held 10 ticks, and only while the model
    # moves more than `esc_lag_motion` × the top speed (RMS per tick): a still rotor tells no lag.
    esc_max_lag_s: float = 0.003
    esc_lag_window_s: float = 0.05
    esc_lag_ticks: int = 10
    esc_lag_motion: float = 0.002
    # The fit's own settings (module docstring): the model's slope taken over 6 ms (twice the
    # limit, so a 3-5 ms lag interpolates within it). A lag worth judging moves the reading by
    # 0.9 % of the top speed RMS (10 rad/s on the Iris; a 5 ms lag of the in-flight task moves it
    # 11-28) and explains 60 % of what a gain error leaves (a 5 ms lag: 62-100 %; a sagging
    # battery's transient 2-13 %; iris_realistic's 1-tick ESC, sagging battery and noisy gyro
    # together 45-66 %, RMS 7-12). A late copy of the speed has no gain error; a dead motor or a
    # 0.75 battery one of 0.25.
    esc_lag_base_s: float = 0.006
    esc_lag_misfit: float = 0.009
    esc_lag_explains: float = 0.6
    esc_lag_gain_max: float = 0.1

    @classmethod
    def for_airframe(cls, airframe: AirframeSpec, **thresholds: float) -> HealthRules:
        """The rules for `airframe`: its top rotor speed and PWM range, a speed model between its
        motors' spin-up and spin-down time constants; `thresholds` replace the defaults above."""
        return cls(rotor_speed_max=airframe.max_rotor_speed, pwm_min=airframe.pwm_min,
                   pwm_max=airframe.pwm_max, **thresholds,
                   motor_tau_s=0.5 * (airframe.motor_tau_up + airframe.motor_tau_down),
                   motor_tau_up_s=airframe.motor_tau_up, motor_tau_down_s=airframe.motor_tau_down)


@dataclass(frozen=True, slots=True)
class Fault:
    """A verdict: `name` says what failed and how (the monitor's `failsafe` and `handover` read it),
    `text` is the STATUSTEXT that says it at `severity`, `verdict` the key it is declared under."""

    verdict: str
    name: str
    severity: int
    text: str


def gyro_fault(how: str) -> Fault:
    """The gyro has failed: the vehicle lands on its setpoint alone."""
    return Fault(GYRO_FAILED, f"gyro {how}", CRITICAL, f"Gyro {how}: rate feedback lost")


def handover(name: str) -> Fault:
    """The policy hands over to the PID because of `name`."""
    return Fault(HANDOVER, name, WARNING, f"Policy hands over to PID: {name}")


def _per_motor(how: str) -> tuple[Fault, ...]:
    return tuple(handover(f"rotor speed {i + 1} {how}") for i in range(4))


GYRO_STALE = gyro_fault("stale")
GYRO_IMPLAUSIBLE = gyro_fault("implausible")
GYRO_STUCK = gyro_fault("stuck")
ROTOR_TOO_OLD = _per_motor("too old")
ROTOR_LOSING_FRAMES = _per_motor("losing frames")
ROTOR_LAGGING = _per_motor("lagging")
ROTOR_STALE = _per_motor("stale")
ROTOR_IMPLAUSIBLE = _per_motor("implausible")
ROTOR_LATE = tuple(Fault(ESC_LATE, f"rotor speed {i + 1} late", WARNING,
                         f"Rotor speed {i + 1} late: read ahead by the model") for i in range(4))


# ---- the gyro ----
def gyro_stale(t_us: int, sampled_us: int, rules: HealthRules) -> Fault | None:
    """NN_GYRO_MAX_AGE: the sample taken at `sampled_us` is too old to fly on at `t_us`."""
    return GYRO_STALE if t_us - sampled_us > rules.gyro_max_age_s * 1e6 else None


def gyro_plausible(g: list[float], last: list[float] | None, elapsed_s: float, rules: HealthRules) -> bool:
    """Whether the sample `g` is within the gyro's full scale and within `gyro_accel_max` ×
    `elapsed_s` of `last`, the last good sample (None: no jump to judge); `elapsed_s` is the time
    since the previous frame's sample: after a late tick the vehicle has had longer to turn, while a
    held run of bad samples earns no room. NaN fails every comparison, so it is implausible."""
    g0, g1, g2 = g
    top = rules.gyro_range
    return (abs(g0) <= top and abs(g1) <= top and abs(g2) <= top
            and (last is None
                 or max(abs(g0 - last[0]), abs(g1 - last[1]), abs(g2 - last[2]))
                 <= rules.gyro_accel_max * elapsed_s))


def gyro_implausible(score: float, rules: HealthRules) -> Fault | None:
    """The implausible samples' score (+1 each, `recovery` off per good one) has reached the limit."""
    return GYRO_IMPLAUSIBLE if score >= rules.gyro_fail_score else None


def torque_asked(pwm: list[float], rules: HealthRules) -> bool:
    """Whether the motors' outputs ask for a torque, under which a gyro that reads nothing new is stuck."""
    return max(pwm) - min(pwm) > rules.torque_spread_us


def gyro_stuck(stuck_ticks: int, rules: HealthRules) -> Fault | None:
    """The gyro has read the same sample for `stuck_ticks` new samples while a torque was asked for."""
    return GYRO_STUCK if stuck_ticks >= rules.gyro_stuck_ticks else None


# ---- each motor's rotor speed (`i` from 0, Betaflight order) ----
def rotor_too_old(i: int, t_us: int, sampled_us: int, rules: HealthRules) -> Fault | None:
    """NN_ESC_MAX_AGE: motor `i`'s newest sample, taken at `sampled_us`, is too old at `t_us`."""
    return ROTOR_TOO_OLD[i] if t_us - sampled_us > rules.esc_max_age_s * 1e6 else None


def rotor_losing_frames(i: int, loss: float, rules: HealthRules) -> Fault | None:
    """NN_ESC_LOSS_MAX: the fraction of motor `i`'s frames lost (over NN_ESC_LOSS_WIN) is too high."""
    return ROTOR_LOSING_FRAMES[i] if loss > rules.esc_loss_max else None


def pwm_moved(pwm: float, pwm_at_change: float, rules: HealthRules) -> bool:
    """Whether a motor's PWM has moved, since its reading last changed, by more than a reading may ignore."""
    return abs(pwm - pwm_at_change) > rules.stale_pwm_us


def rotor_stale(i: int, stale_ticks: int, rules: HealthRules) -> Fault | None:
    """Motor `i` has reported the same speed for `stale_ticks` new samples while its PWM moved."""
    return ROTOR_STALE[i] if stale_ticks >= rules.rotor_stale_ticks else None


def rotor_off_model(v: float, model: float, rules: HealthRules) -> bool:
    """Whether the reading `v` is farther from the model's speed `model` than any rotor could be."""
    return abs(v - model) > rules.rotor_tolerance * rules.rotor_speed_max


def rotor_implausible(i: int, score: float, rules: HealthRules) -> Fault | None:
    """Motor `i`'s off-model samples' score (+1 each, `recovery` off per good one) has reached the limit."""
    return ROTOR_IMPLAUSIBLE[i] if score >= rules.rotor_fail_score else None


def explained_lag(sums: list[float], motion: float, misfit: float, rules: HealthRules) -> float | None:
    """The lag (ticks) the least-squares fit puts on a motor's telemetry, from its decaying sums of
    ṁ², ṁ·m, m², (m − w)·ṁ, (m − w)·m and (m − w)²: None unless the model moves (ṁ² above
    `motion`), a gain error alone leaves a misfit above `misfit`, the delay explains at least
    `esc_lag_explains` of it, and the gain error is within `esc_lag_gain_max` (a rotor that cannot
    follow its command is not late; an early or still fit can put any lag on it)."""
    det = sums[0] * sums[2] - sums[1] * sums[1]
    if not (sums[0] > motion and det > 0.0):
        return None
    lag = (sums[3] * sums[2] - sums[1] * sums[4]) / det
    gain_error = (sums[0] * sums[4] - sums[1] * sums[3]) / det
    left_by_gain = sums[5] - sums[4] * sums[4] / sums[2]
    left = sums[5] - lag * sums[3] - gain_error * sums[4]
    if (abs(gain_error) < rules.esc_lag_gain_max and left_by_gain > misfit
            and left_by_gain - left > rules.esc_lag_explains * left_by_gain):
        return lag
    return None


def rotor_late(i: int, late_ticks: int, rules: HealthRules) -> Fault | None:
    """NN_ESC_MAX_LAG: motor `i`'s fit has put it beyond the limit for `late_ticks` ticks in a row."""
    return ROTOR_LATE[i] if late_ticks >= rules.esc_lag_ticks else None


def rotor_lagging(i: int, lag_ticks: float, max_lag_ticks: int) -> Fault | None:
    """Motor `i`'s judged lag is past what the model reads ahead (NN_ESC_MAX_AGE): too late to fly on."""
    return ROTOR_LAGGING[i] if lag_ticks > max_lag_ticks else None
