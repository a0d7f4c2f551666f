"""`fcemu train`: one training run, top to bottom.

config → batched environment + VecNormalize → SB3 / sb3-contrib algorithm (defaults per
algorithm in `ALGOS`) → callbacks (progress bar, TensorBoard in runs/NAME/tb, checkpoints,
optional in-training evaluation against the PID) → save → export runs/NAME/policy.onnx →
evaluate against the PID presets on the same commands (runs/NAME/eval.json + report) →
summary.

Run layout (what `export.onnx_export` reads): config.json, model.zip, vecnormalize.pkl,
checkpoints/<algo>_<N>_steps.zip + <algo>_vecnormalize_<N>_steps.pkl, tb/, policy.onnx,
eval.json, report/.
"""

from __future__ import annotations

import ast
import copy
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.callbacks import BaseCallback, CallbackList, CheckpointCallback
from stable_baselines3.common.vec_env import VecEnv, VecMonitor, VecNormalize

from evaluation.metrics import compute_metrics
from fcemu import __version__
from sim_bridge.reward import REWARDS
from training import quick_eval

# ── 1. Defaults per algorithm ─────────────────────────────────────────────────────────
# 1 ms steps and 1000-step episodes: a horizon of ~100 ms (γ 0.99, λ 0.95: a yaw rise
# and its settling) credits an action with what it does to the rate, not with the whole
# episode; γ 0.98 / λ 0.9 (~50 ms) beat the tuned PID on 1 seed of 4, γ 0.99 on 2 of 3.
# Exploration is state-dependent (gSDE, noise redrawn once per rollout): white noise on
# every 1 ms action is filtered away by the motors, tells the critic nothing, and PPO
# with it drifts into spinning the vehicle (docs/training_notes.md).
_ON_POLICY_NET = {"net_arch": {"pi": [64, 64], "vf": [64, 64]}, "log_std_init": -1.0}
_OFF_POLICY = {"learning_rate": 1e-3, "gamma": 0.98, "batch_size": 256, "buffer_size": 1_000_000,
               "learning_starts": 10_000, "train_freq": 1, "gradient_steps": 1, "tau": 0.005,
               "policy_kwargs": {"net_arch": [64, 64]}}
ALGOS: dict[str, dict[str, Any]] = {
    "ppo": {"envs": 64, "norm_reward": True, "hp": {
        "n_steps": 128, "batch_size": 2048, "n_epochs": 5, "learning_rate": "lin_3e-4", "gamma": 0.99,
        "gae_lambda": 0.95, "clip_range": 0.2, "ent_coef": 0.0, "vf_coef": 0.5, "max_grad_norm": 0.5,
        "use_sde": True, "sde_sample_freq": -1, "policy_kwargs": _ON_POLICY_NET}},
    "trpo": {"envs": 64, "norm_reward": True, "hp": {
        "n_steps": 128, "batch_size": 2048, "learning_rate": 1e-3, "gamma": 0.98, "gae_lambda": 0.9,
        "target_kl": 0.01, "use_sde": True, "sde_sample_freq": -1, "policy_kwargs": _ON_POLICY_NET}},
    "ddpg": {"envs": 8, "norm_reward": False, "hp": _OFF_POLICY},
    "td3": {"envs": 8, "norm_reward": False, "hp": _OFF_POLICY},
    "sac": {"envs": 8, "norm_reward": False, "hp": {**_OFF_POLICY, "ent_coef": "auto", "use_sde": True}},
}
PID_PRESETS = ("pid", "pid:paper")  # the bar compares with the best of these
NOISE_STD = 0.1  # DDPG/TD3 Gaussian exploration noise on actions in [-1, 1]


