"""CAPS: PPO with action-smoothness regularisation (Mysore et al. 2021, "Regularizing Action
Policies for Smooth Control with Reinforcement Learning", ICRA).

Beside the reward's action-rate penalty (a cost on what the motors did), CAPS shapes the
policy itself: its mean action π(s) should change little from one state to the next
(temporal, ‖π(s_t) − π(s_{t+1})‖) and little under a small perturbation of the state
(spatial, ‖π(s) − π(s̃)‖, s̃ ~ N(s, σ²)). `training.regularised_ppo.RegularisedPPO` adds
λ_T·L_T + λ_S·L_S to PPO's minibatch loss. The CAPS minibatch is drawn from the same
rollout, its pairs (s_t, s_{t+1}) from consecutive steps of one environment, never
across an episode boundary. Observations are those the policy sees (after
VecNormalize), so σ is in normalised units.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th


def mean_action(policy: Any, obs: th.Tensor) -> th.Tensor:
    """The policy's deterministic action (the distribution's mode), differentiable."""
    return policy.get_distribution(obs).mode()


def temporal_smoothness(policy: Any, obs: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """L_T: mean ‖π(s_t) − π(s_{t+1})‖₂ over the pairs."""
    return th.linalg.vector_norm(mean_action(policy, obs) - mean_action(policy, next_obs), dim=-1).mean()


def spatial_smoothness(policy: Any, obs: th.Tensor, sigma: float, generator: th.Generator) -> th.Tensor:
    """L_S: mean ‖π(s) − π(s̃)‖₂, s̃ = s + σ·N(0, I)."""
    noise = th.randn(obs.shape, generator=generator, dtype=obs.dtype, device=obs.device)
    near = obs + sigma * noise
    return th.linalg.vector_norm(mean_action(policy, obs) - mean_action(policy, near), dim=-1).mean()


def consecutive_pairs(observations: np.ndarray, episode_starts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(s_t, s_{t+1}) of a rollout (steps, envs, obs) within episodes: s_{t+1} must not start one."""
    same_episode = episode_starts[1:] == 0.0  # (steps − 1, envs)
    return observations[:-1][same_episode], observations[1:][same_episode]
