"""A teacher that needs no training: the airframe's rate dynamics inverted, one tick at a time.

`fcemu fit` distils it into a policy (`fcemu distill inversion --airframe A`). It knows the
twin's model, read from the MuJoCo rig as `fcemu bound` reads it (`evaluation.bound.rig_constants`):
B, the angular acceleration per newton of each motor's thrust, the inertia, the thrust
coefficient, the top rotor speed and the motors' first-order lags. From what the policy
observes (rate error, rates, rotor speeds) it asks, per tick:

1. an angular acceleration that closes the rate error e as a second-order system with natural
   frequency ω = 1/T_c (T_c = `lag_multiple` × the motors' mean lag, shorter on the stronger of roll
   and pitch, longer on a yaw that rides its range: `axis_speeds`) and damping ζ (`damping`):
   α* = α_now + dt·(ω²·e − 2ζω·α_now), e predicted ahead over the loop's delay (the gyro's
   sample is a tick old, plus the airframe's gyro and ESC delays), less what the body adds by
   itself: the gyroscopic term −I⁻¹(Ω × IΩ) and, where the airframe has them, the rotors'
   gyroscopic moment and the rate damping (without them the law holds a steady error against the
   damping). Its α moves at most at ω²·e per second, so the motors are no rougher than the tuned
   PID's, and it overshoots a few percent where a first-order law (`damping` None:
   α* = (e − dt·α_now)/T_c) rises later, on an exponential tail, and so does its student.
   The α the law steers toward, ω·e/2ζ, is held under the braking curve √(2·J·|e|): no more
   than the motors can take back by the time the error closes (`braking`, `BRAKING_SHARE`). Where the rotors
   carry momentum, the yaw their speeds lend the body is counted in the yaw error (`lent_yaw`): they
   take it back as they return, and a law blind to it closes on a yaw rate that does not remain and
   rises late;
2. the thrusts that give it, within what each rotor can reach by the next tick (its lag from
   its present speed). Two allocations are tried, and the one whose torque lands nearer α*
   (roll and pitch weighted 10 to yaw's 1) is taken: the change of torque with roll and pitch
   served first and yaw from what is left (a share `yaw_first` of yaw's need served before them
   while they gather speed, none while they brake), and a step toward the thrusts that give α* at rest
   (roll and pitch first, yaw scaled into what is left of the output range), the torque's
   direction kept. Both keep the mix's collective at the outer loop's throttle, as the
   `throttle` action mapping does, so the teacher's outputs are ones a policy can give;
3. each rotor's command that reaches its thrust in one tick through its lag (the lag's inverse).

A student fitted to it by DAgger is the policy (`fcemu fit`; its figures: docs/results/fit.md).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from fcemu.firmware.action import action_to_pwm, pwm_to_action
from fcemu.firmware.observation import FIELDS, RATE, RATE_ERROR, ROTOR_SPEED, ObservationSpec
from fcemu.sim_bridge.airframe import Airframe, load_airframe
from fcemu.sim_bridge.plant import body_torque
from fcemu.sim_bridge.tasks import OMEGA_MAX

ROLL_PITCH_WEIGHT = 10.0  # the torque error's weight on roll and pitch against yaw's 1
# T_c = 1/ω in motor lags: a slower law rises late, a faster one shakes the motors for little Error
LAG_MULTIPLE = 0.5
DAMPING = 0.7  # ζ: about 4 % of overshoot (0.5: 15 %, more Error for a faster Rise)
# Yaw's speed where its authority cannot move its rate by a command's size within a motor lag: its
# large steps then ride the motors' range at any speed of the law, and a fast law only shakes the
# motors on its small ones. A yaw that can move that much in a lag keeps full speed: slowed, it rises late.
SATURATED_YAW_SPEED = 0.5
# The braking curve's jerk J, per axis: this share of its authority per motor lag. A law much faster
# than its motors asks for an α it cannot take back in time and overshoots; under the curve it
# overshoots less with smoother motors and the same Rise, while a much smaller share brakes early and
# rises late. The default; `fcemu fit` brings it in per airframe where that pays (docs/results/fit.md).
BRAKING_SHARE = 0.5
# A share of yaw's need served before roll and pitch while they gather speed: served after them, yaw
# waits on large mixed steps, and the rotors' momentum it then meets lends it late. Not while roll or
# pitch brake: there it only adds their overshoot. `fcemu fit` takes it where it pays on the tuning
# commands (docs/results/fit.md).
YAW_FIRST = 0.3
BISECTIONS = 30
SPEC_FIELDS = (*FIELDS, RATE)


@dataclass(frozen=True)
class InversionModel:
    """What the teacher knows of the twin (`evaluation.bound.RigConstants` and the PWM range)."""

    B: np.ndarray  # (3, 4) FRD rad/s² per newton of each motor's thrust
    inertia: np.ndarray  # (3,)
    kf: float
    w_max: float
    a_up: float
    a_down: float
    pwm_min: float
    pwm_max: float
    lag_s: float
    # What the airframe's effects add, zero on the nominal twin (`sim_bridge.plant.body_torque`):
    damping: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) N·m·s/rad, FRD torque −D·Ω
    rotor_inertia: float = 0.0  # kg·m² about each rotor's spin axis
    spin: np.ndarray = field(default_factory=lambda: np.ones(4))  # (4,) +1 counter-clockwise
    gyro_delay_ticks: int = 0  # ticks the gyro adds beside its own one
    esc_delay_ticks: int = 0  # ticks from a command to its motor

    @classmethod
    def of(cls, airframe: Airframe, dt: float = 0.001) -> InversionModel:
        from fcemu.evaluation.bound import rig_constants
        from fcemu.training.pid_tune import nominal

        rig = rig_constants(nominal(airframe), dt)
        m = airframe.motor
        return cls(rig.B, rig.inertia, rig.kf, rig.w_max, rig.a_up, rig.a_down, float(m.pwm_min),
                   float(m.pwm_max), 0.5 * (m.tau_up + m.tau_down),
                   np.asarray(airframe.rate_damping, dtype=float), float(airframe.rotor_inertia),
                   np.asarray(airframe.spin, dtype=float), int(airframe.gyro_delay_ticks),
                   int(airframe.esc_delay_ticks))

    def body_acceleration(self, rates: np.ndarray, rotor: np.ndarray) -> np.ndarray:
        """The body's own angular acceleration (n, 3) beside the thrusts' (`LawRows.body_acceleration`)."""
        return LawRows.of(self).body_acceleration(rates, rotor)


@dataclass(frozen=True)
class LawRows:
    """A model (`InversionModel`) as k rows that broadcast against n rows of signals (k is 1 or n): the
    teacher of one airframe is one row, the teacher of every twin's drawn airframe (`stack`) a row each."""

    B: np.ndarray  # (k, 3, 4)
    inertia: np.ndarray  # (k, 3)
    kf: np.ndarray  # (k, 1), as w_max, a_up, a_down, pwm_min, pwm_max
    w_max: np.ndarray
    a_up: np.ndarray
    a_down: np.ndarray
    pwm_min: np.ndarray
    pwm_max: np.ndarray
    damping: np.ndarray  # (k, 3)
    rotor_inertia: np.ndarray  # (k,)
    spin: np.ndarray  # (k, 4)

    @classmethod
    def of(cls, m: InversionModel) -> LawRows:
        column = [np.array([[float(getattr(m, name))]]) for name in ("kf", "w_max", "a_up", "a_down",
                                                                       "pwm_min", "pwm_max")]
        return cls(m.B[None], m.inertia[None], *column, np.asarray(m.damping, dtype=float)[None],
                   np.array([m.rotor_inertia]), np.asarray(m.spin, dtype=float)[None])

    @classmethod
    def stack(cls, rows: list[LawRows]) -> LawRows:
        return cls(*(np.concatenate([getattr(r, f.name) for r in rows]) for f in fields(cls)))

    def torque(self, thrust: np.ndarray) -> np.ndarray:
        """The angular acceleration (n, 3) the thrusts (n, 4) give: B·T per row."""
        return (self.B @ thrust[..., None])[..., 0]

    def body_acceleration(self, rates: np.ndarray, rotor: np.ndarray) -> np.ndarray:
        """The body's own angular acceleration (n, 3) beside the thrusts': gyroscopic −I⁻¹(Ω × IΩ)
        and the twin's other body torques (`plant.body_torque`: the rotors' gyroscopic moment and the
        rate damping; the rotors held, so no spin-up reaction)."""
        torque = body_torque(rates, rotor, rotor, self.damping, self.rotor_inertia, self.spin.T, dt=1.0)
        return (-np.cross(rates, self.inertia * rates) + torque) / self.inertia