# ── 2. Configuration ──────────────────────────────────────────────────────────────────
@dataclass
class TrainConfig:
    algo: str = "ppo"
    steps: int = 2_000_000
    seed: int = 0
    out: str = "runs/ppo"
    memory: int = 1
    integral: bool = False  # + firmware.observation's rate_error_integral field
    squash: bool = False  # PPO/TRPO: tanh-squashed gSDE actions (SAC, TD3 and DDPG squash already)
    envs: int | None = None  # None: the algorithm's default
    action_mapping: str = "throttle"
    throttle: float | tuple[float, float] | None = (0.5, 0.9)  # the collective training draws from
    task: str = "episodic"
    action_rate_penalty: float = 0.0
    reward: str = "unclipped"  # see REWARDS / RewardOption
    axis_weights: tuple[float, float, float] = (1.0, 1.0, 1.0)  # roll, pitch, yaw error (unclipped only)
    norm_reward: bool | None = None
    norm_obs: bool = True
    hp: dict[str, Any] = field(default_factory=dict)  # overrides of ALGOS[algo]["hp"]
    checkpoint_every: int = 1_000_000  # steps
    eval_every: int = 0  # steps between in-training evaluations against the PID; 0: none
    eval_commands: int = 64
    eval_episodes: int = 1000  # final evaluation, through the firmware loop; 0: skip
    eval_seed: int = 1
    export: str = "best"  # best: the in-training evaluation's best checkpoint (if any); final
    threads: int = 1
    progress: bool = True
    airframe: str = "iris"  # sim_bridge/airframes/<name>.json, e.g. iris_realistic (effects on)
    caps_temporal: float = 0.0  # PPO: λ_T of CAPS's ‖π(s_t) − π(s_t+1)‖ (training.caps)
    caps_spatial: float = 0.0  # PPO: λ_S of CAPS's ‖π(s) − π(s̃)‖, s̃ ~ N(s, caps_sigma²)
    caps_sigma: float = 0.05  # in VecNormalize's normalised observation units

    @property
    def caps(self) -> bool:
        return bool(self.caps_temporal or self.caps_spatial)

    def __post_init__(self) -> None:
        if self.algo not in ALGOS:
            raise ValueError(f"unknown algorithm {self.algo!r}; choose one of {tuple(ALGOS)}")
        if self.reward == "paper" and tuple(self.axis_weights) != (1.0, 1.0, 1.0):
            raise ValueError("axis weights need --reward unclipped")
        if self.reward not in REWARDS:
            raise ValueError(f"unknown reward {self.reward!r}; choose one of {REWARDS}")
        if self.squash and self.algo not in ("ppo", "trpo"):
            raise ValueError(f"--squash is for PPO and TRPO; {self.algo.upper()} squashes already")
        if isinstance(self.throttle, list):
            self.throttle = tuple(self.throttle)
        if self.caps and self.algo != "ppo":
            raise ValueError(f"CAPS (caps_temporal, caps_spatial) is for PPO, not {self.algo.upper()}")

    @property
    def obs_fields(self) -> tuple[str, ...]:
        from firmware.observation import FIELDS, INTEGRAL

        return (*FIELDS, INTEGRAL) if self.integral else FIELDS

    @property
    def n_envs(self) -> int:
        return self.envs or ALGOS[self.algo]["envs"]

    @property
    def hyper(self) -> dict[str, Any]:
        hp = copy.deepcopy({**ALGOS[self.algo]["hp"], **self.hp})  # SB3 writes into policy_kwargs
        if self.squash:
            hp["policy_kwargs"] = {**hp.get("policy_kwargs", {}), "squash_output": True}
        return hp

    @property
    def normalise_reward(self) -> bool:
        return ALGOS[self.algo]["norm_reward"] if self.norm_reward is None else self.norm_reward

    def env_kwargs(self) -> dict[str, Any]:
        return {"task": self.task, "memory": self.memory, "obs_fields": self.obs_fields,
                "action_mapping": self.action_mapping, "throttle": self.throttle,
                "reward": self.reward, "axis_weights": tuple(self.axis_weights),
                "action_rate_penalty": self.action_rate_penalty,
                **({"airframe": self.airframe} if self.airframe != "iris" else {})}


# ── 3. Environment ────────────────────────────────────────────────────────────────────
def make_vec_env(cfg: TrainConfig) -> VecEnv:
    """N twins stepped in one batched call (`sim_bridge.vec_env`), with episode statistics.

    The reward is the env's own (`sim_bridge.reward`), built from `cfg.env_kwargs()`:
    training only chooses the weights, so `gym.make(..., **env_kwargs)` gives the same reward.
    """
    from sim_bridge.vec_env import make_sb3_vec_env

    return VecMonitor(make_sb3_vec_env(cfg.n_envs, seed=cfg.seed, **cfg.env_kwargs()))


