"""GymFC's rate-control tasks as Gymnasium environments over the MuJoCo twin.

`RateControlEnv` flies the Iris on the ball-joint rig: each step applies one action for
one physics step (1 ms) and observes what the firmware's neural controller would see,
built by `firmware.observation` and mapped to PWM by `firmware.action`, so a policy
trained here flies unchanged in the firmware.

Per episode, in this order, the env draws from `np_random` (see `draw_episode`): the
setpoint (a command or a pulse schedule, `sim_bridge.tasks`), the throttle (throttle
mapping with a range), the airframe scale factors (`randomize`; with a `randomize_share`
below 1, first whether this episode draws them or flies the nominal airframe), and the
twin's noise seed (when `noise` is enabled). The batched environment (`sim_bridge.vec_env`) makes the same
draws with the same code, which is what makes the two bit-identical.

Step k (1..T) returns the observation and reward for the setpoint of sample k; the
reward (`sim_bridge.reward`, weights as constructor arguments, terms in `info`) uses the
gyro's noise-free reading (with noise off, exactly what the policy sees). Around the
physics both environments run the same `RateTask`: action to PWM before, observation,
reward and info after.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from fcemu.firmware.action import ACTION_MAPPINGS, DEFAULT_ACTION_MAPPING, action_to_pwm, motor_output
from fcemu.firmware.observation import (
    DEFAULT_LEAK,
    DEFAULT_RMS_LEAK,
    FIELDS,
    ObservationHistory,
    ObservationSpec,
    observe_step,
)
from fcemu.sim_bridge.airframe import Airframe, load_airframe
from fcemu.sim_bridge.plant import SensorNoise
from fcemu.sim_bridge.randomization import Randomization, load_randomization
from fcemu.sim_bridge.reward import UNWEIGHTED, RateReward
from fcemu.sim_bridge.tasks import (
    HOLD_S,
    OMEGA_MAX,
    REST_S,
    TRAINING_TASKS,
    draw_throttle,
    episodic_setpoint,
    pulse_schedule,
)
from fcemu.sim_bridge.twin import Twin

TASKS = TRAINING_TASKS
RANDOMIZE_KEYS = ("mass", "inertia", "kf", "km")  # also the draw order
DEFAULT_EPISODE_S = {"episodic": 1.0, "continuous": 10.0}


@dataclass(frozen=True)
class EnvConfig:
    """Everything that defines a task; shared by the single and the batched environment."""

    task: str = "episodic"
    memory: int = 1
    action_mapping: str = DEFAULT_ACTION_MAPPING
    throttle: float | tuple[float, float] | None = None  # None: the airframe's hover throttle
    episode_s: float | None = None  # None: 1 s episodic, 10 s continuous
    noise: SensorNoise | None = None
    # key -> ± fraction, or ranges (a `sim_bridge.randomization` file, e.g. "iris"); redrawn per episode
    randomize: Mapping[str, float] | Randomization | str | Path | None = None
    omega_max: float = OMEGA_MAX
    action_rate_penalty: float = 0.0
    airframe: Airframe | str = "iris"
    dt: float = 0.001
    hold_s: tuple[float, float] = HOLD_S
    rest_s: tuple[float, float] | None = REST_S
    obs_fields: tuple[str, ...] = FIELDS  # firmware.observation fields, e.g. + rate_error_integral
    reward: str = "paper"  # sim_bridge.reward.REWARDS
    axis_weights: tuple[float, float, float] = UNWEIGHTED  # roll, pitch, yaw error; unclipped only
    integral_leak: float = DEFAULT_LEAK  # λ of rate_error_integral, when it is a field
    rms_leak: float = DEFAULT_RMS_LEAK  # μ of rate_error_rms, when it is a field
    randomize_share: float = 1.0  # with ranges: the share of episodes drawn from them, the rest nominal
    # the action-rate penalty only once the setpoint has been held this long (s): a settled
    # response must be quiet, a step may be sharp (0: every step, Neuroflight's penalty)
    action_rate_after_s: float = 0.0

    def __post_init__(self) -> None:
        if self.task not in TASKS:
            raise ValueError(f"unknown task {self.task!r}; choose one of {TASKS}")
        if self.action_mapping not in ACTION_MAPPINGS:
            raise ValueError(f"unknown action mapping {self.action_mapping!r}; known: {ACTION_MAPPINGS}")
        if isinstance(self.randomize, str | Path):
            object.__setattr__(self, "randomize", load_randomization(self.randomize))
        if not isinstance(self.randomize, Randomization):
            unknown = set(self.randomize or {}) - set(RANDOMIZE_KEYS)
            if unknown:
                raise ValueError(f"cannot randomise {sorted(unknown)}; known: {RANDOMIZE_KEYS}")
            if any(not 0.0 <= f < 1.0 for f in (self.randomize or {}).values()):
                raise ValueError(
                    f"randomisation fractions must be in [0, 1), got {dict(self.randomize or {})}")
        if not 0.0 <= self.randomize_share <= 1.0:
            raise ValueError(f"the randomised share of episodes must be in [0, 1], "
                             f"got {self.randomize_share}")
        if self.randomize_share < 1.0 and not isinstance(self.randomize, Randomization):
            raise ValueError("a randomised share below 1 needs randomisation ranges (e.g. randomize='iris')")
        if not isinstance(self.airframe, Airframe):
            object.__setattr__(self, "airframe", load_airframe(self.airframe))
        if isinstance(self.randomize, Randomization):
            self.randomize.check_airframe(self.airframe)
        if self.noise is None and self.base_airframe.gyro_noise_std:  # the airframe's own gyro noise
            object.__setattr__(self, "noise", SensorNoise(gyro_std=self.base_airframe.gyro_noise_std))
        if self.throttle is None:
            object.__setattr__(self, "throttle", self.base_airframe.hover_throttle())
        elif isinstance(self.throttle, list):
            object.__setattr__(self, "throttle", tuple(self.throttle))
        if self.n_steps < 1:
            raise ValueError(f"episode_s={self.episode_s} is shorter than one step of {self.dt} s")
        object.__setattr__(self, "axis_weights", self.rate_reward.axis_weights)  # validates the reward
        if not (math.isfinite(self.action_rate_after_s) and self.action_rate_after_s >= 0.0):
            raise ValueError(f"action_rate_after_s must be finite and >= 0, got {self.action_rate_after_s}")

    @property
    def base_airframe(self) -> Airframe:
        assert isinstance(self.airframe, Airframe)
        return self.airframe

    @property
    def n_steps(self) -> int:
        return round((self.episode_s or DEFAULT_EPISODE_S[self.task]) / self.dt)

    @property
    def observation_spec(self) -> ObservationSpec:
        return ObservationSpec(memory=self.memory, fields=tuple(self.obs_fields),
                               integral_leak=self.integral_leak, rms_leak=self.rms_leak)

    @property
    def noisy(self) -> bool:
        """Whether an episode draws sensor noise: the configured noise, or a randomised gyro noise."""
        return (self.noise is not None and self.noise.enabled) or self.draws_gyro_noise

    @property
    def draws_gyro_noise(self) -> bool:
        """The randomisation draws each episode's gyro noise (it replaces `noise.gyro_std`)."""
        return isinstance(self.randomize, Randomization) and self.randomize.draws_gyro_noise

    @property
    def gyro_is_not_rate(self) -> bool:
        """Whether some episode's gyro may read other than the rate: noise, vibration or delay."""
        drawn = isinstance(self.randomize, Randomization) and self.randomize.draws_gyro_effects
        return self.noisy or self.base_airframe.gyro_effects or drawn

    def episode_noise(self, airframe: Airframe) -> SensorNoise | None:
        """The sensor noise of an episode flying `airframe` (a draw of the randomisation)."""
        if not self.draws_gyro_noise:
            return self.noise
        return replace(self.noise or SensorNoise(), gyro_std=airframe.gyro_noise_std)

    @property
    def rate_reward(self) -> RateReward:
        return RateReward(self.reward, self.axis_weights, self.action_rate_penalty, self.omega_max)


