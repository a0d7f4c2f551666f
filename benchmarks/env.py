"""Environment throughput for `fcemu bench sim`: env_steps_per_s and vec_env_steps_per_s.

Both step with pre-drawn random actions in [-1, 1] (no policy in the loop), include the
episode resets, and time `seconds` of wall clock after a short warm-up. The action sets
come in ± pairs: a constant bias would spin the undamped rig up without bound over a long
continuous episode, until MuJoCo resets the unstable state.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from fcemu.sim_bridge.env import RateControlEnv
from fcemu.sim_bridge.vec_env import BatchedRateEnv

_ACTION_SETS = 8


def _actions(seed: int, shape: tuple[int, ...]) -> np.ndarray:
    half = np.random.default_rng(seed).uniform(-1, 1, (_ACTION_SETS, *shape)).astype(np.float32)
    return np.concatenate([half, -half])


def _steps_per_s(step_block: Callable[[], int], seconds: float) -> float:
    """Steps per second of repeated `step_block()` calls (each returns the steps it took) after a warm-up."""

    def run(until: float) -> int:
        steps = 0
        while time.perf_counter() < until:
            steps += step_block()
        return steps

    run(time.perf_counter() + min(0.2, seconds / 10))
    start = time.perf_counter()
    steps = run(start + seconds)
    return steps / (time.perf_counter() - start)


def env_steps_per_s(seconds: float = 2.0, seed: int = 0, **env_kwargs: Any) -> float:
    """Steps per second of one `RateControlEnv` (episodic task unless told otherwise)."""
    env = RateControlEnv(**env_kwargs)
    actions = _actions(seed, (4,))
    env.reset(seed=seed)

    def step_block() -> int:
        for a in actions:
            if env.step(a)[3]:
                env.reset()
        return len(actions)

    return _steps_per_s(step_block, seconds)


def vec_env_steps_per_s(n_envs: int = 128, seconds: float = 2.0, seed: int = 0, nthread: int = 0,
                        **env_kwargs: Any) -> float:
    """Aggregate environment steps per second of a `BatchedRateEnv` of `n_envs` copies."""
    env = BatchedRateEnv(n_envs, nthread=nthread, **env_kwargs)
    actions = _actions(seed, (n_envs, 4))
    env.reset(seed=seed)

    def step_block() -> int:
        for a in actions:
            env.step(a)  # auto-resets finished copies
        return len(actions) * n_envs

    try:
        return _steps_per_s(step_block, seconds)
    finally:
        env.close()


if __name__ == "__main__":
    print(f"env_steps_per_s {env_steps_per_s():,.0f}")
    for n in (16, 64, 128, 256, 512):
        print(f"vec_env_steps_per_s n_envs={n} {vec_env_steps_per_s(n):,.0f}")