# ── 4. Algorithm ──────────────────────────────────────────────────────────────────────
def make_model(cfg: TrainConfig, venv: VecEnv, tb_dir: Path):
    hp = dict(cfg.hyper)
    if cfg.algo == "trpo":
        from sb3_contrib import TRPO as Algo
    else:
        import stable_baselines3

        Algo = getattr(stable_baselines3, cfg.algo.upper())
    for key in ("learning_rate", "clip_range"):  # "lin_3e-4": linear decay to 0, as rl-zoo writes it
        if isinstance(hp.get(key), str) and hp[key].startswith("lin_"):
            start = float(hp[key][4:])
            hp[key] = lambda remaining, start=start: remaining * start
    if cfg.algo in ("ddpg", "td3") and "action_noise" not in hp:
        from stable_baselines3.common.noise import NormalActionNoise

        hp["action_noise"] = NormalActionNoise(np.zeros(4), NOISE_STD * np.ones(4))
    if cfg.caps:
        from training.caps import CapsPPO as Algo

        hp.update(caps_temporal=cfg.caps_temporal, caps_spatial=cfg.caps_spatial, caps_sigma=cfg.caps_sigma)
    return Algo("MlpPolicy", venv, seed=cfg.seed, verbose=0, device="cpu", tensorboard_log=str(tb_dir), **hp)


# ── 5. Callbacks ──────────────────────────────────────────────────────────────────────
_REWARD_TAGS = {"paper_reward": "reward/paper", "action_rate": "reward/action_rate",
                "reward_tracking": "reward/tracking", "reward_action_rate": "reward/action_rate_term"}


class RewardTermsCallback(BaseCallback):
    """Logs the env's reward terms separately (TensorBoard): the paper's reward, mean|Δu|, the
    tracking term trained on and the weighted output-oscillation term."""

    def _on_step(self) -> bool:
        batch = self.training_env.unwrapped.last_info
        for key, tag in _REWARD_TAGS.items():
            if key in batch:
                self.logger.record_mean(tag, float(np.mean(batch[key])))
        return True


class PidRaceCallback(BaseCallback):
    """Every `every` steps, score the deterministic policy on fixed commands against the PID.

    Records each evaluation (steps, wall time, error ratio, bar verdict) and saves the best
    policy so far (lowest Error sum) as a checkpoint, `best` holding its path; with
    `stop_at_bar`, ends training once the bar is met.
    """

    def __init__(self, cfg: TrainConfig, every: int, stop_at_bar: bool = False) -> None:
        super().__init__()
        self.cfg, self.every, self.stop_at_bar = cfg, every, stop_at_bar
        self.history: list[dict[str, Any]] = []
        self.best: Path | None = None
        self._best_ratio = np.inf
        self._next = every
        self._t0 = time.perf_counter()
        self.evaluator = quick_eval.BatchedEvaluator(cfg.eval_commands, cfg.eval_seed, cfg.memory,
                                                     cfg.action_mapping, cfg.obs_fields)
        self.pids = quick_eval.pid_references(PID_PRESETS, cfg.eval_commands, cfg.eval_seed)

    def _on_training_start(self) -> None:
        self._t0 = time.perf_counter()

    def _on_step(self) -> bool:
        if self.num_timesteps < self._next:
            return True
        self._next += self.every
        verdict = self.evaluate()
        self.logger.record("eval/error_ratio_vs_pid", verdict["error_ratio"])
        self.logger.record("eval/error_sum", verdict["policy_error_sum"])
        if verdict["error_ratio"] < self._best_ratio:
            self._best_ratio = verdict["error_ratio"]
            self.best = self.save_checkpoint()
        return not (self.stop_at_bar and verdict["meets_bar"])

    def save_checkpoint(self) -> Path:
        """The policy now, in CheckpointCallback's layout (so `fcemu export` takes it)."""
        ckpt = Path(self.cfg.out) / "checkpoints"
        path = ckpt / f"{self.cfg.algo}_{self.num_timesteps}_steps.zip"
        self.model.save(path)
        vecnorm = self.model.get_vec_normalize_env()
        if vecnorm is not None:
            vecnorm.save(str(ckpt / f"{self.cfg.algo}_vecnormalize_{self.num_timesteps}_steps.pkl"))
        return path

    def evaluate(self) -> dict[str, Any]:
        vecnorm = self.model.get_vec_normalize_env()
        traces = self.evaluator.traces(quick_eval.sb3_actor(self.model, vecnorm))
        verdict = quick_eval.bar_verdict(compute_metrics(traces), self.pids)
        verdict.update(steps=self.num_timesteps, wall_s=time.perf_counter() - self._t0)
        self.history.append(verdict)
        rise = "/".join(f"{p:.0f}<{r:.0f}" for p, r in verdict["rise_ms_policy_vs_pid"].values())
        print(f"[eval] {self.num_timesteps} steps {verdict['wall_s']:.0f} s: error "
              f"{verdict['policy_error_sum']:.1f} vs {verdict['best_pid']} {verdict['pid_error_sum']:.1f}"
              f" (×{verdict['error_ratio']:.3f}), success "
              f"{'/'.join(f'{v:.1f}' for v in verdict['success_pct'].values())}, rise {rise}",
              file=sys.stderr)
        return verdict


