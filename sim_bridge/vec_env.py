"""Many twins stepped in one call: the rate-control task batched for training speed.

`BatchedRateEnv` runs N copies of `RateControlEnv` in lockstep. The physics state of
each copy is one row of an (N, nstate) array (MuJoCo's full physics state), and one
`mujoco.rollout` call steps all of them from those rows in C, on one shared MjModel
(or one per copy when mass, inertia or km are randomised: all have the same sizes).
The motors and sensors are the twin's own models (`sim_bridge.plant`) over the batch,
and the step around the physics is the single environment's (`sim_bridge.env.RateTask`,
batch-aware), so a batch and single environments agree to the last bit.

Seeding contract: `reset(seed=s)` seeds copy i with `s + i` (a list seeds each copy);
copy i then makes exactly the draws that `RateControlEnv(...).reset(seed=s + i)` and its
later unseeded resets make, in the same order (`sim_bridge.env.draw_episode`). So copy i
of a batch seeded with s follows the single env seeded with s + i, across auto-resets.

Auto-reset is same-step (what Stable-Baselines3 expects): the step that ends an episode
returns the first observation of the next one, and `info["final_obs"]` holds the last.
`fcemu.training.sb3_env.SB3VecEnv` adapts the batch to Stable-Baselines3.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any, ClassVar

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space
from mujoco import rollout

from fcemu.sim_bridge.airframe import FLU_FROM_FRD, Airframe, build_mjcf
from fcemu.sim_bridge.env import EnvConfig, RateTask, draw_episode, with_options
from fcemu.sim_bridge.plant import AirframeEffects, MotorModel
from fcemu.sim_bridge.sensor_model import NoiseStreams, SensorModel
from fcemu.sim_bridge.twin import Twin, hover_state

FULL_PHYSICS = mujoco.mjtState.mjSTATE_FULLPHYSICS.value
NOISE_BLOCK = 256  # steps of sensor noise drawn at a time per copy
MAX_DELAY_TICKS = 32  # the longest ESC, gyro or telemetry delay a copy's airframe may have
POOL_STREAM = 0x9001  # the second word of a copy's pool-draw seed: a stream apart from its episodes
CTRL_AND_TORQUE = mujoco.mjtState.mjSTATE_CTRL.value | mujoco.mjtState.mjSTATE_QFRC_APPLIED.value


class BatchedRateEnv(VectorEnv):
    """`n_envs` copies of `RateControlEnv(config)` (or of `RateControlEnv(**options)`) stepped together.

    `nthread` > 0 steps the physics on a MuJoCo thread pool (the results do not depend
    on it); `on_time_view` keeps `on_time_observation` too (`RateTask`), and with `truth_view` that
    view is the true rates and rotor speeds (no delay, loss, noise or vibration). Info holds batch
    arrays: setpoint, rate, gyro, pwm, the reward terms (`sim_bridge.reward.REWARD_TERMS`),
    and on episode ends final_obs with its mask _final_obs.
    """

    metadata: ClassVar[dict[str, Any]] = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, n_envs: int, config: EnvConfig | None = None, *, nthread: int = 0,
                 on_time_view: bool = False, truth_view: bool = False, **options: Any) -> None:
        if n_envs < 1:
            raise ValueError(f"n_envs must be >= 1, got {n_envs}")
        cfg = self.config = with_options(config, options)
        self.num_envs = n = n_envs
        self.obs_spec = cfg.observation_spec
        self.single_observation_space = gym.spaces.Box(-np.inf, np.inf, (self.obs_spec.size,), np.float32)
        self.single_action_space = gym.spaces.Box(-1.0, 1.0, (4,), np.float32)
        self.observation_space = batch_space(self.single_observation_space, n)
        self.action_space = batch_space(self.single_action_space, n)
        self.render_mode = None

        twin = Twin(cfg.base_airframe, "rig", None, cfg.dt)  # the reference for state and constants
        self._model = twin.model
        self._state0 = np.empty(mujoco.mj_stateSize(self._model, FULL_PHYSICS))
        mujoco.mj_getState(self._model, twin.data, self._state0, FULL_PHYSICS)
        self._sens0 = twin.data.sensordata.copy()
        g = self._model.sensor("gyro").adr[0]
        self._gyro = slice(g, g + 3)
        self._motors, self._sensors = twin.motors, SensorModel(cfg.noise)
        self._fx = AirframeEffects(cfg.base_airframe, cfg.dt, (n,), MAX_DELAY_TICKS)
        nq, nv = self._model.nq, self._model.nv
        self._qvel = slice(1 + nq, 1 + nq + 3)  # FULLPHYSICS: time, qpos, qvel, ...
        self._control = np.zeros((n, 1, 4 + nv))  # ctrl, qfrc_applied: with body torques
        # Each episode's airframe from a pool of quads (`EnvConfig.airframe_pool`), its MjModel built once.
        self._pool_airframes = cfg.airframe_pool or ()
        self._pool_models: dict[int, mujoco.MjModel] = {}
        self._per_model = bool(set(cfg.randomize or {}) & {"mass", "inertia", "km"} or self._pool_airframes)

        self._n_steps, self._noisy = cfg.n_steps, cfg.noisy
        self._rows = np.arange(n)
        self._models = [self._model] * n
        # Per copy, what a randomised airframe changes in the motors and the gyro noise.
        self._kf = np.full((n, 1), self._motors.kf)
        per_copy = {"speed_per_us": np.full((n, 1), self._motors.speed_per_us)} if self._pool_airframes \
            else {}
        self._motors = replace(self._motors, alpha_up=np.full((n, 1), self._motors.alpha_up),
                               alpha_down=np.full((n, 1), self._motors.alpha_down), **per_copy)
        self._gyro_std = np.full((n, 1), cfg.noise.gyro_std if cfg.noise is not None else 0.0)
        self._state = np.tile(self._state0, (n, 1))
        self._next = np.empty((n, 1, self._state0.size))
        self._sens = np.tile(self._sens0, (n, 1, 1))
        self._ctrl = np.zeros((n, 1, 4))
        self._omega = np.zeros((n, 4))
        self._sched = np.zeros((n, self._n_steps + 1, 3))
        self._t = np.zeros(n, dtype=np.int64)
        self._throttle = np.zeros(n)
        self._truth_view = truth_view and on_time_view
        self._task = RateTask(cfg, (n,), on_time_view, always=self._truth_view)
        self._rngs = [np.random.default_rng() for _ in range(n)]
        # which airframe of the pool each copy flies, drawn apart from `draw_episode`'s draws
        self._picks = [np.random.default_rng() for _ in range(n)]
        self._flown = [cfg.base_airframe] * n
        self._factors: list[dict[str, float]] = [{} for _ in range(n)]
        self._noise = NoiseStreams(n, SensorModel.DRAWS, NOISE_BLOCK) if self._noisy else None
        self._lost = NoiseStreams(n, 4, NOISE_BLOCK, uniform=True) if cfg.loses_telemetry else None
        self._pool = rollout.Rollout(nthread=nthread)
        self._datas = [mujoco.MjData(self._model) for _ in range(max(1, nthread))]
        self._scratch = self._datas[0]

    def reset(self, *, seed: int | Sequence[int | None] | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Start every copy over; `seed` int s seeds copy i with s + i, a list seeds each copy."""
        seeds = [seed + i for i in range(self.num_envs)] if isinstance(seed, int) else seed
        if seeds is not None:
            if len(seeds) != self.num_envs:
                raise ValueError(f"got {len(seeds)} seeds for {self.num_envs} environments")
            for i, s in enumerate(seeds):
                if s is not None:
                    self._rngs[i] = np.random.default_rng(s)
                    self._picks[i] = np.random.default_rng([s, POOL_STREAM])
        obs = self._reset_rows(np.ones(self.num_envs, dtype=bool))
        info = {"setpoint": self._sched[:, 0].copy(), "throttle": self._throttle.copy()}
        return obs, info

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
        pwm = self._task.pwm(actions, self._throttle)
        fx = self._fx
        before = self._omega
        self._omega, self._ctrl[:, 0] = self._motors.step(before, fx.command(pwm), self._kf, fx.speed_scale())
        control, spec = self._ctrl, mujoco.mjtState.mjSTATE_CTRL.value
        if fx.torques:
            rates = self._state[:, self._qvel] * FLU_FROM_FRD
            control, spec = self._control, CTRL_AND_TORQUE
            control[:, 0, :4] = self._ctrl[:, 0]
            control[:, 0, 4:7] = fx.torque(rates, self._omega, before, self._ctrl[:, 0]) * FLU_FROM_FRD
        self._pool.rollout(self._models, self._datas, self._state, control, control_spec=spec,
                           skip_checks=True, nstep=1, state=self._next, sensordata=self._sens,
                           initial_warmstart=None,
                           chunk_size=max(1, self.num_envs // (2 * len(self._datas))))
        self._state[:] = self._next[:, 0]
        fx.advance(self._omega, self._ctrl[:, 0])
        self._t += 1
        rate = self._sens[:, 0, self._gyro] * FLU_FROM_FRD
        gyro, rotor, sent = self._measure(rate, self._rows, False)
        setpoint = self._sched[self._rows, self._t]
        obs, reward, info = self._task.step(setpoint, rate, gyro, rotor, pwm, sent)
        truncated = self._t >= self._n_steps
        if truncated.any():
            info["final_obs"], info["_final_obs"] = obs.copy(), truncated.copy()
            obs[truncated] = self._reset_rows(truncated)[truncated]
        return obs, reward, np.zeros(self.num_envs, dtype=bool), truncated, info

    def close_extras(self, **kwargs: Any) -> None:
        self._pool.close()

    @property
    def current_setpoint(self) -> np.ndarray:
        """Each copy's setpoint (n, 3) for the observation it last returned."""
        return self._sched[self._rows, self._t]

    @property
    def on_time_observation(self) -> np.ndarray | None:
        """Each copy's observation had its gyro and ESC bus been on time (None: not kept, or nothing late)."""
        return self._task.on_time_observation()

    @property
    def current_throttle(self) -> np.ndarray:
        """Each copy's collective this episode (n,)."""
        return self._throttle.copy()

    @property
    def episode_airframes(self) -> list[Airframe]:
        """The airframe each copy flies this episode: the pool's draw, else the reference."""
        return list(self._flown)

    @property
    def episode_factors(self) -> list[dict[str, float]]:
        """Each copy's airframe scale factors for its current episode."""
        return [dict(f) for f in self._factors]

    def _reset_rows(self, rows: np.ndarray) -> np.ndarray:
        """Draw new episodes for the copies in the mask `rows`; returns the observation batch."""
        idx = np.flatnonzero(rows)
        self._state[idx] = self._state0
        self._sens[idx, 0] = self._sens0
        self._omega[idx] = 0.0
        self._t[idx] = 0
        start_pwm = np.full((idx.size, 4), self._motors.pwm_min)
        for row, i in enumerate(idx):
            ep = draw_episode(self._rngs[i], self.config)
            self._sched[i] = ep.setpoints
            self._throttle[i] = ep.throttle
            self._factors[i] = ep.factors
            if self._pool_airframes:
                pool = self._pool_airframes
                k = int(self._picks[i].integers(len(pool))) if len(pool) > 1 else 0
                self._set_airframe(i, pool[k], k)
                # the throttle as far from the copy's hover as from the reference's
                reference = self.config.base_airframe.hover_throttle()
                self._throttle[i] = pool[k].hover_throttle() * (ep.throttle / reference)
            elif ep.factors:
                self._set_airframe(i, self.config.base_airframe.scaled(**ep.factors))
            if self._noise is not None:
                self._noise.reseed(i, ep.noise_seed)
            if self._lost is not None:
                self._lost.reseed(i, ep.telemetry_seed)
            if ep.in_flight:  # as RateControlEnv's twin starts from `hover_state`
                motor = self._flown[i].motor
                self._omega[i] = hover_state(self._flown[i], self._throttle[i]).rotor_speed
                start_pwm[row] = motor.pwm_for_rotor_speed(self._omega[i])
        self._fx.reset(start_pwm, idx)
        gyro, rotor, sent = self._measure(self._sens[idx, 0, self._gyro] * FLU_FROM_FRD, idx, True)
        return self._task.reset(self._sched[idx, 0], gyro, rotor, rows, sent)

    def _set_airframe(self, i: int, airframe: Airframe, pool_index: int | None = None) -> None:
        self._flown[i] = airframe
        self._kf[i] = airframe.motor.kf
        lag = MotorModel.from_spec(airframe.motor, self.config.dt)  # the single twin's arithmetic
        self._motors.alpha_up[i], self._motors.alpha_down[i] = lag.alpha_up, lag.alpha_down
        if pool_index is not None:
            self._motors.speed_per_us[i] = lag.speed_per_us
            top = self.config.base_airframe.motor.max_rotor_speed
            self._task.rotor_gain[i] = top / airframe.motor.max_rotor_speed
        if self.config.draws_gyro_noise:
            self._gyro_std[i] = airframe.gyro_noise_std
        self._fx.set_row(i, airframe)
        self._task.loop_delay[i] = airframe.loop_delay_ticks
        if not self._per_model:
            return
        model = self._pool_models.get(pool_index) if pool_index is not None else None
        if model is None:
            model = mujoco.MjModel.from_xml_string(build_mjcf(airframe, "rig", self.config.dt))
            if pool_index is not None:
                self._pool_models[pool_index] = model
        self._models[i] = model
        d = self._scratch  # the same sizes as every model in the batch
        mujoco.mj_setState(model, d, self._state0, FULL_PHYSICS)
        d.ctrl[:] = 0.0
        mujoco.mj_forward(model, d)
        self._sens[i, 0] = d.sensordata  # the twin's first frame after reset

    def _measure(self, rate: np.ndarray, idx: np.ndarray, reset: bool
                 ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """What the gyro and rotor speed sensors of copies `idx` report, from each copy's noise stream,
        and both as sampled (before the gyro's delay and the ESC bus).

        `reset`: the copies start an episode (the gyro and telemetry delay lines start over).
        """
        omega = self._omega[idx]
        fx = self._fx
        gyro = fx.gyro_truth(rate, omega, idx) if fx.shakes else rate
        if self._noise is not None:
            gyro, _, omega = self._sensors.read(gyro, None, omega, self._noise.next(idx),
                                                self._gyro_std[idx] if self.config.draws_gyro_noise else None)
        sent = (rate, omega) if self._truth_view else (gyro, omega)
        if fx.gyro_delays:
            gyro = fx.gyro_delayed(gyro, None if not reset else idx, reset)
        if fx.telemetry_effects:
            lost_draw = None if reset or self._lost is None else self._lost.next(idx)
            omega, _ = fx.telemetry(omega, lost_draw, None if not reset else idx, reset)
        return gyro, omega, sent