def max_scale(lo: np.ndarray, hi: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Per row, the largest s in [0, 1] for which some collective c keeps lo ≤ s·delta + c ≤ hi on
    every motor (lo ≤ 0 ≤ hi, so s = 0 always holds): the pairs i, j bound s·(δ_j − δ_i) ≤ hi_j − lo_i."""
    dd = delta[..., None, :] - delta[..., :, None]
    room = hi[..., None, :] - lo[..., :, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        limit = np.where(dd > 1e-12, room / np.where(dd > 1e-12, dd, 1.0), np.inf)
    return np.clip(limit.min(axis=(-2, -1)), 0.0, 1.0)


def axis_speeds(m: InversionModel) -> np.ndarray:
    """Each axis's ω over the weaker of roll's and pitch's. Roll and pitch: √ of its authority (the
    largest angular acceleration its thrusts give) over the weaker's, so each asks the same thrust per
    unit error (its α moves at ω²·e): a stretched frame's long axis (the racer's pitch, 1.26 × its
    roll's authority) rises as early as a PID tuned for it. Yaw: `SATURATED_YAW_SPEED` where its
    authority moves its rate by less than the command bound in a motor lag, else roll's and pitch's."""
    from fcemu.evaluation.bound import authority

    a = authority(m.B, m.kf, m.w_max)
    yaw = SATURATED_YAW_SPEED if a[2] * m.lag_s < OMEGA_MAX else 1.0
    return np.array([*np.sqrt(a[:2] / a[:2].min()), yaw])


class InversionTeacher:
    """The teacher for `fcemu distill`: `act(obs)` on its own observation (`spec`), batched."""

    action_mapping = "throttle"

    def __init__(self, airframe: str | Airframe, lag_multiple: float = LAG_MULTIPLE,
                 throttle: float | None = None, dt: float = 0.001, damping: float | None = DAMPING,
                 reads_truth: bool = False, yaw_first: float = 0.0, braking: float = BRAKING_SHARE) -> None:
        """`reads_truth`: its observation is of the true rates (a privileged distillation's), so the
        error is predicted ahead over the ESC's delay only, not the gyro's too. `yaw_first`: the share
        of yaw's need served before roll and pitch while they gather speed (`YAW_FIRST`). `braking`:
        the braking curve's jerk in shares of each axis's authority per motor lag (`BRAKING_SHARE`)."""
        from fcemu.evaluation.bound import authority

        af = airframe if isinstance(airframe, Airframe) else load_airframe(airframe)
        if not lag_multiple > 0.0:
            raise ValueError(f"the inversion teacher's lag multiple must be > 0, got {lag_multiple}")
        if not 0.0 <= yaw_first <= 1.0:
            raise ValueError(f"the share of yaw served first must be in [0, 1], got {yaw_first}")
        if not braking > 0.0:
            raise ValueError(f"the braking share must be > 0, got {braking}")
        self.yaw_first, self.braking = float(yaw_first), float(braking)
        self.airframe = af.name
        self.model = m = InversionModel.of(af, dt)
        self.dt = dt
        self.time_constant = lag_multiple * m.lag_s / axis_speeds(m)  # (3,) roll, pitch, yaw
        self.braking_jerk = braking * authority(m.B, m.kf, m.w_max) / m.lag_s  # (3,) rad/s³
        self.damping = damping
        self.ahead_ticks = 1 + m.esc_delay_ticks + (0 if reads_truth else m.gyro_delay_ticks)
        self.throttle = float(af.hover_throttle() if throttle is None else throttle)
        self.spec = ObservationSpec(memory=1, fields=SPEC_FIELDS, max_rotor_speed=m.w_max)
        # [B; 1 1 1 1]⁻¹'s first three columns: a torque's thrusts with no change of the collective
        self._alloc = np.linalg.inv(np.vstack([m.B, np.ones(4)]))[:, :3]

    def law(self) -> Law:
        """The model and the law as rows (one: this airframe's), from the attributes as they are now."""
        return Law(LawRows.of(self.model), np.reshape(self.time_constant, (1, 3)),
                   np.reshape(self.braking_jerk, (1, 3)), np.full((1, 1), float(self.ahead_ticks)),
                   self._alloc[None], np.full((1, 1), self.throttle))

    def act(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float64)
        spec, columns = self.spec, self.spec.columns
        error = obs[:, columns[RATE_ERROR]] / spec.rate_scale
        rotor = obs[:, columns[ROTOR_SPEED]]  # shares of each row's own top speed, or scaled by the spec's
        rotor = rotor * self.law().rows.w_max if spec.per_airframe_rotor_speed \
            else rotor / spec.rotor_speed_scale
        rates = obs[:, columns[RATE]] / spec.rate_scale
        return pwm_to_action(self.action_mapping, self.pwm(error, rates, rotor))

    def pwm(self, error: np.ndarray, rates: np.ndarray, rotor: np.ndarray,
            throttle: float | np.ndarray | None = None) -> np.ndarray:
        """PWM (n, 4) for rate errors and rates (n, 3, FRD rad/s) and rotor speeds (n, 4, rad/s), at the
        outer loop's `throttle` (default: each airframe's hover throttle)."""
        law = self.law()
        m = law.rows
        if throttle is None:
            throttle = law.throttle
        else:
            throttle = np.reshape(np.asarray(throttle, dtype=float), (-1, 1))
        w = np.clip(rotor, 0.0, m.w_max)
        thrust = m.kf * w * w
        t_max = m.kf * m.w_max**2
        gyroscopic = m.body_acceleration(rates, w)
        from_thrust = m.torque(thrust)
        now = from_thrust + gyroscopic
        if np.any(m.rotor_inertia > 0.0):
            error = error + self.lent_yaw(error, rates, w, throttle, law)
        ahead = error - law.ahead_ticks * self.dt * now
        if self.damping is None:
            wanted = ahead / law.time_constant - gyroscopic  # from the thrusts, rad/s²
        else:
            omega = 1.0 / law.time_constant
            steer = np.minimum(omega * np.abs(ahead) / (2.0 * self.damping),
                               np.sqrt(2.0 * law.braking_jerk * np.abs(ahead)))
            wanted = now + self.dt * 2.0 * self.damping * omega * (np.sign(ahead) * steer - now) - gyroscopic
        lo = m.kf * (w * (1.0 - m.a_down)) ** 2 - thrust  # each rotor's reach by the next tick
        hi = m.kf * (w + m.a_up * (m.w_max - w)) ** 2 - thrust
        hover = m.kf * (throttle * m.w_max) ** 2 / 4.0  # (k, 1)
        candidates = [self._by_change(wanted - from_thrust, lo, hi, hover - thrust.mean(-1, keepdims=True),
                                      from_thrust, law),
                      self._toward_rest_target(wanted, thrust, lo, hi, hover, t_max, law)]
        weights = np.array([ROLL_PITCH_WEIGHT, ROLL_PITCH_WEIGHT, 1.0])
        misses = [(m.torque(thrust + c) - wanted) ** 2 @ weights for c in candidates]
        change = np.where((misses[0] <= misses[1])[:, None], candidates[0], candidates[1])
        change -= change.mean(-1, keepdims=True)
        command = self._at_throttle(w, thrust, change, lo, hi, throttle * m.w_max, t_max, m)
        return m.pwm_min + command / m.w_max * (m.pwm_max - m.pwm_min)

    def lent_yaw(self, error: np.ndarray, rates: np.ndarray, w: np.ndarray,
                 throttle: float | np.ndarray, law: Law | None = None) -> np.ndarray:
        """(n, 3), yaw only: the yaw rate the rotors' speeds lend the body beyond what they lend at the
        setpoint, J_r/I_zz·Σ s_i(ω_i − ω_i*), ω* the speeds whose thrusts hold the setpoint against the
        body's own torques. Rotors that spin up push the body round (`plant.body_torque`'s spin-up) and
        take it back as they return: counted in the error, the law closes on the rate that will remain."""
        law = law or self.law()
        m = law.rows
        throttle = np.reshape(np.asarray(throttle, dtype=float), (-1, 1))
        hold = -law.allocate(m.body_acceleration(rates + error, w))
        w_hold = np.sqrt(np.clip(m.kf * (throttle * m.w_max) ** 2 + hold, 0.0, None) / m.kf)
        lent = np.zeros_like(error)
        lent[:, 2] = m.rotor_inertia / m.inertia[:, 2] * ((w - w_hold) * m.spin).sum(-1)
        return lent

    def _by_change(self, needed: np.ndarray, lo: np.ndarray, hi: np.ndarray, collective: np.ndarray,
                   from_thrust: np.ndarray, law: Law | None = None) -> np.ndarray:
        """Thrust changes: `yaw_first` of yaw's share of `needed` (none where roll or pitch brakes,
        its need against the thrusts' present acceleration), then roll and pitch's, then the rest of
        yaw's, then the collective."""
        law = law or self.law()
        yaw = needed[:, 2:3] * law.alloc[..., 2]
        braking = (needed[:, :2] * from_thrust[:, :2] < 0.0).any(-1)
        share = np.where(braking, 0.0, self.yaw_first)
        first = (share * max_scale(lo, hi, yaw))[:, None] * yaw
        rp = law.allocate(needed, axes=2)
        change = first + max_scale(lo - first, hi - first, rp)[:, None] * rp
        rest = yaw - first
        change = change + max_scale(lo - change, hi - change, rest)[:, None] * rest
        c = np.clip(np.reshape(collective, -1), (lo - change).max(-1), (hi - change).min(-1))
        return change + c[:, None]

    def _toward_rest_target(self, wanted: np.ndarray, thrust: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                            hover: np.ndarray, t_max: np.ndarray, law: Law) -> np.ndarray:
        """Thrust changes toward the thrusts that give `wanted` (roll and pitch first, yaw into what
        is left of the range), as far as the reach allows with the torque's direction kept."""
        rp = law.allocate(wanted, axes=2)
        spread = np.ptp(rp, axis=-1)
        rp = rp * np.minimum(1.0, t_max[:, 0] / np.maximum(spread, 1e-12))[:, None]
        yaw = wanted[:, 2:3] * law.alloc[..., 2]
        mix = rp + max_scale(-rp, t_max - rp, yaw)[:, None] * yaw
        c = np.clip(hover[:, 0], -mix.min(-1), t_max[:, 0] - mix.max(-1))
        target = np.clip(c[:, None] + mix, 0.0, t_max)
        delta = target - thrust
        change = delta - delta.mean(-1, keepdims=True)
        change = max_scale(lo, hi, change)[:, None] * change
        c = np.clip(delta.mean(-1), (lo - change).max(-1), (hi - change).min(-1))
        return change + c[:, None]

    def _at_throttle(self, w: np.ndarray, thrust: np.ndarray, change: np.ndarray, lo: np.ndarray,
                     hi: np.ndarray, goal: np.ndarray, t_max: np.ndarray, m: LawRows) -> np.ndarray:
        """Rotor commands for the thrust change plus the collective (within reach) whose commands
        average the throttle's speed (`goal`, (k, 1)): the outer loop's collective, as the action
        mapping keeps it."""

        def commands(c: np.ndarray) -> np.ndarray:
            target = np.sqrt(np.clip(thrust + change + c[:, None], 0.0, t_max) / m.kf)
            gain = np.where(target > w, m.a_up, m.a_down)
            return np.clip(w + (target - w) / gain, 0.0, m.w_max)

        low, high = (lo - change).max(-1), (hi - change).min(-1)
        high = np.maximum(high, low)
        for _ in range(BISECTIONS):  # the mean command rises with c
            mid = 0.5 * (low + high)
            below = commands(mid).mean(-1) < goal[:, 0]
            low, high = np.where(below, mid, low), np.where(below, high, mid)
        return commands(0.5 * (low + high))


class DrawnInversionTeacher(InversionTeacher):
    """The teacher of each twin's airframe as drawn this episode, a row each (`follow`): on randomised
    twins it knows the delays, damping and motors of the twin it labels, not only the nominal's; on
    twins of a pool of quads (`EnvConfig.airframe_pool`), each one's airframe."""

    def __init__(self, make: Callable[[Airframe], InversionTeacher], base: Airframe) -> None:
        self.__dict__.update(make(base).__dict__)  # the nominal teacher's spec, law and options
        self._make, self._base = make, base
        self._env: Any = None
        self._laws: dict[Any, Law] = {}
        self._keys: list[Any] = []
        self._drawn: Law | None = None

    def follow(self, env: Any) -> None:
        """Label the rows of `env` (a `BatchedRateEnv`), each with its airframe as drawn from its base."""
        self._env, self._base = env, env.config.base_airframe
        if env.config.airframe_pool is not None:  # the twins observe shares of their own top speeds
            self.spec = replace(self.spec, per_airframe_rotor_speed=True)

    def act(self, obs: np.ndarray) -> np.ndarray:
        if self._env is not None and self.spec.per_airframe_rotor_speed:
            flown = self._env.episode_airframes  # looked up only for a quad not met before
            self._draw([id(a) for a in flown], lambda key: next(a for a in flown if id(a) == key), keep=True)
        elif self._env is not None:
            self._draw([tuple(sorted(f.items())) for f in self._env.episode_factors],
                       lambda key: self._base.scaled(**dict(key)) if key else self._base)
        return super().act(obs)

    def law(self) -> Law:
        return super().law() if self._drawn is None else self._drawn

    def _draw(self, keys: list[Any], airframe_of: Callable[[Any], Airframe], keep: bool = False) -> None:
        """The rows' laws for `keys`, each built once; `keep`: also the laws of airframes no twin flies
        now (a pool's, flown again), else only the present ones (drawn afresh each episode)."""
        if keys == self._keys:
            return
        for key in set(keys) - set(self._laws):
            self._laws[key] = self._make(airframe_of(key)).law()
        if not keep:
            self._laws = {key: self._laws[key] for key in keys}
        self._keys, self._drawn = keys, Law.stack([self._laws[key] for key in keys])


@dataclass(frozen=True)
class Law:
    """What `InversionTeacher.pwm` reads, as rows (`LawRows`): the model and, per row, the law's time
    constants and braking jerks (k, 3), the ticks it predicts ahead (k, 1), the allocation (k, 4, 3)
    (the first three columns of [B; 1 1 1 1]⁻¹: a torque's thrusts with no change of the collective)
    and the hover throttle (k, 1)."""

    rows: LawRows
    time_constant: np.ndarray
    braking_jerk: np.ndarray
    ahead_ticks: np.ndarray
    alloc: np.ndarray
    throttle: np.ndarray

    def allocate(self, accel: np.ndarray, axes: int = 3) -> np.ndarray:
        """The thrust changes (n, 4) that give the first `axes` axes of `accel` (n, 3)."""
        return (self.alloc[..., :axes] @ accel[:, :axes, None])[..., 0]

    @classmethod
    def stack(cls, laws: list[Law]) -> Law:
        return cls(LawRows.stack([w.rows for w in laws]),
                   *(np.concatenate([getattr(w, f.name) for w in laws]) for f in fields(cls)[1:]))


class InversionController:
    """The teacher flying one vehicle in the firmware's loop (`RateController`), as the fit's teacher
    stages fly it; `mapped`: its PWM through the action mapping and back, all a policy can give."""

    name = "inversion"

    def __init__(self, teacher: InversionTeacher, mapped: bool = False) -> None:
        self.teacher = teacher
        self.mapped = mapped

    def reset(self) -> None:
        pass

    def update(self, setpoint, frame, dt: float) -> np.ndarray:
        rates = np.asarray(frame.gyro, dtype=np.float64)[None]
        error = np.asarray(setpoint.rates, dtype=np.float64)[None] - rates
        rotor = np.asarray(frame.rotor_speed, dtype=np.float64)[None]
        pwm = self.teacher.pwm(error, rates, rotor, setpoint.throttle)
        if self.mapped:
            mapping = self.teacher.action_mapping
            pwm = action_to_pwm(mapping, pwm_to_action(mapping, pwm), setpoint.throttle)
        return pwm[0]