# ── 6. The run ────────────────────────────────────────────────────────────────────────
def run_config(cfg: TrainConfig) -> dict[str, Any]:
    algo_hp = cfg.hyper
    return {"algo": cfg.algo, "observation": json.loads(_spec(cfg).to_json()),
            "action_mapping": cfg.action_mapping, "throttle": cfg.throttle, "loop_rate_hz": 1000.0,
            "seed": cfg.seed, "trained_steps": 0, "fcemu_version": __version__,
            "env": cfg.env_kwargs(), "reward": cfg.reward, "axis_weights": list(cfg.axis_weights),
            "n_envs": cfg.n_envs,
            "norm_reward": cfg.normalise_reward,
            "hyperparameters": json.loads(json.dumps(algo_hp, default=repr)),
            "torch_threads": cfg.threads, "command": " ".join(sys.argv),
            **({"caps": {"temporal": cfg.caps_temporal, "spatial": cfg.caps_spatial, "sigma": cfg.caps_sigma}}
               if cfg.caps else {})}


def _spec(cfg: TrainConfig):
    from firmware.observation import ObservationSpec

    return ObservationSpec(memory=cfg.memory, fields=cfg.obs_fields)


def train(cfg: TrainConfig, race: PidRaceCallback | None = None) -> dict[str, Any]:
    """Train, save, export, evaluate; returns the summary (also in runs/NAME/summary.json)."""
    torch.set_num_threads(cfg.threads)
    out = Path(cfg.out)
    (out / "checkpoints").mkdir(parents=True, exist_ok=True)
    config = run_config(cfg)
    (out / "config.json").write_text(json.dumps(config, indent=2) + "\n")

    venv = VecNormalize(make_vec_env(cfg), norm_obs=cfg.norm_obs, norm_reward=cfg.normalise_reward,
                        clip_obs=10.0, gamma=cfg.hyper.get("gamma", 0.99))
    model = make_model(cfg, venv, out / "tb")
    callbacks: list[BaseCallback] = [
        RewardTermsCallback(),
        CheckpointCallback(max(1, cfg.checkpoint_every // cfg.n_envs), str(out / "checkpoints"),
                           name_prefix=cfg.algo, save_vecnormalize=True),
    ]
    if race is None and cfg.eval_every:
        race = PidRaceCallback(cfg, cfg.eval_every)
    if race is not None:
        callbacks.append(race)

    t0 = time.perf_counter()
    model.learn(cfg.steps, callback=CallbackList(callbacks), progress_bar=cfg.progress, tb_log_name="run")
    train_s = time.perf_counter() - t0

    model.save(out / "model.zip")
    venv.save(str(out / "vecnormalize.pkl"))
    config.update(trained_steps=int(model.num_timesteps), train_wall_s=round(train_s, 1),
                  steps_per_s=round(model.num_timesteps / train_s, 1))
    (out / "config.json").write_text(json.dumps(config, indent=2) + "\n")
    venv.close()

    from export.onnx_export import export_policy

    source = race.best if cfg.export == "best" and race is not None and race.best else out
    export = export_policy(source, out / "policy.onnx")
    summary: dict[str, Any] = {"run": str(out), "algo": cfg.algo, "steps": int(model.num_timesteps),
                               "train_wall_s": round(train_s, 1), "steps_per_s": config["steps_per_s"],
                               "exported": str(source), "export": export}
    if race is not None:
        summary["in_training_evals"] = race.history
    if cfg.eval_episodes:
        summary["eval"] = evaluate_run(out, cfg)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=float) + "\n")
    return summary


