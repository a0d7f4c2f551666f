"""Sensor health: what the flight controller makes of a gyro or ESC telemetry it can no longer trust.

`HealthMonitor.check(frame, pwm)` runs once per tick before the controller, on plain floats (a
few µs), and returns the frame the controller should read: the same object while nothing is
wrong. The rules, with `HealthRules`' defaults at 1 kHz (docs/DESIGN.md, "Faults and the
firmware's answers"):

- Gyro sample implausible: not finite, beyond the gyro's full scale (±2000 deg/s), or farther
  from the last good sample than `gyro_accel_max` (5000 rad/s², no airframe accelerates that
  fast) allows over the time since the last frame's sample: after a late tick the vehicle has had
  longer to turn, and judging by one tick would fail a good gyro. The sample is replaced by the
  last good one (a dropped or spiked sample costs one tick of old data). Each implausible sample
  adds 1 to a score, each good one takes `recovery` off; at `gyro_fail_score` the gyro has FAILED.
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

Each rule's judgment is a pure function in firmware/health_checks.py that returns the named fault
it finds; `HealthMonitor` keeps the state those functions are given and acts on what they return.
"""

from __future__ import annotations

import math

import numpy as np

from fcemu.firmware.health_checks import (
    Fault,
    HealthRules,
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
from fcemu.firmware.sensors import SensorFrame

_ZERO3 = np.zeros(3)


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
        self._loss_gain = 1.0 - math.exp(-dt / r.esc_loss_window_s)
        self._lag_base = max(1, round(r.esc_lag_base_s / dt))
        self._max_lag = read_ahead_ticks(r.esc_lag_base_s, r.esc_max_age_s, dt)
        self._speed_per_us = r.rotor_speed_max / (r.pwm_max - r.pwm_min)
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
        self._taken_us: int | None = None  # the last frame's gyro sample time
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

    # ---- acting on a fault ----
    def _declare(self, fault: Fault) -> None:
        if fault.verdict not in self.detected:
            self.detected[fault.verdict] = self.ticks
            self.outbox.append((fault.severity, fault.text))

    def _hand_over(self, fault: Fault | None) -> None:
        if fault is not None and self.policy_trusted and self.policy_flying:
            self.policy_trusted = False
            self.handover = fault.name
            self._declare(fault)

    def _fail_gyro(self, fault: Fault) -> None:
        self.gyro_failed = True
        self.failsafe = fault.name
        self._declare(fault)
        self._hand_over(handover(fault.name))

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
        taken = t_us if sampled is None else sampled
        if sampled is not None:
            fault = gyro_stale(t_us, sampled, r)
            if fault is not None:
                self._fail_gyro(fault)
                return _ZERO3
            fresh = self._gyro_t is None or sampled > self._gyro_t
            self._gyro_t = sampled
        last = self._last_good
        # The time since the last frame's sample, not since the last good one: a held run of bad
        # samples earns no room, or garbage would in time be taken for a turn.
        elapsed_s = max(taken - (taken if self._taken_us is None else self._taken_us), self._dt_us) * 1e-6
        self._taken_us = taken
        if not gyro_plausible(g, last, elapsed_s, r):
            self.glitches += 1
            self._gyro_score += 1.0
            fault = gyro_implausible(self._gyro_score, r)
            if fault is not None:
                self._fail_gyro(fault)
                return _ZERO3
            if self._held is None:
                self._held = np.array(last) if last is not None else _ZERO3
            return self._held
        self._gyro_score = max(0.0, self._gyro_score - r.recovery)
        if g == last:
            if fresh and torque_asked(p, r):
                self._stuck += 1
                fault = gyro_stuck(self._stuck, r)
                if fault is not None:
                    self._fail_gyro(fault)
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
            # A hand-over is latched: of the faults found here, the first in this order is the one said.
            fault = rotor_too_old(i, t_us, sample_t[i], r) or rotor_losing_frames(i, loss[i], r)
            if fault is not None:
                self._hand_over(fault)
            if new:
                self._judge_sample(i, v, pi, first)
                if not first:
                    self._lag[i].add(v, expected[i], slope)
                    over = self._lag[i].over  # judged as the other counts are, on the ticks it rises
                    if over and not self._bus_late and (fault := rotor_late(i, over, r)) is not None:
                        self._bus_late = True
                        self._declare(fault)
            if self._bus_late:
                lag = self._lag[i].lag
                self._hand_over(rotor_lagging(i, lag, self._max_lag))
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
            elif pwm_moved(pi, self._pwm_at_change[i], r):
                self._stale[i] += 1
                self._hand_over(rotor_stale(i, self._stale[i], r))
        else:
            self._stale[i] = 0
            # The first frame after arming was read under the PWM written before it (disarmed),
            # whatever the rotors were doing: its reading is judged from the first armed PWM.
            self._pwm_at_change[i] = math.nan if first else pi
            self._prev_speed[i] = v
        assert self._expected is not None
        if rotor_off_model(v, self._expected[i], r):
            self._rotor_score[i] += 1.0
            self._hand_over(rotor_implausible(i, self._rotor_score[i], r))
        elif self._rotor_score[i]:
            self._rotor_score[i] = max(0.0, self._rotor_score[i] - r.recovery)


class LagFit:
    """One motor's lag fit (the module docstring): decaying sums of ṁ², ṁ·m, m², (m − w)·ṁ,
    (m − w)·m and (m − w)², from which `explained_lag` solves the least-squares fit."""

    def __init__(self, rules: HealthRules, dt: float) -> None:
        self.rules = r = rules
        self.keep = keep = math.exp(-dt / r.esc_lag_window_s)
        self.limit = r.esc_max_lag_s / dt  # in ticks, the fit's unit
        self.motion = (r.esc_lag_motion * r.rotor_speed_max) ** 2 / (1.0 - keep)
        self.misfit = (r.esc_lag_misfit * r.rotor_speed_max) ** 2 / (1.0 - keep)
        self.sums = [0.0] * 6
        self.over = 0  # ticks in a row the fit has been late (`rotor_late` judges them)
        self.lag = 0.0  # the last lag the fit judged (ticks): how far a late bus is read ahead

    def add(self, v: float, m: float, dm: float) -> None:
        """Add the sample `v` against the model's speed `m` and slope `dm`, and refit."""
        keep, sums = self.keep, self.sums
        miss = m - v
        sums[0] = sums[0] * keep + dm * dm
        sums[1] = sums[1] * keep + dm * m
        sums[2] = sums[2] * keep + m * m
        sums[3] = sums[3] * keep + miss * dm
        sums[4] = sums[4] * keep + miss * m
        sums[5] = sums[5] * keep + miss * miss
        lag = explained_lag(sums, self.motion, self.misfit, self.rules)
        late = False
        if lag is not None:
            self.lag = lag
            late = lag > self.limit
        self.over = self.over + 1 if late else 0
