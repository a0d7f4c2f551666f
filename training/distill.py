"""`fcemu distill`: a compact student policy fitted to a teacher policy (.onnx) by DAgger.

The teacher may also be `inversion`: the airframe's model inverted tick by tick
(`training.inversion_teacher`), which needs no training; `fcemu fit` distils it.

The student flies the randomised twins (`sim_bridge.vec_env.BatchedRateEnv`); the teacher,
in onnxruntime, labels every state the student visits with its own action, from its own
observation. Both observations come from one firmware observation (`firmware.observation`)
that holds the fields and the history of both: the environment builds it with the union of
the two specs, and each policy reads its columns. So the student may observe less, and a
shorter history, than the teacher, but only what the firmware can compute. Round 0 is flown
by the teacher; in round r a twin's episode is flown by the teacher with probability β^r,
else by the student (the DAgger mixture). After each round the student is fitted (Adam, mean
squared error against the teacher's action clipped to the action range, the gain match on
nudged copies of the samples (`nudge`), and an optional penalty on the change of the student's
action from one step to the next) on every sample so far. The defaults are the shipped
default's recipe: the teacher's whole history through a first layer of 8 units, 32-32 after
it, the gain match at 0.1 (policies/README.md).

The run directory is `fcemu train`'s (config.json, model.zip, vecnormalize.pkl, policy.onnx):
the student is the actor of an SB3 PPO model, so `fcemu export DIR` exports it and
`fcemu train --init DIR` fine-tunes it (its critic is untrained).
"""

from __future__ import annotations

import json
import sys
import time
import warnings
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fcemu.firmware.observation import AUTHORITY, FIELDS, INTEGRAL, MOTOR_OUTPUT, RATE, RMS
from fcemu.training.distill_config import DistillConfig, from_args
from fcemu.training.distill_teacher import (
    INVERSION,
    DistillError,
    Teacher,
    columns,
    is_model_based,
    make_teacher,
    union_spec,
)

__all__ = ["INVERSION", "DistillConfig", "DistillError", "Teacher", "columns", "distill", "fly", "nudge",
           "student_train_config", "union_spec"]

COLLECTIVE_WEIGHT = 0.1
OPTIONAL_FIELDS = {INTEGRAL: "integral", RMS: "error_rms", MOTOR_OUTPUT: "motor_output", RATE: "rate",
                   AUTHORITY: "authority"}


def student_train_config(cfg: DistillConfig, teacher: Teacher):
    """The student as a `fcemu train` run: its spec, the teacher's action contract, the twins."""
    from fcemu.training.config import TrainConfig

    fields = tuple(cfg.fields or teacher.spec.fields)
    if fields[:2] != FIELDS or set(fields[2:]) - set(OPTIONAL_FIELDS):
        raise DistillError(f"student fields {fields}: rate_error and rotor_speed first, then any of "
                           f"{tuple(OPTIONAL_FIELDS)}")
    flags = {flag: name in fields for name, flag in OPTIONAL_FIELDS.items()}
    leaks = {**({"integral_leak": teacher.spec.integral_leak} if flags["integral"] else {}),
             **({"rms_leak": teacher.spec.rms_leak} if flags["error_rms"] else {})}
    throttle = tuple(teacher.throttle) if isinstance(teacher.throttle, list) else teacher.throttle
    hp = {"policy_kwargs": {"net_arch": {"pi": list(cfg.net_arch), "vf": [64, 64]}, "log_std_init": -3.0}}
    memory = teacher.spec.memory if cfg.memory is None else cfg.memory
    ranges = cfg.ranges()
    env = {**{name: getattr(cfg, name) for name in type(cfg).env_options}, "randomize": ranges,
           "randomize_share": cfg.randomize_share if ranges else 1.0}
    train_cfg = TrainConfig(algo="ppo", seed=cfg.seed, out=cfg.out, memory=memory, **flags, **leaks,
                            envs=1, action_mapping=teacher.action_mapping, throttle=throttle,
                            obs_clip=0.0, hp=hp, threads=cfg.threads, progress=cfg.progress, **env)
    if not cfg.foreign_teacher and train_cfg.env_config().base_airframe.name != teacher.airframe:
        raise DistillError(f"the teacher was made for airframe {teacher.airframe!r}, not "
                           f"{train_cfg.env_config().base_airframe.name!r}: give --foreign-teacher to "
                           "distil it for this one")
    from fcemu.training.train import _observation_spec

    spec = _observation_spec(train_cfg)
    if (spec.rate_scale, spec.rotor_speed_scale) != (teacher.spec.rate_scale, teacher.spec.rotor_speed_scale):
        raise DistillError("the teacher's observation scales are not the firmware's defaults")
    return train_cfg, spec