# ── 7. Final evaluation: the exported file through the firmware loop, same commands ────
def evaluate_run(out: Path, cfg: TrainConfig, specs: tuple[str, ...] = ("pid", "pid:paper")) -> dict:
    from evaluation.evaluate import result_json
    from evaluation.report import ControllerResult, write_report
    from evaluation.runner import EvalConfig, run_controller

    ecfg = EvalConfig(task="episodic", episodes=cfg.eval_episodes, seed=cfg.eval_seed)
    policy = str(out / "policy.onnx")
    results, metrics = [], {}
    for spec in (*specs, policy):
        traces = run_controller(spec, ecfg, progress=cfg.progress)
        metrics[spec] = compute_metrics(traces)
        results.append(ControllerResult(spec, metrics[spec], traces))
    verdict = quick_eval.bar_verdict(metrics[policy], {s: metrics[s] for s in specs})
    payload = {"seed": ecfg.seed, "episodes": ecfg.episodes, "task": ecfg.task, "throttle": "hover",
               "results": [result_json(s, ecfg, metrics[s]) for s in metrics], "bar": verdict}
    (out / "eval.json").write_text(json.dumps(payload, indent=2, default=float) + "\n")
    write_report(out / "report", results, command=" ".join(sys.argv), seed=ecfg.seed, task=ecfg.task,
                 episodes=ecfg.episodes, title=f"fcemu training run {out.name}")
    return payload


def print_summary(summary: dict[str, Any]) -> None:
    print(f"{summary['run']}: {summary['algo']} {summary['steps']} steps in {summary['train_wall_s']:.0f} s "
          f"({summary['steps_per_s']:.0f} steps/s); exported {summary['export']['out']} "
          f"({summary['export']['bytes']} bytes, parity {summary['export']['parity_max_abs_diff']:.1e})")
    if "eval" not in summary:
        return
    from evaluation.metrics import AXES

    for r in summary["eval"]["results"]:
        m = r["metrics"]
        cells = {k: "/".join(f"{m[k][a][0]:.1f}" if m[k][a][0] is not None else "n/a" for a in AXES)
                 for k in ("error", "rise_ms", "peak_pct", "success_pct")}
        total = sum(m["error"][a][0] for a in AXES)
        print(f"  {r['controller']:>28}  error {cells['error']} (sum {total:.1f})  rise ms {cells['rise_ms']}"
              f"  peak % {cells['peak_pct']}  success % {cells['success_pct']}")
    bar = summary["eval"]["bar"]
    print(f"  bar vs {bar['best_pid']}: error ×{bar['error_ratio']:.3f} (≤ {bar['error_ratio_bar']}), "
          f"checks {bar['checks']} → {'MET' if bar['meets_bar'] else 'not met'}")


# ── 8. Command line ───────────────────────────────────────────────────────────────────
def parse_hp(items: list[str] | None) -> dict[str, Any]:
    """`key=value` pairs; values are Python literals (numbers, lists, dicts), else strings."""
    hp: dict[str, Any] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--hp {item!r}: expected key=value")
        try:
            hp[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            hp[key] = value
    return hp


def config_from_args(args) -> TrainConfig:
    throttle = args.throttle
    if throttle is not None:
        throttle = tuple(throttle) if len(throttle) == 2 else throttle[0]
    return TrainConfig(algo=args.algo, steps=args.steps, seed=args.seed, out=args.out or f"runs/{args.algo}",
                       memory=args.memory, integral=args.integral, squash=args.squash, envs=args.envs,
                       action_mapping=args.action_mapping,
                       throttle=throttle if args.throttle is not None else TrainConfig.throttle,
                       task=args.task, action_rate_penalty=args.action_rate_penalty, reward=args.reward,
                       axis_weights=tuple(args.axis_weights),
                       norm_reward=args.norm_reward, norm_obs=args.norm_obs, hp=parse_hp(args.hp),
                       checkpoint_every=args.checkpoint_every, eval_every=args.eval_every,
                       eval_episodes=args.eval_episodes, eval_seed=args.eval_seed, export=args.export,
                       threads=args.threads, progress=not args.no_progress)


def train_command(args) -> int:
    cfg = config_from_args(args)
    summary = train(cfg)
    if args.json:
        print(json.dumps(summary, default=float))
    else:
        print_summary(summary)
    return 0

