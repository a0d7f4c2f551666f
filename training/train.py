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

import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.callbacks import BaseCallback, CallbackList, CheckpointCallback
from stable_baselines3.common.vec_env import VecEnv, VecMonitor, VecNormalize

from fcemu import __version__
from fcemu.evaluation import bar
from fcemu.evaluation.metrics import compute_metrics
from fcemu.training import quick_eval
from fcemu.training.config import ALGOS, TrainConfig, parse_hp
from fcemu.training.init import (
    InitError,
    fit_critic_on_own_flights,
    fly_own_flights,
    init_checkpoint,
    start_from,
)

# ── 1. Defaults per algorithm (ALGOS) and 2. the configuration (TrainConfig): training.config ──
__all__ = ["ALGOS", "PID_PRESETS", "InitError", "TrainConfig", "parse_hp", "train"]
PID_PRESETS = ("pid", "pid:paper")  # the bar compares with the best of these
NOISE_STD = 0.1  # DDPG/TD3 Gaussian exploration noise on actions in [-1, 1]

# ── 3. Environment ────────────────────────────────────────────────────────────────────
def make_vec_env(cfg: TrainConfig) -> VecEnv:
    """N twins stepped in one batched call (`sim_bridge.vec_env`), with episode statistics.

    The reward is the env's own (`sim_bridge.reward`), built from `cfg.env_config()`:
    training only chooses the weights, so `gym.make(..., **cfg.env_kwargs())` gives the same reward.
    """
    from fcemu.training.sb3_env import make_sb3_vec_env

    return VecMonitor(make_sb3_vec_env(cfg.n_envs, seed=cfg.seed, config=cfg.env_config()))


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
    if cfg.caps or cfg.anchor:
        from fcemu.training.regularised_ppo import RegularisedPPO as Algo

        hp.update(caps_temporal=cfg.caps_temporal, caps_spatial=cfg.caps_spatial, caps_sigma=cfg.caps_sigma,
                  anchor=cfg.anchor)
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

    Both fly `cfg.airframe` as it is (no randomisation: the race is on the nominal
    airframe). Records each evaluation (steps, wall time, the bar's verdict,
    `bar.bar_verdict`) and saves the best policy so far as a checkpoint, `best`
    holding its path: best by `quick_eval.selection_key` with `cfg.select` (by default one
    meeting the bar beats one that does not, then the lowest Error, rough outputs
    penalised; or the lowest Error). With `stop_at_bar`, ends
    training once the bar is met.
    """

    def __init__(self, cfg: TrainConfig, every: int, stop_at_bar: bool = False) -> None:
        super().__init__()
        self.cfg, self.every, self.stop_at_bar = cfg, every, stop_at_bar
        self.history: list[dict[str, Any]] = []
        self.best: Path | None = None
        self._best_key: tuple[int, float] = (2, np.inf)
        self._next = every
        self._t0: float | None = None  # `start_clock`, else when learning starts
        observed = {k: v for k, v in cfg.env_kwargs().items() if k in quick_eval.OBSERVED}
        self.evaluator = quick_eval.BatchedEvaluator(cfg.eval_commands, cfg.eval_seed, **observed)
        self.pids = quick_eval.pid_references(PID_PRESETS, cfg.eval_commands, cfg.eval_seed, cfg.airframe)

    def start_clock(self, t0: float) -> None:
        """Time the race from `t0` (before a warm start) rather than from when learning starts."""
        self._t0 = t0

    def _on_training_start(self) -> None:
        if self._t0 is None:
            self._t0 = time.perf_counter()

    def _on_step(self) -> bool:
        if self.num_timesteps < self._next:
            return True
        self._next += self.every
        verdict = self.evaluate()
        self.logger.record("eval/error_ratio_vs_pid", verdict["error_ratio"])
        self.logger.record("eval/error_sum", verdict["policy_error_sum"])
        self.logger.record("eval/smoothness_ratio_vs_pid", verdict["smoothness_ratio"])
        self.logger.record("eval/meets_bar", float(verdict["meets_bar"]))
        key = tuple(verdict["selection_key"])
        if key < self._best_key:
            self._best_key = key
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
        metrics = compute_metrics(traces)
        verdict = bar.bar_verdict(metrics, self.pids)
        verdict.update(steps=self.num_timesteps, wall_s=time.perf_counter() - self._t0,
                       selection_key=list(quick_eval.selection_key(verdict, self.cfg.select)))
        self.history.append(verdict)
        print(f"[eval] {self.num_timesteps} steps {verdict['wall_s']:.0f} s: "
              f"{bar.format_verdict(verdict)}", file=sys.stderr)
        return verdict


# ── 6. The run ────────────────────────────────────────────────────────────────────────
def run_config(cfg: TrainConfig) -> dict[str, Any]:
    algo_hp = cfg.hyper
    return {"algo": cfg.algo, "observation": json.loads(_observation_spec(cfg).to_json()),
            "action_mapping": cfg.action_mapping, "throttle": cfg.throttle, "loop_rate_hz": 1000.0,
            "seed": cfg.seed, "trained_steps": 0, "fcemu_version": __version__,
            "env": cfg.env_kwargs(), "reward": cfg.reward, "axis_weights": list(cfg.axis_weights),
            "airframe": cfg.airframe, "randomize": cfg.randomize,  # what the export's envelope reads
            "n_envs": cfg.n_envs,
            "norm_reward": cfg.normalise_reward, "obs_clip": cfg.obs_clip, "select": cfg.select,
            "hyperparameters": json.loads(json.dumps(algo_hp, default=repr)),
            "torch_threads": cfg.threads, "command": " ".join(sys.argv),
            **({"caps": {"temporal": cfg.caps_temporal, "spatial": cfg.caps_spatial, "sigma": cfg.caps_sigma}}
               if cfg.caps else {}),
            **({"anchor": cfg.anchor, "anchor_from_ticks": cfg.anchor_from_ticks} if cfg.anchor else {})}


def _anchor_samples(data: tuple, from_ticks: int) -> tuple:
    """The warm start's (observations, labels) from airframes with at least `from_ticks` of loop
    delay; all of them, uncopied, at 0 (the dataset is hundreds of MB at m = 16)."""
    raw, labels, delays = data
    if not from_ticks:
        return raw, labels
    keep = delays >= from_ticks
    if not keep.any():
        raise ValueError(f"--anchor-from-ticks {from_ticks}: no warm-start sample came from an airframe "
                         f"with that much delay (at most {int(delays.max())} ticks)")
    return raw[keep], labels[keep]


def _observation_spec(cfg: TrainConfig):
    """The spec the training env observes with (what the exported model's metadata carries)."""
    return cfg.env_config().observation_spec


def check_references(cfg: TrainConfig) -> None:
    """The PID the race and the final evaluation compare with (and fall back to) is tuned for the
    airframe: refused before training (`ControllerSpecError`, one line) rather than after it."""
    if not (cfg.eval_every or cfg.eval_episodes):
        return
    from fcemu.firmware.controllers import load_controller
    from fcemu.sim_bridge.airframe_spec import airframe_spec

    load_controller(PID_PRESETS[0], airframe=airframe_spec(cfg.airframe))


POOL_REFUSED = ("--airframe-pool: `fcemu train` races and evaluates one airframe against its tuned PID; "
                "`fcemu distill inversion --airframe-pool` trains one policy across quads")


def train(cfg: TrainConfig, race: PidRaceCallback | None = None) -> dict[str, Any]:
    """Train, save, export, evaluate; returns the summary (also in runs/NAME/summary.json)."""
    if cfg.airframe_pool is not None:
        raise ValueError(POOL_REFUSED)
    check_references(cfg)
    torch.set_num_threads(cfg.threads)
    out = Path(cfg.out)
    config = run_config(cfg)
    init = init_checkpoint(cfg.init, config) if cfg.init else None  # refused: nothing written
    if init is not None:
        config["init"] = str(init.checkpoint.model_path)
        if init.added:
            config["init_added_fields"] = list(init.added)
    (out / "checkpoints").mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(config, indent=2) + "\n")

    venv = VecNormalize(make_vec_env(cfg), norm_obs=cfg.norm_obs, norm_reward=cfg.normalise_reward,
                        clip_obs=cfg.obs_clip or np.inf, gamma=cfg.hyper.get("gamma", 0.99))
    model = make_model(cfg, venv, out / "tb")
    critic, anchored = None, 0
    if init is not None:
        try:
            start_from(model, venv, init)
        except InitError:
            venv.close()
            raise
        flights = fly_own_flights(model, venv) if init.distilled or cfg.anchor else None
        if init.distilled:
            critic = fit_critic_on_own_flights(model, venv, flights)
            print(f"[init] a distilled student: its critic fitted on {critic['env_steps']} steps of its own "
                  f"flights, mse {critic['critic_mse_before']:.4f} -> {critic['critic_mse']:.4f}",
                  file=sys.stderr)
        if cfg.anchor:  # held to what the loaded policy did on its own flights
            model.set_anchor_data(*flights.samples(), venv.normalize_obs)
            anchored = flights.rewards.size
        del flights
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
    if race is not None:
        race.start_clock(t0)  # the race's clock includes the warm start
    warm = None
    if cfg.warm_start:
        from fcemu.training.warm_start import WarmStart

        warm = WarmStart(cfg.warm_start_rounds, cfg.warm_start_steps, preset=cfg.warm_start).run(model, venv)
        data = warm.pop("dataset")  # the fit's samples: the anchor's, else let go here
        if cfg.anchor:
            anchor = _anchor_samples(data, cfg.anchor_from_ticks)
            model.set_anchor_data(*anchor, venv.normalize_obs)
            warm["anchor_samples"] = len(anchor[0])
            del anchor
        del data
        warm["wall_s"] = round(time.perf_counter() - t0, 1)
        print(f"[warm start] {warm['env_steps']} env steps, {warm['wall_s']:.0f} s: "
              + ", ".join(f"actor mse {h['actor_mse']:.4f}" for h in warm["history"])
              + f", critic mse {warm['critic_mse']:.4f}", file=sys.stderr)
    model.learn(cfg.steps, callback=CallbackList(callbacks), progress_bar=cfg.progress, tb_log_name="run")
    train_s = time.perf_counter() - t0
    learn_s = train_s - (warm["wall_s"] if warm else 0.0)

    model.save(out / "model.zip")
    venv.save(str(out / "vecnormalize.pkl"))
    config.update(trained_steps=int(model.num_timesteps), train_wall_s=round(train_s, 1),
                  steps_per_s=round(model.num_timesteps / learn_s, 1))
    (out / "config.json").write_text(json.dumps(config, indent=2) + "\n")
    venv.close()

    from fcemu.export.onnx_export import export_policy

    source = race.best if cfg.export == "best" and race is not None and race.best else out
    export = export_policy(source, out / "policy.onnx")
    summary: dict[str, Any] = {"run": str(out), "algo": cfg.algo, "steps": int(model.num_timesteps),
                               "train_wall_s": round(train_s, 1), "steps_per_s": config["steps_per_s"],
                               "exported": str(source), "export": export}
    if warm is not None:
        summary["warm_start"] = warm
    if critic is not None:
        summary["init_critic"] = critic
    if anchored:
        summary["init_anchor_samples"] = anchored
    if race is not None:
        summary["in_training_evals"] = race.history
    if cfg.eval_episodes:
        summary["eval"] = evaluate_run(out, cfg)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=float) + "\n")
    return summary


