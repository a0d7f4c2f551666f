"""GymFC's rate-control tasks as Gymnasium environments over the MuJoCo twin.

`RateControlEnv` flies the Iris on the ball-joint rig: each step applies one action for
one physics step (1 ms) and observes what the firmware's neural controller would see,
built by `firmware.observation` and mapped to PWM by `firmware.action`, so a policy
trained here flies unchanged in the firmware.

Per episode, in this order, the env draws from `np_random` (see `draw_episode`): the
setpoint (a command or a pulse schedule, `sim_bridge.tasks`), the throttle (throttle
mapping with a range), the airframe scale factors (`randomize`), and the twin's noise seed
(when `noise` is enabled). The batched environment (`sim_bridge.vec_env`) makes the same
draws with the same code, which is what makes the two bit-identical.

Step k (1..T) returns the observation and reward for the setpoint of sample k; the
reward uses the gyro's noise-free reading (with noise off, exactly what the policy sees).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from firmware.action import ACTION_MAPPINGS, PWM_MIN, PWM_SPAN, action_to_pwm
from firmware.observation import FIELDS, ObservationHistory, ObservationSpec, observe_step
from sim_bridge.airframe import FLU_FROM_FRD, Airframe, load_airframe
from sim_bridge.randomization import Randomization, load_randomization
from sim_bridge.tasks import (
    HOLD_S,
    OMEGA_MAX,
    REST_S,
    TRAINING_TASKS,
    draw_throttle,
    episodic_setpoint,
    pulse_schedule,
    rate_reward,
)
from sim_bridge.twin import SensorNoise, Twin

TASKS = TRAINING_TASKS
RANDOMIZE_KEYS = ("mass", "inertia", "kf", "km")  # also the draw order
DEFAULT_EPISODE_S = {"episodic": 1.0, "continuous": 10.0}


@dataclass(frozen=True)
class EnvConfig:
    """Everything that defines a task; shared by the single and the batched environment."""

    task: str = "episodic"
    memory: int = 1
    action_mapping: str = "gymfc"
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
        if not isinstance(self.airframe, Airframe):
            object.__setattr__(self, "airframe", load_airframe(self.airframe))
        if isinstance(self.randomize, Randomization):
            self.randomize.check_airframe(self.airframe)
        if self.throttle is None:
            hover = (self.base_airframe.hover_pwm() - PWM_MIN) / PWM_SPAN
            object.__setattr__(self, "throttle", hover)
        elif isinstance(self.throttle, list):
            object.__setattr__(self, "throttle", tuple(self.throttle))
        if self.n_steps < 1:
            raise ValueError(f"episode_s={self.episode_s} is shorter than one step of {self.dt} s")

    @property
    def base_airframe(self) -> Airframe:
        assert isinstance(self.airframe, Airframe)
        return self.airframe

    @property
    def n_steps(self) -> int:
        return round((self.episode_s or DEFAULT_EPISODE_S[self.task]) / self.dt)

    @property
    def observation_spec(self) -> ObservationSpec:
        return ObservationSpec(memory=self.memory, fields=tuple(self.obs_fields))

    @property
    def noisy(self) -> bool:
        return self.noise is not None and self.noise.enabled


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
        factors = cfg.randomize.draw(rng)
    else:
        frac = cfg.randomize or {}
        factors = {k: float(rng.uniform(1.0 - frac[k], 1.0 + frac[k])) for k in RANDOMIZE_KEYS if k in frac}
    noise_seed = int(rng.integers(2**63)) if cfg.noisy else None
    return Episode(setpoints, throttle, factors, noise_seed)


def motor_output_rate(u: np.ndarray, previous: np.ndarray) -> np.ndarray:
    """Mean |Δu| over the four motors, u = (PWM − 1000)/1000; summed in a fixed order."""
    d = np.abs(u - previous)
    return (d[..., 0] + d[..., 1] + d[..., 2] + d[..., 3]) * 0.25


class RateControlEnv(gym.Env[np.ndarray, np.ndarray]):
    """Track body-rate setpoints on the ball-joint rig with four motor commands.

    Observation: `firmware.observation` (rate error and rotor speeds, last `memory`
    steps). Action: a ∈ [-1, 1]^4 through `firmware.action` (`gymfc` or `throttle`).
    Reward: −clip(Σ|Ω* − Ω| / (3·Ω_max), 0, 1) − action_rate_penalty · mean|Δu|.
    Episodes are truncated after `episode_s`; they never terminate.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, task: str = "episodic", memory: int = 1, action_mapping: str = "gymfc",
                 throttle: float | tuple[float, float] | None = None, episode_s: float | None = None,
                 noise: SensorNoise | None = None,
                 randomize: Mapping[str, float] | Randomization | str | Path | None = None,
                 omega_max: float = OMEGA_MAX, action_rate_penalty: float = 0.0,
                 airframe: Airframe | str = "iris", dt: float = 0.001,
                 render_mode: str | None = None, obs_fields: tuple[str, ...] = FIELDS) -> None:
        self.config = EnvConfig(task, memory, action_mapping, throttle, episode_s, noise, randomize,
                                omega_max, action_rate_penalty, airframe, dt, obs_fields=tuple(obs_fields))
        self.obs_spec = self.config.observation_spec
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (self.obs_spec.size,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (4,), np.float32)
        self.render_mode = render_mode
        self._history = ObservationHistory(self.obs_spec)
        self._n_steps, self._noisy = self.config.n_steps, self.config.noisy
        self._factors: dict[str, float] = {}
        self._set_twin(self.config.base_airframe)
        self._episode: Episode | None = None
        self._t = 0
        self._prev_u: np.ndarray | None = None

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
        self._t, self._prev_u = 0, None
        setpoint = ep.setpoints[0]
        obs = self._history.reset(observe_step(self.obs_spec, setpoint, frame.gyro, frame.rotor_speed))
        info = {"setpoint": setpoint.copy(), "rate": self._rate(frame.gyro), "gyro": frame.gyro,
                "throttle": ep.throttle, "factors": dict(ep.factors)}
        return obs, info

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._episode is None:
            raise RuntimeError("call reset() before step()")
        action = np.asarray(action, dtype=np.float32)
        pwm = action_to_pwm(self.config.action_mapping, action, self._episode.throttle)
        frame = self._twin.step(pwm)
        pwm = np.asarray(pwm, dtype=float)  # float32 actions give float32 PWM; Δu is float64
        self._t += 1
        setpoint = self._episode.setpoints[self._t]
        rate = self._rate(frame.gyro)
        paper_reward = float(rate_reward(setpoint, rate, self.config.omega_max))
        u = (pwm - PWM_MIN) / PWM_SPAN
        action_rate = 0.0 if self._prev_u is None else float(motor_output_rate(u, self._prev_u))
        self._prev_u = u
        reward = paper_reward - self.config.action_rate_penalty * action_rate
        obs = self._history.push(observe_step(self.obs_spec, setpoint, frame.gyro, frame.rotor_speed))
        info = {"setpoint": setpoint.copy(), "rate": rate, "gyro": frame.gyro,
                "pwm": pwm, "paper_reward": paper_reward,
                "action_rate": action_rate}
        return obs, reward, False, self._t >= self._n_steps, info

    def _set_twin(self, airframe: Airframe) -> None:
        self._twin = Twin(airframe, "rig", self.config.noise, self.config.dt)
        adr = self._twin.model.sensor("gyro").adr[0]
        self._gyro_clean = self._twin.data.sensordata[adr:adr + 3]

    def _rate(self, gyro: np.ndarray) -> np.ndarray:
        """The rate the reward judges: the gyro's reading without noise or bias."""
        return self._gyro_clean * FLU_FROM_FRD if self._noisy else gyro


gym.register("fcemu/RateEpisodic-v0", entry_point="sim_bridge.env:RateControlEnv",
             kwargs={"task": "episodic"})
gym.register("fcemu/RateContinuous-v0", entry_point="sim_bridge.env:RateControlEnv",
             kwargs={"task": "continuous"})
