"""Sensor health: what the flight controller makes of a gyro or ESC telemetry it can no longer trust.

`HealthMonitor.check(frame, pwm)` runs once per tick before the controller, on plain floats (a
few µs), and returns the frame the controller should read: the same object while nothing is
wrong. The rules, with `HealthRules`' defaults at 1 kHz (docs/DESIGN.md, "Faults and the
firmware's answers"):

- Gyro sample implausible: not finite, beyond the gyro's full scale (±2000 deg/s), or a jump of
  more than `gyro_jump` rad/s from the last good sample in one tick (no airframe accelerates that
  fast). The sample is replaced by the last good one (a dropped or spiked sample costs one tick
  of old data). Each implausible sample adds 1 to a score, each good one takes `recovery` off;
  at `gyro_fail_score` the gyro has FAILED.
- Gyro stuck: all three axes bit-identical for `gyro_stuck_ticks` ticks in which the motor
  outputs were asking for a torque (their spread above `torque_spread_us`): FAILED.
- Gyro stale: the sample older than `gyro_max_age_s` (NN_GYRO_MAX_AGE, 10 ms: PX4's
  mc_nn_control refuses older gyro data): FAILED. A repeated sample with its old time is a lost
  frame, not a stuck gyro: only samples with a new time count toward "stuck".
- Gyro FAILED (latched until the next arming): the controller reads zero rates from then on
  (it flies on its setpoint alone), the policy hands over to the PID, and `failsafe` asks the
  vehicle for LAND; said once.
- Rotor speed judged by age and loss rate, not by single frames: a lost frame (a non-finite
  reading, or one whose sample time did not advance) is held, the last sample standing in for it
  (as a spiking gyro sample is replaced). The policy hands over when a motor's telemetry is older
  than `esc_max_age_s` (NN_ESC_MAX_AGE), or when the fraction of its frames lost, averaged over
  `esc_loss_window_s` (NN_ESC_LOSS_WIN), passes `esc_loss_max` (NN_ESC_LOSS_MAX).
- Rotor speed lagging: the delay d that best fits a motor's telemetry w to a first-order model m
  of the commanded speed (the airframe's spin-up and spin-down time constants), linearised so it
  costs a few µs a tick: w ≈ (1 − k)·m(t − d) ≈ m − k·m − d·ṁ (ṁ the model's slope over
  `esc_lag_base_s`), d and a gain error k fitted by least squares over the last
  `esc_lag_window_s`. It is judged only while the model moves (ṁ's RMS above `esc_lag_motion` ×
  the top speed per tick) and the gain alone leaves a misfit (RMS above `esc_lag_misfit` × the
  top speed) of which the delay explains at least `esc_lag_explains`, with a gain error k
  within `esc_lag_gain_max` (a rotor that cannot follow its command, on a sagging battery or
  a dead motor, is not late); d beyond `esc_max_lag_s` (NN_ESC_MAX_LAG) for `esc_lag_ticks`
  ticks in a row is late beyond the ESC's own pipeline, and the policy flies on: from then on every
  motor's readings (one late motor says the bus is late) are brought forward by the model over
  that motor's last judged lag, w + m(t) − m(t − d) (a Smith predictor: the reading keeps what the
  model misses, a sagging battery, and gains the change the lag hides). A late ESC handed over
  to the PID cost the default 3.3× its fault-free Error at 5 ms; brought forward, 1.3×
  (docs/results/faults.md). A judged lag past `esc_max_age_s` (a reading that old says little
  of the rotor now) hands over.
- Rotor speed stale: a motor's new samples bit-identical for `rotor_stale_ticks` ticks while its
  PWM moved more than `stale_pwm_us` from where it was when the reading last changed. Rotor speed
  implausible: a new sample farther than `rotor_tolerance` × the top speed from the model, scored
  as the gyro's, at `rotor_fail_score`. Each rotor-speed verdict but "late" hands the policy over to the PID
  (latched until the next arming) and is said once; the PID does not read rotor speed, so the
  vehicle flies on. While the PID flies (`policy_flying` False, set by the loop each tick) there
  is nothing to hand over and nothing is said about rotor speed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fcemu.firmware.airframe_spec import AirframeSpec
from fcemu.firmware.sensors import SensorFrame

CRITICAL, WARNING = 2, 4  # MAV_SEVERITY
_ZERO3 = np.zeros(3)


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
    gyro_jump: float = 5.0  # rad/s in one tick (5000 rad/s² at 1 kHz)
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


def read_ahead_ticks(esc_lag_base_s: float, esc_max_age_s: float, dt: float) -> int:
    """The most ticks a late reading is brought forward: `esc_max_age_s` (NN_ESC_MAX_AGE), and at
    least the model's slope base. Betaflight's patch reads ahead as far (NEURAL_LAG_AHEAD_TICKS)."""
    return max(1, round(esc_lag_base_s / dt), round(esc_max_age_s / dt))


class HealthMonitor:
    """The rules above for one vehicle; `detected` maps each verdict to the tick it was reached."""

    def __init__(self, rules: HealthRules, dt: float = 0.001) -> None:
        self.rules = r = rules
        # the model's decay per µs of sensor time, spinning up and down
        self._keep_up = math.exp(-1e-6 / (r.motor_tau_up_s or r.motor_tau_s))
        self._keep_down = math.exp(-1e-6 / (r.motor_tau_down_s or r.motor_tau_s))
        self._dt_us = round(dt * 1e6)
        self._gyro_max_age_us = r.gyro_max_age_s * 1e6
        self._esc_max_age_us = r.esc_max_age_s * 1e6
        self._loss_gain = 1.0 - math.exp(-dt / r.esc_loss_window_s)
        self._lag_base = max(1, round(r.esc_lag_base_s / dt))
        self._max_lag = read_ahead_ticks(r.esc_lag_base_s, r.esc_max_age_s, dt)
        self._speed_per_us = r.rotor_speed_max / (r.pwm_max - r.pwm_min)
        self._tolerance = r.rotor_tolerance * r.rotor_speed_max
        self.outbox: list[tuple[int, str]] = []
        self.policy_flying = True  # the loop says which controller flies; only a policy hands over
        self.reset()

    def reset(self) -> None:
        """Start over (at arming): every verdict cleared, the models restarted from the next frame."""
        self.ticks = 0
        self.policy_trusted = True
        self.gyro_failed = False
        self.failsafe = ""
        self.handover = ""  # why the policy handed over ("" while it flies)
        self.detected: dict[str, int] = {}
        self.glitches = 0
        self._gyro_score = 0.0
        self._last_good: list[float] | None = None
        self._held: np.ndarray | None = None
        self._stuck = 0
        self._expected: list[float] | None = None
        self._t_us: int | None = None
        self._prev_speed = [math.nan] * 4
        self._pwm_at_change = [math.nan] * 4  # each motor's PWM when its reading last changed
        self._stale = [0] * 4
        self._rotor_score = [0.0] * 4
        self._gyro_t: int | None = None
        self._sample_t: list[int] = [0] * 4  # each motor's newest sample time
        self._held_speed: list[float] | None = None
        self._loss = [0.0] * 4
        self._lag = [LagFit(self.rules, self._dt_us * 1e-6) for _ in range(4)]
        self._model_past: list[list[float]] = []  # per motor, the model's speeds, a ring of `_max_lag` + 1
        self._past_at = 0
        self._bus_late = False  # every motor's readings brought forward by the model, each over its own lag

    # ---- verdicts ----
    def _declare(self, what: str, severity: int, text: str) -> None:
        if what not in self.detected:
            self.detected[what] = self.ticks
            self.outbox.append((severity, text))

    def _hand_over(self, why: str) -> None:
        if self.policy_trusted and self.policy_flying:
            self.policy_trusted = False
            self.handover = why
            self._declare("handover", WARNING, f"Policy hands over to PID: {why}")

    def _fail_gyro(self, why: str) -> None:
        self.gyro_failed = True
        self.failsafe = f"gyro {why}"
        self._declare("gyro_failed", CRITICAL, f"Gyro {why}: rate feedback lost")
        self._hand_over(f"gyro {why}")

    # ---- the tick ----
    def check(self, frame: SensorFrame, pwm: np.ndarray) -> SensorFrame:
        """The frame to fly on, given this tick's `frame` and the PWM written the tick before."""
        self.ticks += 1
        p = pwm.tolist()
        gyro = self._check_gyro(frame.gyro.tolist(), p, frame.t_us, frame.gyro_t_us)
        held = self._check_rotors(frame, p)
        if gyro is None and held is None:
            return frame
        return frame._replace(gyro=frame.gyro if gyro is None else gyro,
                              rotor_speed=frame.rotor_speed if held is None else held)

    def _check_gyro(self, g: list[float], p: list[float], t_us: int,
                    sampled: int | None) -> np.ndarray | None:
        r = self.rules
        if self.gyro_failed:
            return _ZERO3
        fresh = True  # a sample with a new time (a frame without times: every sample is)
        if sampled is not None:
            if t_us - sampled > self._gyro_max_age_us:
                self._fail_gyro("stale")
                return _ZERO3
            fresh = self._gyro_t is None or sampled > self._gyro_t
            self._gyro_t = sampled
        last = self._last_good
        g0, g1, g2 = g
        top, jump = r.gyro_range, r.gyro_jump
        valid = (abs(g0) <= top and abs(g1) <= top and abs(g2) <= top
                 and (last is None or max(abs(g0 - last[0]), abs(g1 - last[1]), abs(g2 - last[2])) <= jump))
        if not valid:  # NaN fails every comparison above
            self.glitches += 1
            self._gyro_score += 1.0
            if self._gyro_score >= r.gyro_fail_score:
                self._fail_gyro("implausible")
                return _ZERO3
            if self._held is None:
                self._held = np.array(last) if last is not None else _ZERO3
            return self._held
        self._gyro_score = max(0.0, self._gyro_score - r.recovery)
        if g == last:
            if fresh and max(p) - min(p) > r.torque_spread_us:
                self._stuck += 1
                if self._stuck >= r.gyro_stuck_ticks:
                    self._fail_gyro("stuck")
                    return _ZERO3
        else:
            self._stuck = 0
        self._last_good = g
        self._held = None
        return None

    def _check_rotors(self, frame: SensorFrame, p: list[float]) -> np.ndarray | None:
        """Judges each motor's telemetry; returns the rotor speeds to fly on where a frame was lost."""
        r = self.rules
        w = frame.rotor_speed.tolist()
        t_us = frame.t_us
        sampled = [t_us] * 4 if frame.rotor_speed_t_us is None else frame.rotor_speed_t_us.tolist()
        expected = self._expected
        if expected is None:
            expected = self._expected = [v if math.isfinite(v) else 0.0 for v in w]
            self._held_speed = list(expected)
            self._sample_t = [t - 1 for t in sampled]  # the first frame's samples are new
            self._model_past = [[e] * (self._max_lag + 1) for e in expected]
        # The model advances by the frames' own clock: ticks the loop skipped moved the rotors too.
        first = self._t_us is None
        elapsed = self._dt_us if first else min(max(t_us - self._t_us, 0), 100_000)
        self._t_us = t_us
        up, down = 1.0 - self._keep_up ** elapsed, 1.0 - self._keep_down ** elapsed
        per_us, lo = self._speed_per_us, r.pwm_min
        hi_speed = r.rotor_speed_max
        held_speed, sample_t, loss, gain = self._held_speed, self._sample_t, self._loss, self._loss_gain
        judging = self.policy_flying and self.policy_trusted
        replaced = None
        at, base, ring = self._past_at, self._lag_base, self._max_lag + 1
        self._past_at = (at + 1) % ring
        for i in range(4):
            v, pi = w[i], p[i]
            command = min(max((pi - lo) * per_us, 0.0), hi_speed)
            gap = command - expected[i]
            expected[i] += (up if gap > 0.0 else down) * gap
            past = self._model_past[i]
            slope = (expected[i] - past[(at - base) % ring]) / base
            past[at] = expected[i]
            new = v == v and sampled[i] > sample_t[i]  # v == v: not NaN
            if new:
                sample_t[i] = sampled[i]
                held_speed[i] = v
                loss[i] -= gain * loss[i]
            else:
                loss[i] += gain * (1.0 - loss[i])
                if not math.isfinite(v):
                    if replaced is None:
                        replaced = list(w)
                    replaced[i] = held_speed[i]
            if not judging:
                continue
            if t_us - sample_t[i] > self._esc_max_age_us:
                self._hand_over(f"rotor speed {i + 1} too old")
            if loss[i] > r.esc_loss_max:
                self._hand_over(f"rotor speed {i + 1} losing frames")
            if new:
                self._judge_sample(i, v, pi, first)
                if not first and self._lag[i].late(v, expected[i], slope) and not self._bus_late:
                    self._bus_late = True
                    self._declare("esc_late", WARNING, f"Rotor speed {i + 1} late: read ahead by the model")
            if self._bus_late:
                lag = self._lag[i].lag
                if lag > self._max_lag:
                    self._hand_over(f"rotor speed {i + 1} lagging")
                if replaced is None:
                    replaced = list(w)
                d = min(max(round(lag), 0), self._max_lag)
                replaced[i] = held_speed[i] + expected[i] - past[(at - d) % ring]
        return None if replaced is None else np.array(replaced)

    def _judge_sample(self, i: int, v: float, pi: float, first: bool) -> None:
        """The stale and implausible rules on motor `i`'s new sample `v` under PWM `pi`."""
        r = self.rules
        if v == self._prev_speed[i]:
            if self._pwm_at_change[i] != self._pwm_at_change[i]:  # NaN: no reference yet
                self._pwm_at_change[i] = pi
            elif abs(pi - self._pwm_at_change[i]) > r.stale_pwm_us:
                self._stale[i] += 1
                if self._stale[i] >= r.rotor_stale_ticks:
                    self._hand_over(f"rotor speed {i + 1} stale")
        else:
            self._stale[i] = 0
            # The first frame after arming was read under the PWM written before it (disarmed),
            # whatever the rotors were doing: its reading is judged from the first armed PWM.
            self._pwm_at_change[i] = math.nan if first else pi
            self._prev_speed[i] = v
        assert self._expected is not None
        if abs(v - self._expected[i]) > self._tolerance:
            self._rotor_score[i] += 1.0
            if self._rotor_score[i] >= r.rotor_fail_score:
                self._hand_over(f"rotor speed {i + 1} implausible")
        elif self._rotor_score[i]:
            self._rotor_score[i] = max(0.0, self._rotor_score[i] - r.recovery)