@dataclass(frozen=True)
class Episode:
    setpoints: np.ndarray  # (n_steps + 1, 3): sample k is the setpoint after step k
    throttle: float
    factors: dict[str, float] = field(default_factory=dict)  # airframe scale factors
    noise_seed: int | None = None


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
    return Episode(setpoints, throttle, factors, noise_seed)


class RateTask:
    """The environment step around the physics, for one vehicle (batch shape ()) or a batch.

    Before the physics, the action's PWM (`firmware.action`); after it, the observation
    (`firmware.observation`, its history kept here), the reward and the info. Both
    `RateControlEnv` and `BatchedRateEnv` step through this, which keeps them bit-identical.
    """

    def __init__(self, cfg: EnvConfig, batch_shape: tuple[int, ...] = ()) -> None:
        self.config, self.spec, self.reward = cfg, cfg.observation_spec, cfg.rate_reward
        self.history = ObservationHistory(self.spec, batch_shape)
        self._previous_u = np.zeros((*batch_shape, 4))
        self._first = np.ones(batch_shape, dtype=bool)  # episode starts: no previous output
        self._any_first = True
        # the action-rate penalty's gate: how long each copy's setpoint has been held (ticks)
        self._gate_ticks = round(cfg.action_rate_after_s / cfg.dt) if cfg.action_rate_after_s else 0
        self._held = np.zeros(batch_shape, dtype=np.int64)
        self._held_setpoint = np.zeros((*batch_shape, 3))

    def pwm(self, action: np.ndarray, throttle: np.ndarray | float) -> np.ndarray:
        return action_to_pwm(self.config.action_mapping, np.asarray(action, dtype=np.float32), throttle)

    def reset(self, setpoint: np.ndarray, gyro: np.ndarray, rotor_speed: np.ndarray,
              rows: np.ndarray | None = None) -> np.ndarray:
        """The first observation of a new episode; with a mask `rows`, of those copies (given theirs)."""
        step = observe_step(self.spec, setpoint, gyro, rotor_speed)
        self._any_first = True
        if rows is None:
            self._first[...] = True
            self._held[...] = 0
            self._held_setpoint[...] = setpoint
            return self.history.reset(step)
        self._first[rows] = True
        self._held[rows] = 0
        self._held_setpoint[rows] = setpoint
        full = np.zeros((*self._first.shape, self.spec.step_size), dtype=np.float32)
        full[rows] = step
        return self.history.reset(full, rows)

    def _settled(self, setpoint: np.ndarray) -> np.ndarray | None:
        """Where the setpoint has been held for `action_rate_after_s` (None: no gate)."""
        if not self._gate_ticks:
            return None
        held = (setpoint == self._held_setpoint).all(axis=-1)
        self._held = np.where(held, self._held + 1, 0)
        self._held_setpoint[...] = setpoint
        return self._held >= self._gate_ticks

    def step(self, setpoint: np.ndarray, rate: np.ndarray, gyro: np.ndarray, rotor_speed: np.ndarray,
             pwm: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        """(observation, reward, info) after the physics step: `rate` is what the reward judges."""
        pwm = np.asarray(pwm, dtype=float)  # float32 actions give float32 PWM; Δu is float64
        u = motor_output(pwm)  # also the next observation's motor_output, as in flight
        if self._any_first:  # a first step has no Δu: its previous output is its own
            np.copyto(self._previous_u, u, where=self._first[..., None])
            self._first[...], self._any_first = False, False
        reward, terms = self.reward(setpoint, rate, u, self._previous_u, self._settled(setpoint))
        self._previous_u = u
        obs = self.history.push(observe_step(self.spec, setpoint, gyro, rotor_speed, motor_output=u))
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

    def __init__(self, task: str = "episodic", memory: int = 1, action_mapping: str = DEFAULT_ACTION_MAPPING,
                 throttle: float | tuple[float, float] | None = None, episode_s: float | None = None,
                 noise: SensorNoise | None = None,
                 randomize: Mapping[str, float] | Randomization | str | Path | None = None,
                 omega_max: float = OMEGA_MAX, action_rate_penalty: float = 0.0,
                 airframe: Airframe | str = "iris", dt: float = 0.001,
                 render_mode: str | None = None, obs_fields: tuple[str, ...] = FIELDS,
                 reward: str = "paper", axis_weights: tuple[float, float, float] = UNWEIGHTED,
                 integral_leak: float = DEFAULT_LEAK, randomize_share: float = 1.0,
                 action_rate_after_s: float = 0.0, rms_leak: float = DEFAULT_RMS_LEAK) -> None:
        self.config = EnvConfig(task, memory, action_mapping, throttle, episode_s, noise, randomize,
                                omega_max, action_rate_penalty, airframe, dt, obs_fields=tuple(obs_fields),
                                reward=reward, axis_weights=tuple(axis_weights),  # type: ignore[arg-type]
                                integral_leak=integral_leak, randomize_share=randomize_share,
                                action_rate_after_s=action_rate_after_s, rms_leak=rms_leak)
        self.obs_spec = self.config.observation_spec
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (self.obs_spec.size,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (4,), np.float32)
        self.render_mode = render_mode
        self._task = RateTask(self.config)
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

    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        ep = self._episode = draw_episode(self.np_random, self.config)
        if ep.factors != self._factors:  # a new airframe: a new model (cheap, once per episode)
            self._set_twin(self.config.base_airframe.scaled(**ep.factors))
            self._factors = ep.factors
        frame = self._twin.reset(seed=ep.noise_seed)
        self._t = 0
        setpoint = ep.setpoints[0]
        obs = self._task.reset(setpoint, frame.gyro, frame.rotor_speed)
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
                                            pwm)
        return obs, float(reward), False, self._t >= self._n_steps, info

    def _set_twin(self, airframe: Airframe) -> None:
        self._twin = Twin(airframe, "rig", self.config.episode_noise(airframe), self.config.dt)

    def _rate(self, gyro: np.ndarray) -> np.ndarray:
        """The rate the reward judges: the gyro's reading without vibration, noise or delay."""
        return self._twin.clean_gyro() if self._noisy else gyro


gym.register("fcemu/RateEpisodic-v0", entry_point="fcemu.sim_bridge.env:RateControlEnv",
             kwargs={"task": "episodic"})
gym.register("fcemu/RateContinuous-v0", entry_point="fcemu.sim_bridge.env:RateControlEnv",
             kwargs={"task": "continuous"})