# ── 7. Final evaluation: the exported file through the firmware loop, same commands ────
def evaluate_run(out: Path, cfg: TrainConfig, specs: tuple[str, ...] = ("pid", "pid:paper")) -> dict:
    from fcemu.evaluation.evaluate import result_json
    from fcemu.evaluation.report import ControllerResult, write_report
    from fcemu.evaluation.runner import EvalConfig, run_controller

    ecfg = EvalConfig(task="episodic", episodes=cfg.eval_episodes, seed=cfg.eval_seed, airframe=cfg.airframe)
    policy = str(out / "policy.onnx")
    results, metrics = [], {}
    for spec in (*specs, policy):
        traces = run_controller(spec, ecfg, progress=cfg.progress)
        metrics[spec] = compute_metrics(traces)
        results.append(ControllerResult(spec, metrics[spec], traces))
    verdict = bar.bar_verdict(metrics[policy], {s: metrics[s] for s in specs})
    payload = {"seed": ecfg.seed, "episodes": ecfg.episodes, "task": ecfg.task, "throttle": "hover",
               "results": [result_json(s, ecfg, metrics[s]) for s in metrics], "bar": verdict}
    (out / "eval.json").write_text(json.dumps(payload, indent=2, default=float) + "\n")
    write_report(out / "report", results, command=" ".join(sys.argv), seed=ecfg.seed, task=ecfg.task,
                 airframe=ecfg.airframe,
                 episodes=ecfg.episodes, title=f"fcemu training run {out.name}")
    return payload


