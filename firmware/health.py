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
- Gyro FAILED (latched until the next arming): the controller reads zero rates from then on
  (it flies on its setpoint alone), the policy hands over to the PID, and `failsafe` asks the
  vehicle for LAND; said once.
- Rotor speed absent (any non-finite ESC reading): the policy's input is incomplete, it hands
  over to the PID at once (1 tick). Rotor speed stale: a motor's reading bit-identical for
  `rotor_stale_ticks` ticks while its PWM moved more than `stale_pwm_us` from where it was when
  the reading last changed. Rotor speed implausible: a reading farther than `rotor_tolerance`
  × the top speed from a first-order model of the commanded speed, scored as the gyro's, at
  `rotor_fail_score`. Each hands the policy over to the PID (latched until the next arming) and
  is said once; the PID does not read rotor speed, so the vehicle flies on. While the PID
  flies (`policy_flying` False, set by the loop each tick) there is nothing to hand over and
  nothing is said about rotor speed.
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
    motor_tau_s: float = field(kw_only=True)  # the speed model's time constant
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

    @classmethod
    def for_airframe(cls, airframe: AirframeSpec, **thresholds: float) -> HealthRules:
        """The rules for `airframe`: its top rotor speed and PWM range, a speed model between its
        motors' spin-up and spin-down time constants; `thresholds` replace the defaults above."""
        return cls(rotor_speed_max=airframe.max_rotor_speed, pwm_min=airframe.pwm_min,
                   pwm_max=airframe.pwm_max, **thresholds,
                   motor_tau_s=0.5 * (airframe.motor_tau_up + airframe.motor_tau_down))


class HealthMonitor:
    """The rules above for one vehicle; `detected` maps each verdict to the tick it was reached."""

    def __init__(self, rules: HealthRules, dt: float = 0.001) -> None:
        self.rules = r = rules
        self._keep_per_us = math.exp(-1e-6 / r.motor_tau_s)  # the model's decay per µs of sensor time
        self._dt_us = round(dt * 1e6)
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
        gyro = self._check_gyro(frame.gyro.tolist(), p)
        self._check_rotors(frame.rotor_speed.tolist(), p, frame.t_us)
        return frame if gyro is None else frame._replace(gyro=gyro)

    def _check_gyro(self, g: list[float], p: list[float]) -> np.ndarray | None:
        r = self.rules
        if self.gyro_failed:
            return _ZERO3
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
            if max(p) - min(p) > r.torque_spread_us:
                self._stuck += 1
                if self._stuck >= r.gyro_stuck_ticks:
                    self._fail_gyro("stuck")
                    return _ZERO3
        else:
            self._stuck = 0
        self._last_good = g
        self._held = None
        return None

    def _check_rotors(self, w: list[float], p: list[float], t_us: int) -> None:
        r = self.rules
        expected = self._expected
        if expected is None:
            expected = self._expected = [v if math.isfinite(v) else 0.0 for v in w]
        # The model advances by the frames' own clock: ticks the loop skipped moved the rotors too.
        first = self._t_us is None
        elapsed = self._dt_us if first else min(max(t_us - self._t_us, 0), 100_000)
        self._t_us = t_us
        alpha = 1.0 - self._keep_per_us ** elapsed
        per_us, lo = self._speed_per_us, r.pwm_min
        hi_speed = r.rotor_speed_max
        for i in range(4):
            v, pi = w[i], p[i]
            command = min(max((pi - lo) * per_us, 0.0), hi_speed)
            expected[i] += alpha * (command - expected[i])
            if not math.isfinite(v):
                self._hand_over(f"rotor speed {i + 1} absent")
                continue
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
            if abs(v - expected[i]) > self._tolerance:
                self._rotor_score[i] += 1.0
                if self._rotor_score[i] >= r.rotor_fail_score:
                    self._hand_over(f"rotor speed {i + 1} implausible")
            elif self._rotor_score[i]:
                self._rotor_score[i] = max(0.0, self._rotor_score[i] - r.recovery)
