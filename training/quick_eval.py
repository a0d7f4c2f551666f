"""The in-training evaluation: the paper's metrics for a torch policy on the batched twin.

`run_controller` flies an exported ONNX file through the firmware loop, one episode at a
time (~40 ms each); during training we want a verdict in about a second. This flies the
deterministic policy, with its observation normalisation, on `BatchedRateEnv` (the same
twin arithmetic, bit for bit) and builds the same `Traces`, so `compute_metrics` scores
it exactly as `fcemu eval` would. Copy i flies the command `episodic_commands(seed + i, 1)`,
so the PID reference is `run_controller(pid, EvalConfig(episodes=1, seed=seed + i))`. Both
fly the training airframe as it is, without randomisation; the trace holds the body rate
(the gyro's reading without vibration, noise or delay), as `fcemu eval` records it.

`bar_verdict` judges the policy against the best PID preset by the shipped policy's criteria;
`selection_key` ranks in-training evaluations for the exported checkpoint.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fcemu.evaluation.metrics import AXES, EvalMetrics, compute_metrics
from fcemu.evaluation.runner import EvalConfig, run_controller
from fcemu.firmware.observation import FIELDS
from fcemu.sim_bridge.vec_env import BatchedRateEnv
from fcemu.sitl.traces import Traces
from fcemu.training.config import SELECT


def error_sum(metrics: EvalMetrics) -> float:
    """The bar's figure: mean Error per episode, summed over roll, pitch and yaw."""
    return float(sum(metrics.stat("error", a).mean for a in AXES))


def concat_traces(parts: list[Traces], controller: str, seed: int) -> Traces:
    return Traces(parts[0].t, np.concatenate([p.setpoint for p in parts]),
                  np.concatenate([p.rate for p in parts]), np.concatenate([p.pwm for p in parts]),
                  controller=controller, seed=seed, task="episodic")


def pid_reference(spec: str, n: int, seed: int, airframe: str = "iris") -> Traces:
    """The PID flown through the firmware loop on the commands the batched evaluation uses."""
    parts = [run_controller(spec, EvalConfig(episodes=1, seed=seed + i, airframe=airframe), progress=False)
             for i in range(n)]
    return concat_traces(parts, spec, seed)


def pid_references(specs: tuple[str, ...], n: int, seed: int,
                   airframe: str = "iris") -> dict[str, EvalMetrics]:
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


@dataclass
class BatchedEvaluator:
    """Fly a policy (obs → action, already normalised inside) over n fixed commands at hover on `airframe`."""

    n: int
    seed: int
    memory: int = 1
    action_mapping: str = "throttle"
    obs_fields: tuple[str, ...] = FIELDS
    airframe: str = "iris"
    obs_leaks: dict[str, float] = field(default_factory=dict)  # EnvConfig's λ of integrated fields
    env: BatchedRateEnv = field(init=False)

    def __post_init__(self) -> None:
        self.env = BatchedRateEnv(self.n, task="episodic", memory=self.memory, obs_fields=self.obs_fields,
                                  action_mapping=self.action_mapping, throttle=None, airframe=self.airframe,
                                  **self.obs_leaks)

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


ERROR_RATIO_BAR = 0.95  # Error sum ≤ this × the PID's
PEAK_MARGIN_PCT = 3.0  # Peak ≤ the PID's + this, every axis
SUCCESS_BAR_PCT = 99.8  # Success ≥ this, every axis
SMOOTHNESS_BAR = 1.5  # smoothness (mean |Δpwm| per step) ≤ this × the PID's
PERTURBED_SUCCESS_BAR_PCT = 99.0  # on perturbed airframes: Success ≥ this, every axis (Error ≤ the PID's)


def bar_verdict(policy: EvalMetrics, pids: dict[str, EvalMetrics], error_ratio: float = ERROR_RATIO_BAR,
                min_success: float = SUCCESS_BAR_PCT, peak_margin: float = PEAK_MARGIN_PCT,
                smoothness_ratio: float = SMOOTHNESS_BAR) -> dict:
    """The bar against the best PID preset (lowest Error sum); every criterion, its figures and its check.

    Error sum ≤ `error_ratio` × the PID's; Rise ≤ the PID's, Peak ≤ the PID's + `peak_margin`
    points and Success ≥ `min_success` % on every axis; smoothness ≤ `smoothness_ratio` × the
    PID's. A figure that is missing (NaN: e.g. no episode rose) fails its check.
    """
    best = min(pids, key=lambda k: error_sum(pids[k]))
    ref = pids[best]
    pol_sum, ref_sum = error_sum(policy), error_sum(ref)
    rise = {a: [policy.stat("rise_ms", a).mean, ref.stat("rise_ms", a).mean] for a in AXES}
    peak = {a: [policy.stat("peak_pct", a).mean, ref.stat("peak_pct", a).mean] for a in AXES}
    success = {a: policy.stat("success_pct", a).mean for a in AXES}
    # smoothness is one figure over the motors, the same on every axis
    smooth, smooth_pid = policy.stat("smoothness", "roll").mean, ref.stat("smoothness", "roll").mean
    checks = {
        "error_ratio": pol_sum / ref_sum <= error_ratio,
        "rise": all(p <= r for p, r in rise.values()),
        "peak": all(p <= r + peak_margin for p, r in peak.values()),
        "success": all(success[a] >= min_success for a in AXES),
        "smoothness": smooth <= smoothness_ratio * smooth_pid,
    }
    return {"best_pid": best, "policy_error_sum": pol_sum, "pid_error_sum": ref_sum,
            "error_ratio": pol_sum / ref_sum, "error_ratio_bar": error_ratio,
            "success_pct": success, "success_bar": min_success,
            "rise_ms_policy_vs_pid": rise, "peak_pct_policy_vs_pid": peak, "peak_margin": peak_margin,
            "smoothness": smooth, "pid_smoothness": smooth_pid, "smoothness_ratio": smooth / smooth_pid,
            "smoothness_bar": smoothness_ratio,
            "checks": checks, "meets_bar": all(checks.values())}


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


def format_verdict(verdict: dict) -> str:
    """The verdict on one line: each criterion's figures (roll/pitch/yaw) vs the PID's, and which fail."""
    def pair(key: str, fmt: str) -> str:
        pol, ref = zip(*verdict[key].values(), strict=True)
        return f"{'/'.join(f'{x:{fmt}}' for x in pol)} vs {'/'.join(f'{x:{fmt}}' for x in ref)}"

    v = verdict
    failed = [k for k, ok in v["checks"].items() if not ok]
    success = "/".join(f"{x:.1f}" for x in v["success_pct"].values())
    return (f"error {v['policy_error_sum']:.1f} vs {v['best_pid']} {v['pid_error_sum']:.1f} "
            f"(×{v['error_ratio']:.3f} ≤ {v['error_ratio_bar']}), "
            f"rise ms {pair('rise_ms_policy_vs_pid', '.0f')}, "
            f"peak % {pair('peak_pct_policy_vs_pid', '.1f')} (+{v['peak_margin']:g}), "
            f"success % {success} (≥ {v['success_bar']}), "
            f"smoothness {v['smoothness']:.2f} vs {v['pid_smoothness']:.2f} "
            f"(×{v['smoothness_ratio']:.2f} ≤ {v['smoothness_bar']}) "
            f"→ {'MET' if v['meets_bar'] else 'not met: ' + ', '.join(failed)}")
