"""The rate-control reward: one definition, built by both environments from their arguments.

Like Gymnasium's MuJoCo environments, the weights are constructor arguments
(`RateControlEnv(reward="unclipped", axis_weights=(1, 1, 2), action_rate_penalty=2)`) and
each term is reported in `info`; the terms add up to the reward:

- `reward_tracking`: the rate error. ``paper`` (Koch et al.):
  −clip(Σ|Ω* − Ω| / (3·Ω_max), 0, 1). ``unclipped``: −Σ w_axis·|Ω* − Ω| / (3·Ω_max);
  once a spinning vehicle passes the paper's clip every action scores the same and there
  is nothing to learn from, unclipped the way back always pays.
  With `relative_error` K (unclipped only), also −K·Σ w_axis·|Ω* − Ω| / (|e0| + 0.1 rad/s) / 3,
  e0 the axis's error when its command began: the error on the evaluation's Success scale
  (the settling error as a share of the step), where a small step's steady residual counts as
  much as a large step's, not fifteen times less.
- `reward_action_rate`: −action_rate_penalty · mean|Δu| over the four motors,
  u = (PWM − 1000)/1000 (zero on an episode's first step, which has no Δu), the
  output-oscillation term.

`info` also carries `paper_reward`, the paper's reward whatever is trained on (what the
evaluation compares), and `action_rate`, mean|Δu| before weighting.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from fcemu.sim_bridge.tasks import OMEGA_MAX, rate_reward

REWARDS = ("paper", "unclipped")
REWARD_TERMS = ("reward_tracking", "reward_action_rate", "paper_reward", "action_rate")  # info keys
UNWEIGHTED = (1.0, 1.0, 1.0)
RELATIVE_FLOOR = 0.1  # rad/s: the smallest step the evaluation judges (evaluation.metrics.MIN_E0)


def motor_output_rate(u: np.ndarray, previous: np.ndarray) -> np.ndarray:
    """Mean |Δu| over the four motors, u = (PWM − 1000)/1000; summed in a fixed order."""
    d = np.abs(u - previous)
    return (d[..., 0] + d[..., 1] + d[..., 2] + d[..., 3]) * 0.25


@dataclass(frozen=True)
class RateReward:
    """The reward with its weights; call it on one vehicle or a batch (any leading shape)."""

    kind: str = "paper"
    axis_weights: tuple[float, float, float] = UNWEIGHTED  # roll, pitch, yaw error (unclipped only)
    action_rate_penalty: float = 0.0
    omega_max: float = OMEGA_MAX
    relative_error: float = 0.0  # weight of the error relative to the command's step (unclipped only)

    def __post_init__(self) -> None:
        if self.kind not in REWARDS:
            raise ValueError(f"unknown reward {self.kind!r}; choose one of {REWARDS}")
        weights = tuple(float(w) for w in self.axis_weights)
        if len(weights) != 3 or not all(math.isfinite(w) and w >= 0.0 for w in weights):
            raise ValueError(f"axis_weights must be 3 finite weights >= 0, got {self.axis_weights!r}")
        if self.kind == "paper" and weights != UNWEIGHTED:
            raise ValueError("axis_weights weight the unclipped reward; the paper's reward is unweighted")
        if not (math.isfinite(self.action_rate_penalty) and self.action_rate_penalty >= 0.0):
            raise ValueError(f"action_rate_penalty must be finite and >= 0, got {self.action_rate_penalty}")
        if not (math.isfinite(self.relative_error) and self.relative_error >= 0.0):
            raise ValueError(f"relative_error must be finite and >= 0, got {self.relative_error}")
        if self.kind == "paper" and self.relative_error:
            raise ValueError("relative_error adds to the unclipped reward; the paper's has no such term")
        if not (math.isfinite(self.omega_max) and self.omega_max > 0.0):
            raise ValueError(f"omega_max must be > 0, got {self.omega_max}")
        object.__setattr__(self, "axis_weights", weights)

    def __call__(self, setpoint: np.ndarray, rate: np.ndarray, u: np.ndarray, previous_u: np.ndarray,
                 penalised: np.ndarray | None = None, step: np.ndarray | None = None
                 ) -> tuple[np.ndarray, dict[str, Any]]:
        """(reward, terms) for rates (..., 3) and motor outputs (..., 4).

        `previous_u` is the step before's u; on an episode's first step, u itself (Δu = 0).
        `penalised` (...,) bool: where the action-rate penalty applies (default: everywhere).
        `step` (..., 3): each axis's |e0|, the error when its command began (needed with
        `relative_error`).
        """
        paper = rate_reward(setpoint, rate, self.omega_max)
        if self.kind == "paper":
            tracking = paper
        else:
            e = np.abs(setpoint - rate)
            w = self.axis_weights
            scale = 1.0 / (3.0 * self.omega_max)
            tracking = -((w[0] * e[..., 0] + w[1] * e[..., 1] + w[2] * e[..., 2]) * scale)
            if self.relative_error:
                r = e / (np.asarray(step) + RELATIVE_FLOOR)
                tracking = tracking - (w[0] * r[..., 0] + w[1] * r[..., 1] + w[2] * r[..., 2]) * (
                    self.relative_error / 3.0)
        action_rate = motor_output_rate(u, previous_u)
        penalty = self.action_rate_penalty * action_rate
        if penalised is not None:
            penalty = np.where(penalised, penalty, 0.0)
        terms = {"reward_tracking": tracking, "reward_action_rate": -penalty, "paper_reward": paper,
                 "action_rate": action_rate}  # REWARD_TERMS
        return tracking - penalty, terms