class LagFit:
    """One motor's lag fit (the module docstring): decaying sums of ṁ², ṁ·m, m², (m − w)·ṁ,
    (m − w)·m and (m − w)², the least-squares fit's normal equations and its misfit."""

    def __init__(self, rules: HealthRules, dt: float) -> None:
        self.rules = r = rules
        self.keep = keep = math.exp(-dt / r.esc_lag_window_s)
        self.limit = r.esc_max_lag_s / dt  # in ticks, the fit's unit
        self.motion = (r.esc_lag_motion * r.rotor_speed_max) ** 2 / (1.0 - keep)
        self.misfit = (r.esc_lag_misfit * r.rotor_speed_max) ** 2 / (1.0 - keep)
        self.sums = [0.0] * 6
        self.over = 0  # ticks in a row the fit has been late
        self.lag = 0.0  # the last lag the fit judged (ticks): how far a late bus is read ahead

    def late(self, v: float, m: float, dm: float) -> bool:
        """Add the sample `v` against the model's speed `m` and slope `dm`; True once the fit has put
        the telemetry more than the limit late for `esc_lag_ticks` ticks in a row."""
        keep, sums, r = self.keep, self.sums, self.rules
        miss = m - v
        sums[0] = sums[0] * keep + dm * dm
        sums[1] = sums[1] * keep + dm * m
        sums[2] = sums[2] * keep + m * m
        sums[3] = sums[3] * keep + miss * dm
        sums[4] = sums[4] * keep + miss * m
        sums[5] = sums[5] * keep + miss * miss
        det = sums[0] * sums[2] - sums[1] * sums[1]
        late = False
        if sums[0] > self.motion and det > 0.0:
            lag = (sums[3] * sums[2] - sums[1] * sums[4]) / det
            gain_error = (sums[0] * sums[4] - sums[1] * sums[3]) / det
            left_by_gain = sums[5] - sums[4] * sums[4] / sums[2]
            left = sums[5] - lag * sums[3] - gain_error * sums[4]
            if (abs(gain_error) < r.esc_lag_gain_max and left_by_gain > self.misfit
                    and left_by_gain - left > r.esc_lag_explains * left_by_gain):
                self.lag = lag  # a fit the delay explains; an early or still one can be anything
                late = lag > self.limit
        self.over = self.over + 1 if late else 0
        return self.over >= r.esc_lag_ticks