# ── The student network ────────────────────────────────────────────────────────────────
class Student:
    """The actor of an SB3 PPO model with fixed observation statistics: raw observation → mean action."""

    def __init__(self, model, mean: np.ndarray, var: np.ndarray, eps: float) -> None:
        self.policy = model.policy
        self.mean = torch.as_tensor(mean, dtype=torch.float32)
        self.inv_std = torch.as_tensor(1.0 / np.sqrt(var + eps), dtype=torch.float32)
        self.params = [*self.policy.mlp_extractor.policy_net.parameters(),
                       *self.policy.action_net.parameters()]

    def __call__(self, raw: torch.Tensor) -> torch.Tensor:
        x = (raw - self.mean) * self.inv_std
        return self.policy.action_net(self.policy.mlp_extractor.forward_actor(x))

    def act(self, raw: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return self(torch.as_tensor(raw)).numpy()


@dataclass
class Dataset:
    """Every labelled sample so far; `next_row` is the sample one step later on the same twin, or −1."""

    obs: list[np.ndarray] = field(default_factory=list)
    labels: list[np.ndarray] = field(default_factory=list)
    nudged_obs: list[np.ndarray] = field(default_factory=list)
    nudged_labels: list[np.ndarray] = field(default_factory=list)
    next_row: list[np.ndarray] = field(default_factory=list)
    size: int = 0

    def add(self, obs: np.ndarray, labels: np.ndarray, ended: np.ndarray) -> None:
        """One round's (steps, twins, ...) arrays; `ended[k]`: the twins whose episode ended at step k."""
        steps, n = ended.shape
        rows = self.size + np.arange(steps * n).reshape(steps, n)
        nxt = np.full((steps, n), -1)
        nxt[:-1] = np.where(ended[:-1], -1, rows[1:])
        self.obs.append(obs.reshape(steps * n, -1))
        self.labels.append(np.clip(labels, -1.0, 1.0).reshape(steps * n, 4))  # past ±1 the mixer clips
        self.next_row.append(nxt.reshape(-1))
        self.size += steps * n

    def add_nudged(self, obs: np.ndarray, labels: np.ndarray) -> None:
        """The round's observations nudged (`nudge`), in `add`'s order, and the teacher's labels there."""
        self.nudged_obs.append(obs.reshape(-1, obs.shape[-1]))
        self.nudged_labels.append(np.clip(labels, -1.0, 1.0).reshape(-1, 4))

    def tensors(self) -> dict[str, torch.Tensor]:
        out = {"obs": np.concatenate(self.obs), "labels": np.concatenate(self.labels),
               "next_row": np.concatenate(self.next_row)}
        if self.nudged_obs:
            out.update(nudged_obs=np.concatenate(self.nudged_obs),
                       nudged_labels=np.concatenate(self.nudged_labels))
        return {k: torch.as_tensor(v) for k, v in out.items()}


def differential(a: torch.Tensor) -> torch.Tensor:
    """The part of four motor actions the mixer keeps: a − mean(a) (`firmware.action`, both mappings
    up to the collective, which the throttle mapping takes from the outer loop)."""
    return a - a.mean(dim=-1, keepdim=True)


def differential_mse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The squared error of the differential, and a tenth of the collective's: the clip before the
    mixer still sees the collective, so it must not drift."""
    error = pred - target
    return differential(error).pow(2).mean() + COLLECTIVE_WEIGHT * error.mean(dim=-1).pow(2).mean()


def as_mixed(pred: torch.Tensor, label: torch.Tensor) -> torch.Tensor:
    """The prediction as the mixer takes it, against a label: past a label at an end of the action
    range the mixer clips both to the same action (`firmware.action`), so there is no error there.
    Without this the fit pulls every saturated output back inside the range, and the student comes
    out slow wherever the teacher saturates."""
    past = ((label >= 1.0) & (pred > 1.0)) | ((label <= -1.0) & (pred < -1.0))
    return torch.where(past, label, pred)


def imitation_mse(pred: torch.Tensor, label: torch.Tensor) -> torch.Tensor:
    return differential_mse(as_mixed(pred, label), label)


def fit(student: Student, data: Dataset, steps: int, cfg: DistillConfig, gen: torch.Generator) -> dict:
    """Adam on the imitation error (and the gain match, the smoothness penalty) over the aggregate;
    the final losses."""
    t = data.tensors()
    x, y, nxt = t["obs"], t["labels"], t["next_row"]
    opt = torch.optim.Adam(student.params, lr=cfg.learning_rate)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps, eta_min=cfg.learning_rate * 0.05)
    with_next = torch.nonzero(nxt >= 0).squeeze(1)
    for _ in range(steps):
        idx = torch.randint(len(x), (cfg.batch_size,), generator=gen)
        pred = student(x[idx])
        loss = imitation_mse(pred, y[idx])
        if cfg.gain_weight:
            response = differential_mse(student(t["nudged_obs"][idx]) - pred,
                                        t["nudged_labels"][idx] - y[idx])
            loss = loss + cfg.gain_weight * response / cfg.gain_step**2
        if cfg.smoothness:
            pair = with_next[torch.randint(len(with_next), (cfg.batch_size,), generator=gen)]
            step = differential(student(x[pair]) - student(x[nxt[pair]]))
            loss = loss + cfg.smoothness * step.pow(2).sum(1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    with torch.no_grad():
        probe = torch.randint(len(x), (min(len(x), 65536),), generator=gen)
        losses = {"imitation_mse": float(imitation_mse(student(x[probe]), y[probe]))}
        if "nudged_obs" in t:  # the slopes' error, per unit nudge
            response = student(t["nudged_obs"][probe]) - student(x[probe])
            losses["gain_mse"] = float(differential_mse(response, t["nudged_labels"][probe] - y[probe])
                                       / cfg.gain_step**2)
    return losses


# ── DAgger ─────────────────────────────────────────────────────────────────────────────
def fly(env, teacher: Teacher, student: Student | None, cols: tuple[np.ndarray, np.ndarray], steps: int,
        teacher_share: float, rng: np.random.Generator, obs: np.ndarray, bar,
        keep_union: bool = False, privileged: bool = False) -> tuple:
    """One round: every twin `steps` steps; the student's observations, the teacher's labels,
    the episode ends, the tracking error |Ω* − Ω| of the student's episodes, the next observation,
    and (`keep_union`) the whole observations both read (the student's, the teacher's).

    `privileged`: where the twins' gyro or ESC telemetry is late or lossy, the teacher reads the
    observation of the readings as sampled (`BatchedRateEnv.on_time_observation`) and the student
    its own: the student learns what the teacher would do had it seen the rates and rotors now."""
    t_cols, s_cols = cols
    n = env.num_envs
    by_teacher = np.ones(n, dtype=bool) if student is None else rng.random(n) < teacher_share
    s_obs = np.empty((steps, n, len(s_cols)), dtype=np.float32)
    labels = np.empty((steps, n, 4), dtype=np.float32)
    ended = np.empty((steps, n), dtype=bool)
    union = np.empty((steps, *obs.shape), dtype=np.float32) if keep_union else None
    privileged = privileged and env.on_time_observation is not None
    seen = np.empty_like(union) if keep_union and privileged else None
    errors: list[float] = []
    for k in range(steps):
        s_obs[k] = obs[:, s_cols]
        on_time = env.on_time_observation if privileged else None
        teacher_obs = obs if on_time is None else on_time
        if union is not None:
            union[k] = teacher_obs
            if seen is not None:
                seen[k] = obs
        labels[k] = teacher.act(np.ascontiguousarray(teacher_obs[:, t_cols]))
        action = labels[k] if student is None else np.where(by_teacher[:, None], labels[k],
                                                              student.act(s_obs[k]))
        obs, _, _, truncated, info = env.step(np.clip(action, -1.0, 1.0).astype(np.float32))
        if not by_teacher.all():
            errors.append(float(np.abs(info["setpoint"] - info["rate"])[~by_teacher].sum(1).mean()))
        ended[k] = truncated
        if truncated.any() and student is not None:
            by_teacher[truncated] = rng.random(int(truncated.sum())) < teacher_share
        if bar is not None and k % 50 == 49:
            bar.update(50)
    return s_obs, labels, ended, (float(np.mean(errors)) if errors else None), obs, (union, seen)


def nudge(union: np.ndarray, teacher: Teacher, cols: tuple[np.ndarray, np.ndarray], std: np.ndarray,
          step: float, rng: np.random.Generator, seen: np.ndarray | None = None
          ) -> tuple[np.ndarray, np.ndarray]:
    """Each observation with the student's columns moved by `step` standard deviations in a random
    direction (the teacher's other columns as they were), and the teacher's action there. `union` is
    what the teacher read; `seen`, where it differs, what the student read, moved the same way.

    Fitting the difference of the two actions to the teacher's fits the student's local gains, the
    slope of the action against each input it sees, which decide how the closed loop rings; the
    squared error alone fits the values and leaves the slopes to chance."""
    t_cols, s_cols = cols
    flat = union.reshape(-1, union.shape[-1]).copy()
    moved = (step * std * rng.standard_normal((len(flat), len(s_cols)))).astype(np.float32)
    flat[:, s_cols] += moved
    labels = np.concatenate([teacher.act(np.ascontiguousarray(chunk[:, t_cols]))
                             for chunk in np.array_split(flat, max(1, len(flat) // 8192))])
    if seen is None:
        return flat[:, s_cols], labels
    return seen.reshape(-1, seen.shape[-1])[:, s_cols] + moved, labels


def distill(cfg: DistillConfig) -> dict[str, Any]:
    """DAgger rounds, the fit, the run directory and its exported policy.onnx; the summary."""
    from stable_baselines3.common.vec_env import VecNormalize

    from fcemu.export.onnx_export import export_policy
    from fcemu.sim_bridge.vec_env import BatchedRateEnv
    from fcemu.training.train import make_model, make_vec_env, run_config

    memory = 1 if cfg.memory is None else cfg.memory
    if min(memory, cfg.rounds, cfg.steps, cfg.envs) < 1 or not 0.0 <= cfg.beta <= 1.0:
        raise DistillError("--memory, --rounds, --steps and --envs must be >= 1 and --beta in [0, 1]")
    for name in ("gain_weight", "gain_step"):
        value = getattr(cfg, name)
        if not (np.isfinite(value) and value >= 0.0):
            raise DistillError(f"--{name.replace('_', '-')} must be finite and >= 0, got {value}")
    if cfg.gain_weight and not cfg.gain_step:
        raise DistillError("--gain-weight needs a --gain-step above 0")
    if cfg.airframe_pool is not None:  # a pool's twins fly other quads than --airframe: each its own teacher
        cfg = replace(cfg, per_twin=True, gain_weight=0.0)
    if cfg.per_twin and cfg.gain_weight:
        raise DistillError("--per-twin teaches without the gain match (--gain-weight 0): its nudged samples "
                           "are labelled after the rounds, when the twins' airframes are drawn anew")
    teacher = make_teacher(cfg.teacher, cfg.airframe, cfg.privileged, per_twin=cfg.per_twin)
    train_cfg, spec = student_train_config(cfg, teacher)
    torch.set_num_threads(train_cfg.threads)
    torch.manual_seed(cfg.seed)
    union = union_spec(teacher.spec, spec)
    cols = (columns(teacher.spec, union), columns(spec, union))
    env_kwargs = {**train_cfg.env_kwargs(), "memory": union.memory, "obs_fields": union.fields,
                  "integral_leak": union.integral_leak, "rms_leak": union.rms_leak}
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    config = run_config(train_cfg)
    config["distill"] = {**asdict(cfg), "teacher": str(cfg.teacher)}
    (out / "config.json").write_text(json.dumps(config, indent=2) + "\n")

    venv = VecNormalize(make_vec_env(train_cfg), norm_obs=True, norm_reward=False, clip_obs=np.inf)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # PPO's batch size against one twin's rollout: never rolled out
        model = make_model(train_cfg, venv, out / "tb")
    env = BatchedRateEnv(cfg.envs, on_time_view=cfg.privileged, truth_view=is_model_based(cfg.teacher),
                         **env_kwargs)
    if cfg.per_twin:
        teacher.follow(env)
    rng = np.random.default_rng(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    data, student, history = Dataset(), None, []
    obs, _ = env.reset(seed=cfg.seed * 1000)
    bar = None
    if cfg.progress:
        from tqdm import tqdm

        bar = tqdm(total=cfg.rounds * cfg.steps, unit="step", desc="distill", file=sys.stderr)
    t0 = time.perf_counter()
    for r in range(cfg.rounds):
        share = cfg.beta ** r
        s_obs, labels, ended, flown_error, obs, (union_obs, seen_obs) = fly(
            env, teacher, student, cols, cfg.steps, share, rng, obs, bar, keep_union=bool(cfg.gain_weight),
            privileged=cfg.privileged)
        data.add(s_obs, labels, ended)
        if student is None:  # the observation statistics, from the teacher's flights (as VecNormalize's)
            venv.obs_rms.mean = s_obs.reshape(-1, s_obs.shape[-1]).mean(0).astype(np.float64)
            venv.obs_rms.var = s_obs.reshape(-1, s_obs.shape[-1]).var(0).astype(np.float64)
            venv.obs_rms.count = float(s_obs.shape[0] * s_obs.shape[1])
            student = Student(model, venv.obs_rms.mean, venv.obs_rms.var, venv.epsilon)
        if union_obs is not None:
            data.add_nudged(*nudge(union_obs, teacher, cols, np.sqrt(venv.obs_rms.var), cfg.gain_step, rng,
                                   seen_obs))
            del union_obs, seen_obs
        if bar is not None:
            bar.set_postfix_str(f"fitting on {data.size} samples")
        losses = fit(student, data, cfg.fit_steps * (3 if r == cfg.rounds - 1 else 1), cfg, gen)
        history.append({"round": r, "teacher_share": share, "samples": data.size,
                        "student_flown_error": flown_error, **losses})
        if bar is not None:
            bar.set_postfix(mse=f"{losses['imitation_mse']:.4f}",
                            err="-" if flown_error is None else f"{flown_error:.3f}")
    if bar is not None:
        bar.close()
    wall = time.perf_counter() - t0
    env.close()
    model.num_timesteps = cfg.rounds * cfg.steps * cfg.envs
    model.save(out / "model.zip")
    venv.save(str(out / "vecnormalize.pkl"))
    venv.close()
    config.update(trained_steps=model.num_timesteps, train_wall_s=round(wall, 1))
    (out / "config.json").write_text(json.dumps(config, indent=2) + "\n")
    export = export_policy(out, out / "policy.onnx")
    summary = {"run": str(out), "teacher": str(cfg.teacher), "observation": json.loads(spec.to_json()),
               "inputs": spec.size, "net_arch": list(cfg.net_arch), "env_steps": model.num_timesteps,
               "wall_s": round(wall, 1), "history": history, "export": export}
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def distill_command(args) -> int:
    from fcemu.firmware.errors import UserError

    try:
        cfg = from_args(args)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    try:
        summary = distill(cfg)
    except ValueError as exc:  # DistillError, a bad TrainConfig value, an ExportError
        raise UserError(str(exc)) from None
    if args.json:
        print(json.dumps(summary, default=float))
    else:
        last = summary["history"][-1]
        print(f"{summary['run']}: student {summary['inputs']} inputs, {summary['net_arch']}, "
              f"{summary['env_steps']} env steps in {summary['wall_s']:.0f} s, imitation mse "
              f"{last['imitation_mse']:.5f}, exported {summary['export']['out']} "
              f"(parity {summary['export']['parity_max_abs_diff']:.1e})")
    return 0
