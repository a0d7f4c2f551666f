"""PPO with extra terms in its minibatch loss: CAPS smoothness and a teacher anchor.

- CAPS (`training.caps`): λ_T·L_T + λ_S·L_S, action smoothness over a rollout's pairs.
- The teacher anchor: λ_A·‖π(s) − a_teacher(s)‖² averaged over a minibatch of the warm
  start's data (`training.warm_start`: states the teacher and the network flew, labelled
  by the teacher). PPO's own update may walk away from what the warm start fitted, and
  with domain randomisation its advantages cannot tell the airframes apart; the anchor
  keeps the network near its teacher wherever the reward gives no clear reason to leave
  it, as behaviour-cloning terms do in demonstration-augmented policy gradients (DAPG,
  Rajeswaran et al. 2018). The data are raw observations, normalised with the training
  VecNormalize's statistics of the moment, as the rollout's are.

Stable-Baselines3's `PPO.train` builds its loss inline, so the terms enter through the
optimiser: each minibatch's `zero_grad` is followed by the terms' backward, PPO's own
backward then accumulates onto it, and the gradient clip and step act on the sum,
exactly as if the terms were in PPO's loss.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch as th
from stable_baselines3 import PPO

from fcemu.training.caps import consecutive_pairs, mean_action, spatial_smoothness, temporal_smoothness


class RegularisedPPO(PPO):
    """PPO whose minibatch loss carries λ_T·L_T + λ_S·L_S + λ_A·L_A (module docstring); logs
    each term unweighted to TensorBoard (train/caps_temporal, train/caps_spatial, train/anchor)."""

    def __init__(self, *args: Any, caps_temporal: float = 0.0, caps_spatial: float = 0.0,
                 caps_sigma: float = 0.05, anchor: float = 0.0, **kwargs: Any) -> None:
        for name, value in (("caps_temporal", caps_temporal), ("caps_spatial", caps_spatial),
                            ("caps_sigma", caps_sigma), ("anchor", anchor)):
            if not (np.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be finite and >= 0, got {value}")
        self.caps_temporal, self.caps_spatial, self.caps_sigma = caps_temporal, caps_spatial, caps_sigma
        self.anchor = anchor
        self._anchor_data: tuple[np.ndarray, np.ndarray, Callable[[np.ndarray], np.ndarray]] | None = None
        super().__init__(*args, **kwargs)
        self._caps_gen = th.Generator(device=self.device)
        self._caps_gen.manual_seed(0 if self.seed is None else int(self.seed))
        self._anchor_rng = np.random.default_rng(self.seed)

    def set_anchor_data(self, raw_obs: np.ndarray, labels: np.ndarray,
                        normalise: Callable[[np.ndarray], np.ndarray]) -> None:
        """The teacher's states (raw observations) and actions; `normalise` maps raw
        observations to what the policy sees (the training VecNormalize's `normalize_obs`)."""
        if len(raw_obs) != len(labels) or labels.shape[1:] != self.action_space.shape:
            raise ValueError(f"anchor data: {len(raw_obs)} observations, labels of shape {labels.shape}")
        self._anchor_data = (raw_obs, labels, normalise)

    def _excluded_save_params(self) -> list[str]:
        # The anchor data are the warm start's whole dataset (hundreds of MB): not part of a checkpoint.
        return [*super()._excluded_save_params(), "_anchor_data"]

    def train(self) -> None:
        buffer = self.rollout_buffer
        caps = bool(self.caps_temporal or self.caps_spatial)
        if caps:  # an anchor-only run has no use for the rollout's pairs
            obs, next_obs = consecutive_pairs(buffer.observations, buffer.episode_starts)
            pairs = (th.as_tensor(obs, device=self.device), th.as_tensor(next_obs, device=self.device))
        optimizer = self.policy.optimizer
        zero_grad = optimizer.zero_grad
        terms: dict[str, list[float]] = {"caps_temporal": [], "caps_spatial": [], "anchor": []}

        def zero_grad_then_terms(set_to_none: bool = True) -> None:
            zero_grad(set_to_none=set_to_none)
            loss = th.zeros((), device=self.device)
            if caps:
                temporal, spatial = self.caps_losses(*pairs)
                terms["caps_temporal"].append(float(temporal.detach()))
                terms["caps_spatial"].append(float(spatial.detach()))
                loss = loss + self.caps_temporal * temporal + self.caps_spatial * spatial
            if self.anchor and self._anchor_data is not None:
                imitation = self.anchor_loss()
                terms["anchor"].append(float(imitation.detach()))
                loss = loss + self.anchor * imitation
            if loss.requires_grad:  # no pairs and no anchor: nothing to add
                loss.backward()

        optimizer.zero_grad = zero_grad_then_terms  # type: ignore[method-assign]
        try:
            super().train()
        finally:
            del optimizer.zero_grad  # the class's method again
        for name, values in terms.items():
            if values:
                self.logger.record(f"train/{name}", float(np.mean(values)))

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

    def anchor_loss(self) -> th.Tensor:
        """L_A: mean squared error of the policy's action against the teacher's, on a minibatch
        (PPO's batch size) of the anchor data, normalised as the policy sees it now."""
        assert self._anchor_data is not None
        raw, labels, normalise = self._anchor_data
        idx = self._anchor_rng.integers(len(raw), size=min(self.batch_size, len(raw)))
        obs = th.as_tensor(normalise(raw[idx]), dtype=th.float32, device=self.device)
        target = th.as_tensor(labels[idx], dtype=th.float32, device=self.device)
        return th.nn.functional.mse_loss(mean_action(self.policy, obs), target)
