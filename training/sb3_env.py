"""A `BatchedRateEnv` as a Stable-Baselines3 VecEnv: what `fcemu train` steps."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnvIndices, VecEnvStepReturn

from fcemu.sim_bridge.env_config import EnvConfig
from fcemu.sim_bridge.vec_env import BatchedRateEnv


class SB3VecEnv(VecEnv):
    """A `BatchedRateEnv` as a Stable-Baselines3 VecEnv.

    `seed(s)` then `reset()` seeds copy i with s + i, as SB3's own VecEnvs do. Infos
    carry `TimeLimit.truncated` and, on episode ends, `terminal_observation`; wrap in
    `VecMonitor` for episode statistics. Attributes and methods are the batch's, shared
    by every copy: `get_attr` and `env_method` answer once per requested index.
    """

    def __init__(self, batch: BatchedRateEnv) -> None:
        self.batch = batch
        super().__init__(batch.num_envs, batch.single_observation_space, batch.single_action_space)
        self._actions = np.zeros((batch.num_envs, 4), dtype=np.float32)
        self._last_info: dict[str, Any] = {}

    def reset(self) -> np.ndarray:
        seeds = self._seeds if any(s is not None for s in self._seeds) else None
        obs, self._last_info = self.batch.reset(seed=seeds)
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> VecEnvStepReturn:
        obs, reward, terminated, truncated, info = self.batch.step(self._actions)
        self._last_info = info
        dones = terminated | truncated
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        for i in np.flatnonzero(dones):
            infos[i]["terminal_observation"] = info["final_obs"][i]
            infos[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
        return obs, reward.astype(np.float32), dones, infos

    @property
    def last_info(self) -> dict[str, Any]:
        """The batch's info arrays from the last reset or step (setpoint, rate, pwm, ...)."""
        return self._last_info

    def close(self) -> None:
        self.batch.close()

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        value = getattr(self.batch, attr_name)
        return [value for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        setattr(self.batch, attr_name, value)

    def env_method(self, method_name: str, *method_args: Any, indices: VecEnvIndices = None,
                   **method_kwargs: Any) -> list[Any]:
        result = getattr(self.batch, method_name)(*method_args, **method_kwargs)
        return [result for _ in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper],
                       indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]


def make_sb3_vec_env(n_envs: int, seed: int | None = None, nthread: int = 0, config: EnvConfig | None = None,
                     **options: Any) -> SB3VecEnv:
    """`SB3VecEnv(BatchedRateEnv(n_envs, config))` (or with EnvConfig's fields as keywords), seeded so
    copy i follows the single env seeded seed + i."""
    venv = SB3VecEnv(BatchedRateEnv(n_envs, config, nthread=nthread, **options))
    if seed is not None:
        venv.seed(seed)
    return venv