def print_summary(summary: dict[str, Any]) -> None:
    print(f"{summary['run']}: {summary['algo']} {summary['steps']} steps in {summary['train_wall_s']:.0f} s "
          f"({summary['steps_per_s']:.0f} steps/s); exported {summary['export']['out']} "
          f"({summary['export']['bytes']} bytes, parity {summary['export']['parity_max_abs_diff']:.1e})")
    if "eval" not in summary:
        return
    from fcemu.evaluation.metrics import AXES

    for r in summary["eval"]["results"]:
        m = r["metrics"]
        cells = {k: "/".join(f"{m[k][a][0]:.1f}" if m[k][a][0] is not None else "n/a" for a in AXES)
                 for k in ("error", "rise_ms", "peak_pct", "success_pct")}
        total = sum(m["error"][a][0] for a in AXES)
        print(f"  {r['controller']:>28}  error {cells['error']} (sum {total:.1f})  rise ms {cells['rise_ms']}"
              f"  peak % {cells['peak_pct']}  success % {cells['success_pct']}")
    verdict = summary["eval"]["bar"]
    print(f"  bar: {bar.format_verdict(verdict)}")


# ── 8. Command line ───────────────────────────────────────────────────────────────────
def train_command(args) -> int:
    from fcemu.firmware.errors import UserError
    from fcemu.training.config import from_args

    try:
        cfg = from_args(args)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if cfg.airframe_pool is not None:
        raise UserError(POOL_REFUSED)
    try:
        summary = train(cfg)
    except InitError as exc:
        raise UserError(str(exc)) from None
    if args.json:
        print(json.dumps(summary, default=float))
    else:
        print_summary(summary)
    return 0
