"""GymFC's rate-control tasks as Gymnasium environments over the MuJoCo twin.

`RateControlEnv` flies the Iris on the ball-joint rig: each step applies one action for
one physics step (1 ms) and observes what the firmware's neural controller would see,
built by `firmware.observation` and mapped to PWM by `firmware.action`, so a policy
trained here flies unchanged in the firmware.

Per episode, in this order, the env draws from `np_random` (see `draw_episode`): the
setpoint (a command or a pulse schedule, `sim_bridge.tasks`), the throttle (throttle
mapping with a range), the airframe scale factors (`randomize`; with a `randomize_share`
below 1, first whether this episode draws them or flies the nominal airframe), the
twin's noise seed (when `noise` is enabled), whether it starts in flight (`inflight_share`)
and the seed of the ESC telemetry frames it loses (when some airframe loses any). The batched
environment (`sim_bridge.vec_env`) makes the same draws with the same code, which is what makes
the two bit-identical.

Step k (1..T) returns the observation and reward for the setpoint of sample k; the
reward (`sim_bridge.reward`, weights as constructor arguments, terms in `info`) uses the
gyro's noise-free reading (with noise off, exactly what the policy sees). Around the
physics both environments run the same `RateTask`: action to PWM before, observation,
reward and info after.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from fcemu.firmware.action import action_to_pwm, motor_output
from fcemu.firmware.observation import ObservationHistory, observe_step
from fcemu.sim_bridge.airframe import Airframe
from fcemu.sim_bridge.env_config import (
    DEFAULT_AIRFRAME,
    DEFAULT_EPISODE_S,
    RANDOMIZE_KEYS,
    TASKS,
    EnvConfig,
)
from fcemu.sim_bridge.randomization import Randomization
from fcemu.sim_bridge.tasks import draw_throttle, episodic_setpoint, pulse_schedule
from fcemu.sim_bridge.twin import Twin, hover_state

__all__ = ["DEFAULT_AIRFRAME", "DEFAULT_EPISODE_S", "RANDOMIZE_KEYS", "TASKS", "EnvConfig", "Episode",
           "RateControlEnv", "RateTask", "draw_episode", "with_options"]


def with_options(config: EnvConfig | None, options: dict[str, Any]) -> EnvConfig:
    """An environment's configuration: `config`, or `EnvConfig(**options)` (its fields as keywords).

    Not both: a built EnvConfig has resolved its defaults against its airframe (hover
    throttle, gyro noise), which other options would leave stale."""
    if config is None:
        return EnvConfig(**options)
    if not isinstance(config, EnvConfig):
        raise TypeError(f"config must be an EnvConfig, got {type(config).__name__} (options go by keyword)")
    if options:
        raise TypeError(f"give an EnvConfig or its fields as keywords, not both (got {sorted(options)})")
    return config


@dataclass(frozen=True)
class Episode:
    setpoints: np.ndarray  # (n_steps + 1, 3): sample k is the setpoint after step k
    throttle: float
    factors: dict[str, float] = field(default_factory=dict)  # airframe scale factors
    noise_seed: int | None = None
    in_flight: bool = False  # rotors at the throttle's speed, not at rest (`EnvConfig.inflight_share`)
    telemetry_seed: int | None = None  # which ESC telemetry frames are lost (`EnvConfig.loses_telemetry`)


def draw_episode(rng: np.random.Generator, cfg: EnvConfig) -> Episode:
    n = cfg.n_steps + 1
    if cfg.task == "episodic":
        setpoints = np.broadcast_to(episodic_setpoint(rng, cfg.omega_max), (n, 3))
    else:
        setpoints = pulse_schedule(rng, n, cfg.dt, cfg.omega_max, cfg.hold_s, cfg.rest_s)
    throttle = draw_throttle(rng, cfg.throttle) if cfg.action_mapping == "throttle" else 0.0
    if isinstance(cfg.randomize, Randomization):
        drawn = cfg.randomize_share >= 1.0 or rng.random() < cfg.randomize_share  # no extra draw at 1
        factors = cfg.randomize.draw(rng) if drawn else cfg.randomize.nominal()
    else:
        frac = cfg.randomize or {}
        factors = {k: float(rng.uniform(1.0 - frac[k], 1.0 + frac[k])) for k in RANDOMIZE_KEYS if k in frac}
    noise_seed = int(rng.integers(2**63)) if cfg.noisy else None
    in_flight = cfg.inflight_share > 0.0 and cfg.task == "episodic" and rng.random() < cfg.inflight_share
    telemetry_seed = int(rng.integers(2**63)) if cfg.loses_telemetry else None
    return Episode(setpoints, throttle, factors, noise_seed, bool(in_flight), telemetry_seed)


class RateTask:
    """The environment step around the physics, for one vehicle (batch shape ()) or a batch.

    Before the physics, the action's PWM (`firmware.action`); after it, the observation
    (`firmware.observation`, its history kept here), the reward and the info. Both
    `RateControlEnv` and `BatchedRateEnv` step through this, which keeps them bit-identical.
    """

    def __init__(self, cfg: EnvConfig, batch_shape: tuple[int, ...] = (), on_time_view: bool = False,
                 always: bool = False) -> None:
        self.config, self.spec, self.reward = cfg, cfg.observation_spec, cfg.rate_reward
        self.history = ObservationHistory(self.spec, batch_shape)
        # `on_time_view`: also the observation of the readings as sampled, before the gyro's delay and
        # the ESC bus, where some are late (`always`: whether or not they are, for a view of the truth):
        # a distillation teacher's (privileged) view
        keep = on_time_view and (always or cfg.late_sensors)
        self.on_time = ObservationHistory(self.spec, batch_shape) if keep else None
        self._previous_u = np.zeros((*batch_shape, 4))
        self._first = np.ones(batch_shape, dtype=bool)  # episode starts: no previous output
        self._any_first = True
        # the action-rate penalty's gate: how long each copy's setpoint has been held (ticks)
        self._gate_ticks = round(cfg.action_rate_after_s / cfg.dt) if cfg.action_rate_after_s else 0
        self._held = np.zeros(batch_shape, dtype=np.int64)
        self._held_setpoint = np.zeros((*batch_shape, 3))
        # the relative error's |e0|: each axis's error when its command began, and that command
        self._relative = bool(cfg.relative_error)
        self._step_size = np.zeros((*batch_shape, 3))
        self._command = np.zeros((*batch_shape, 3))
        # each copy's loop delay as its firmware is configured with it (ticks): the `loop_delay` field
        self.loop_delay = np.full(batch_shape, float(cfg.base_airframe.loop_delay_ticks))
        # Flying a pool of quads: each copy's rotor speeds × its reference's top speed / its own, so the
        # spec's scale (the reference's) observes them as shares of the copy's own top speed.
        self.rotor_gain = np.ones((*batch_shape, 1)) if cfg.airframe_pool else None

    def pwm(self, action: np.ndarray, throttle: np.ndarray | float) -> np.ndarray:
        return action_to_pwm(self.config.action_mapping, np.asarray(action, dtype=np.float32), throttle)

    def reset(self, setpoint: np.ndarray, gyro: np.ndarray, rotor_speed: np.ndarray,
              rows: np.ndarray | None = None, on_time: tuple[np.ndarray, np.ndarray] | None = None
              ) -> np.ndarray:
        """The first observation of a new episode; with a mask `rows`, of those copies (given theirs)."""
        self._any_first = True
        at = ... if rows is None else rows
        self._first[at] = True
        self._held[at] = 0
        self._held_setpoint[at] = setpoint
        if self._relative:
            self._command[at], self._step_size[at] = setpoint, np.abs(setpoint - gyro)
        delay = self.loop_delay if rows is None else self.loop_delay[rows]
        rotor_speed, on_time = self._as_shares(rotor_speed, on_time, rows)
        if self.on_time is not None:
            self._start(self.on_time, observe_step(self.spec, setpoint, *on_time, loop_delay=delay), rows)
        step = observe_step(self.spec, setpoint, gyro, rotor_speed, loop_delay=delay)
        return self._start(self.history, step, rows)

    def _as_shares(self, rotor_speed: np.ndarray, on_time: tuple[np.ndarray, np.ndarray] | None,
                   rows: np.ndarray | None = None) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
        """The rotor speeds (and the on-time view's) × `rotor_gain`, flying a pool; else as they are."""
        if self.rotor_gain is None:
            return rotor_speed, on_time
        gain = self.rotor_gain if rows is None else self.rotor_gain[rows]
        return rotor_speed * gain, None if on_time is None else (on_time[0], on_time[1] * gain)

    def _start(self, history: ObservationHistory, step: np.ndarray, rows: np.ndarray | None) -> np.ndarray:
        if rows is None:
            return history.reset(step)
        full = np.zeros((*self._first.shape, self.spec.step_size), dtype=np.float32)
        full[rows] = step
        return history.reset(full, rows)

    def on_time_observation(self) -> np.ndarray | None:
        """The observation of the readings as sampled (None: no input is ever late or lossy)."""
        return None if self.on_time is None else self.on_time.observation()

    def _settled(self, setpoint: np.ndarray) -> np.ndarray | None:
        """Where the setpoint has been held for `action_rate_after_s` (None: no gate)."""
        if not self._gate_ticks:
            return None
        held = (setpoint == self._held_setpoint).all(axis=-1)
        self._held = np.where(held, self._held + 1, 0)
        self._held_setpoint[...] = setpoint
        return self._held >= self._gate_ticks

    def _command_step(self, setpoint: np.ndarray, rate: np.ndarray) -> np.ndarray | None:
        """Each axis's |e0| for the relative error (None: no such term): the error on the step
        its command changed, held until it changes again."""
        if not self._relative:
            return None
        new = (setpoint != self._command).any(axis=-1, keepdims=True)
        self._step_size = np.where(new, np.abs(setpoint - rate), self._step_size)
        self._command = np.where(new, setpoint, self._command)
        return self._step_size

    def step(self, setpoint: np.ndarray, rate: np.ndarray, gyro: np.ndarray, rotor_speed: np.ndarray,
             pwm: np.ndarray, on_time: tuple[np.ndarray, np.ndarray] | None = None
             ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        """(observation, reward, info) after the physics step: `rate` is what the reward judges."""
        pwm = np.asarray(pwm, dtype=float)  # float32 actions give float32 PWM; Δu is float64
        u = motor_output(pwm)  # also the next observation's motor_output, as in flight
        if self._any_first:  # a first step has no Δu: its previous output is its own
            np.copyto(self._previous_u, u, where=self._first[..., None])
            self._first[...], self._any_first = False, False
        reward, terms = self.reward(setpoint, rate, u, self._previous_u, self._settled(setpoint),
                                    self._command_step(setpoint, rate))
        self._previous_u = u
        rotor_speed, on_time = self._as_shares(rotor_speed, on_time)
        obs = self.history.push(observe_step(self.spec, setpoint, gyro, rotor_speed, motor_output=u,
                                             loop_delay=self.loop_delay))
        if self.on_time is not None:
            self.on_time.push(observe_step(self.spec, setpoint, *on_time, motor_output=u,
                                           loop_delay=self.loop_delay))
        return obs, reward, {"setpoint": setpoint, "rate": rate, "gyro": gyro, "pwm": pwm, **terms}


class RateControlEnv(gym.Env[np.ndarray, np.ndarray]):
    """Track body-rate setpoints on the ball-joint rig with four motor commands.

    Observation: `firmware.observation` (rate error and rotor speeds, last `memory`
    steps). Action: a ∈ [-1, 1]^4 through `firmware.action` (`gymfc` or `throttle`).
    Reward (`sim_bridge.reward`): `reward` "paper" −clip(Σ|Ω* − Ω| / (3·Ω_max), 0, 1) or
    "unclipped" −Σ w·|Ω* − Ω| / (3·Ω_max) (w: `axis_weights`), − action_rate_penalty ·
    mean|Δu|; info reports each term (reward_tracking, reward_action_rate) and the paper's
    reward. Episodes are truncated after `episode_s`; they never terminate.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, config: EnvConfig | None = None, render_mode: str | None = None,
                 on_time_view: bool = False, **options: Any) -> None:
        """`config`, or EnvConfig's fields as keywords (`RateControlEnv(memory=3)`); `on_time_view`:
        keep `on_time_observation` too."""
        self.config = with_options(config, options)
        if self.config.airframe_pool is not None:
            raise ValueError("a pool of airframes is flown by the batched environment (BatchedRateEnv); "
                             "a single environment flies one airframe")
        self.obs_spec = self.config.observation_spec
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (self.obs_spec.size,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (4,), np.float32)
        self.render_mode = render_mode
        self._task = RateTask(self.config, on_time_view=on_time_view)
        self._n_steps = self.config.n_steps
        self._noisy = self.config.gyro_is_not_rate
        self._factors: dict[str, float] = {}
        self._set_twin(self.config.base_airframe)
        self._episode: Episode | None = None
        self._t = 0

    @property
    def twin(self) -> Twin:
        return self._twin

    @property
    def episode(self) -> Episode | None:
        return self._episode

    @property
    def on_time_observation(self) -> np.ndarray | None:
        """The observation had the gyro and the ESC bus been on time (None: not kept, or nothing late)."""
        return self._task.on_time_observation()

    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        ep = self._episode = draw_episode(self.np_random, self.config)
        if ep.factors != self._factors:  # a new airframe: a new model (cheap, once per episode)
            self._set_twin(self.config.base_airframe.scaled(**ep.factors))
            self._factors = ep.factors
        start = hover_state(self.config.base_airframe, ep.throttle) if ep.in_flight else None
        frame = self._twin.reset(seed=ep.noise_seed, state=start, telemetry_seed=ep.telemetry_seed)
        self._t = 0
        setpoint = ep.setpoints[0]
        obs = self._task.reset(setpoint, frame.gyro, frame.rotor_speed, None, self._twin.sampled)
        info = {"setpoint": setpoint.copy(), "rate": self._rate(frame.gyro), "gyro": frame.gyro,
                "throttle": ep.throttle, "factors": dict(ep.factors)}
        return obs, info

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._episode is None:
            raise RuntimeError("call reset() before step()")
        pwm = self._task.pwm(action, self._episode.throttle)
        frame = self._twin.step(pwm)
        self._t += 1
        setpoint = self._episode.setpoints[self._t].copy()
        obs, reward, info = self._task.step(setpoint, self._rate(frame.gyro), frame.gyro, frame.rotor_speed,
                                            pwm, self._twin.sampled)
        return obs, float(reward), False, self._t >= self._n_steps, info

    def _set_twin(self, airframe: Airframe) -> None:
        self._twin = Twin(airframe, "rig", self.config.episode_noise(airframe), self.config.dt)
        self._task.loop_delay[...] = airframe.loop_delay_ticks

    def _rate(self, gyro: np.ndarray) -> np.ndarray:
        """The rate the reward judges: the gyro's reading without vibration, noise or delay."""
        return self._twin.clean_gyro() if self._noisy else gyro


gym.register("fcemu/RateEpisodic-v0", entry_point="fcemu.sim_bridge.env:RateControlEnv",
             kwargs={"task": "episodic"})
gym.register("fcemu/RateContinuous-v0", entry_point="fcemu.sim_bridge.env:RateControlEnv",
             kwargs={"task": "continuous"})
