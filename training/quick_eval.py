"""The in-training evaluation: the paper's metrics for a torch policy on the batched twin.

`run_controller` flies an exported ONNX file through the firmware loop, one episode at a
time (~40 ms each); during training we want a verdict in about a second. This flies the
deterministic policy, with its observation normalisation, on `BatchedRateEnv` (the same
twin arithmetic, bit for bit) and builds the same `Traces`, so `compute_metrics` scores
it exactly as `fcemu eval` would. Copy i flies the command `episodic_commands(seed + i, 1)`,
so the PID reference is `run_controller(pid, EvalConfig(episodes=1, seed=seed + i))`. Both
fly the training airframe as it is, without randomisation; the trace holds the body rate
(the gyro's reading without vibration, noise or delay), as `fcemu eval` records it.

`fcemu.evaluation.bar.bar_verdict` judges it against the best PID preset by the deployable bar;
`selection_key` ranks in-training evaluations for the exported checkpoint.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from fcemu.evaluation.metrics import EvalMetrics, compute_metrics
from fcemu.evaluation.runner import EvalConfig, run_controller
from fcemu.sim_bridge.env_config import DEFAULT_AIRFRAME, EnvConfig
from fcemu.sim_bridge.vec_env import BatchedRateEnv
from fcemu.sitl.traces import Traces
from fcemu.training.config import SELECT


def concat_traces(parts: list[Traces], controller: str, seed: int) -> Traces:
    return Traces(parts[0].t, np.concatenate([p.setpoint for p in parts]),
                  np.concatenate([p.rate for p in parts]), np.concatenate([p.pwm for p in parts]),
                  controller=controller, seed=seed, task="episodic")


def pid_reference(spec: str, n: int, seed: int, airframe: str = DEFAULT_AIRFRAME) -> Traces:
    """The PID flown through the firmware loop on the commands the batched evaluation uses."""
    parts = [run_controller(spec, EvalConfig(episodes=1, seed=seed + i, airframe=airframe), progress=False)
             for i in range(n)]
    return concat_traces(parts, spec, seed)


def pid_references(specs: tuple[str, ...], n: int, seed: int,
                   airframe: str = DEFAULT_AIRFRAME) -> dict[str, EvalMetrics]:
    """Metrics of each PID preset that loads (a preset file still missing is skipped)."""
    out = {}
    for spec in specs:
        try:
            out[spec] = compute_metrics(pid_reference(spec, n, seed, airframe))
        except FileNotFoundError:
            continue
    if not out:
        raise FileNotFoundError(f"none of the PID presets {specs} could be loaded")
    return out


# The training env's options the race keeps: what the policy observes and how its actions map,
# on which airframe; the flights are the evaluation's own (`BatchedEvaluator.EVALUATED`).
OBSERVED = ("memory", "obs_fields", "integral_leak", "rms_leak", "action_mapping", "airframe")


class BatchedEvaluator:
    """Fly a policy (obs → action, already normalised inside) over n fixed commands: `EVALUATED`
    episodes (from rest, at hover) on the nominal airframe, observed as `options` (EnvConfig's
    fields by keyword: memory, obs_fields, leaks, action_mapping, airframe) say."""

    EVALUATED: ClassVar[dict[str, Any]] = {"task": "episodic", "throttle": None, "episode_s": None,
                                           "randomize": None, "randomize_share": 1.0}

    def __init__(self, n: int, seed: int, **options: Any) -> None:
        self.n, self.seed = n, seed
        self.env = BatchedRateEnv(n, EnvConfig(**{**options, **self.EVALUATED}))

    def traces(self, act, name: str = "policy") -> Traces:
        """`act(obs (n, size) float32) -> actions (n, 4)`; trace sample k is tick k, as in the runner."""
        env, n = self.env, self.n
        ticks = env.config.n_steps
        obs, info = env.reset(seed=self.seed)
        setpoint = np.broadcast_to(info["setpoint"][:, None, :], (n, ticks, 3)).copy()
        rate, pwm = np.zeros((n, ticks, 3)), np.zeros((n, ticks, 4))  # the rig starts at rest: rate[0] = 0
        for k in range(ticks):
            obs, _, _, _, info = env.step(np.clip(act(obs), -1.0, 1.0))
            pwm[:, k] = info["pwm"]
            if k + 1 < ticks:
                rate[:, k + 1] = info["rate"]
        t = np.arange(ticks) * env.config.dt
        return Traces(t, setpoint, rate, pwm, controller=name, seed=self.seed, task="episodic")

    def close(self) -> None:
        self.env.close()


def sb3_actor(model, vecnormalize=None):
    """A deterministic `act(obs)` for an SB3 model, normalising observations as in training.

    For an actor-critic policy (PPO, TRPO) the mean action comes straight from the actor
    network: `predict` would also build the gSDE distribution, check its input and run
    the critic's features on every 1 ms step. The result is `predict`'s, bit for bit."""
    import torch
    from stable_baselines3.common.policies import ActorCriticPolicy

    policy = model.policy
    if not isinstance(policy, ActorCriticPolicy):
        def act(obs: np.ndarray) -> np.ndarray:
            if vecnormalize is not None:
                obs = vecnormalize.normalize_obs(obs)
            return model.predict(obs, deterministic=True)[0]
        return act

    low, high = policy.action_space.low, policy.action_space.high

    def act_mean(obs: np.ndarray) -> np.ndarray:
        if vecnormalize is not None:
            obs = vecnormalize.normalize_obs(obs)
        with torch.no_grad():
            features = policy.extract_features(torch.as_tensor(obs), policy.pi_features_extractor)
            mean = policy.action_net(policy.mlp_extractor.forward_actor(features))
            if policy.squash_output:  # gSDE's tanh bijector, then predict's rescaling
                return policy.unscale_action(torch.tanh(mean).numpy())
        return np.clip(mean.numpy(), low, high)
    policy.set_training_mode(False)
    return act_mean


def selection_key(verdict: dict, select: str = "bar") -> tuple[int, float]:
    """Rank of an evaluation for the exported checkpoint (`--export best`); lower is better.

    `select` "bar": one meeting every criterion beats one that does not; among those
    meeting, the lowest Error wins; among the others, the lowest Error ratio ×
    max(1, smoothness ratio / bar), i.e. the Error ratio with a penalty for output
    roughness beyond the bar. "error": the lowest Error ratio, however rough.
    """
    if select == "error":
        return 0, verdict["error_ratio"]
    if select != "bar":
        raise ValueError(f"unknown selection {select!r}; choose one of {SELECT}")
    if verdict["meets_bar"]:
        return 0, verdict["error_ratio"]
    rough = verdict["smoothness_ratio"] / verdict["smoothness_bar"]
    penalty = rough if rough > 1.0 else 1.0  # NaN smoothness: no penalty rather than an unrankable key
    return 1, verdict["error_ratio"] * penalty
