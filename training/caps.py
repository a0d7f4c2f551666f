"""CAPS: PPO with action-smoothness regularisation (Mysore et al. 2021, "Regularizing Action
Policies for Smooth Control with Reinforcement Learning", ICRA).

Beside the reward's action-rate penalty (a cost on what the motors did), CAPS shapes the
policy itself: its mean action π(s) should change little from one state to the next
(temporal, ‖π(s_t) − π(s_{t+1})‖) and little under a small perturbation of the state
(spatial, ‖π(s) − π(s̃)‖, s̃ ~ N(s, σ²)). `CapsPPO` adds λ_T·L_T + λ_S·L_S to PPO's
minibatch loss. Stable-Baselines3's `PPO.train` builds that loss inline, so the terms
enter through the optimiser: each minibatch's `zero_grad` is followed by the CAPS
backward, PPO's own backward then accumulates onto it, and the gradient clip and step
act on the sum, exactly as if the terms were in PPO's loss. The CAPS minibatch is drawn
from the same rollout, its pairs (s_t, s_{t+1}) from consecutive steps of one
environment, never across an episode boundary. Observations are those the policy sees
(after VecNormalize), so σ is in normalised units.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from stable_baselines3 import PPO


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


class CapsPPO(PPO):
    """PPO whose minibatch loss carries λ_T·L_T + λ_S·L_S (module docstring); logs both terms
    (train/caps_temporal, train/caps_spatial, unweighted) to TensorBoard."""

    def __init__(self, *args: Any, caps_temporal: float = 0.0, caps_spatial: float = 0.0,
                 caps_sigma: float = 0.05, **kwargs: Any) -> None:
        for name, value in (("caps_temporal", caps_temporal), ("caps_spatial", caps_spatial),
                            ("caps_sigma", caps_sigma)):
            if not (np.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be finite and >= 0, got {value}")
        self.caps_temporal, self.caps_spatial, self.caps_sigma = caps_temporal, caps_spatial, caps_sigma
        super().__init__(*args, **kwargs)
        self._caps_gen = th.Generator(device=self.device)
        self._caps_gen.manual_seed(0 if self.seed is None else int(self.seed))

    def train(self) -> None:
        buffer = self.rollout_buffer
        obs, next_obs = consecutive_pairs(buffer.observations, buffer.episode_starts)
        pairs = (th.as_tensor(obs, device=self.device), th.as_tensor(next_obs, device=self.device))
        optimizer = self.policy.optimizer
        zero_grad = optimizer.zero_grad
        terms: dict[str, list[float]] = {"temporal": [], "spatial": []}

        def zero_grad_then_caps(set_to_none: bool = True) -> None:
            zero_grad(set_to_none=set_to_none)
            temporal, spatial = self.caps_losses(*pairs)
            terms["temporal"].append(float(temporal.detach()))
            terms["spatial"].append(float(spatial.detach()))
            loss = self.caps_temporal * temporal + self.caps_spatial * spatial
            if loss.requires_grad:  # a rollout of one step per environment has no pairs: nothing to add
                loss.backward()

        optimizer.zero_grad = zero_grad_then_caps  # type: ignore[method-assign]
        try:
            super().train()
        finally:
            del optimizer.zero_grad  # the class's method again
        for name, values in terms.items():
            if values:
                self.logger.record(f"train/caps_{name}", float(np.mean(values)))

    def caps_losses(self, obs: th.Tensor, next_obs: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """(L_T, L_S) on a minibatch (PPO's batch size) drawn from the pairs `obs`, `next_obs`."""
        if len(obs) == 0:
            zero = th.zeros((), device=self.device)
            return zero, zero
        idx = th.randint(len(obs), (min(self.batch_size, len(obs)),), generator=self._caps_gen,
                         device=obs.device)
        s, s_next = obs[idx], next_obs[idx]
        return (temporal_smoothness(self.policy, s, s_next),
                spatial_smoothness(self.policy, s, self.caps_sigma, self._caps_gen))
