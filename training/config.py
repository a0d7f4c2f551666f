"""One declaration of a training run's options: `TrainConfig`, and the command line made from it.

Every option of `fcemu train` is a field here; its metadata (help, choices, nargs, a
parser for the raw value) is all the command line needs, so `fcemu train`, `fcemu bench
train` and `fcemu sweep` generate their options from this class (`add_arguments`) and
build it back (`from_args`), as CleanRL builds its command line from one dataclass with
tyro. The environment's options (task, airframe, reward, ...) are not declared here: they
are `sim_bridge.env_config.EnvConfig`'s, added to `TrainConfig` as fields by
`with_env_options`, with training's own defaults in `TRAIN_RECIPE`. This module imports
neither torch nor MuJoCo: `fcemu --help` builds every parser.
"""

from __future__ import annotations

import argparse
import ast
import copy
import dataclasses
import math
import typing
from dataclasses import dataclass, field
from typing import Any

from fcemu.firmware.observation import DEFAULT_LEAK, DEFAULT_RMS_LEAK
from fcemu.firmware.timing import available_cpus
from fcemu.sim_bridge.env_config import ENV_FIELDS, EnvConfig, add_option, command_options
from fcemu.sim_bridge.reward import REWARDS

# ── Defaults per algorithm ─────────────────────────────────────────────────────────────
# 1 ms steps and 1000-step episodes: a horizon of ~100 ms (γ 0.99, λ 0.95: a yaw rise and
# its settling) credits an action with what it does to the rate, not with the whole episode.
# Exploration is state-dependent (gSDE, noise redrawn once per rollout): the motors filter
# away white noise on every 1 ms action, so it teaches the critic nothing and PPO drifts
# into spinning the vehicle.
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
# After a warm start (or from --init) PPO refines a network that already flies: its
# advantages are mostly noise, and five full epochs per rollout walk the fitted actor away
# from the PID's Error before the signal accumulates. A KL limit (TRPO's target) stops an
# update's epochs early.
WARM_START_ROUNDS = 3
WARM_START_STEPS = 1500  # per environment copy and round
WARM_START_TARGET_KL = 0.01
SELECT = ("bar", "error")  # how `--export best` ranks evaluations (quick_eval.selection_key)


# ── The environment's options, declared in EnvConfig ───────────────────────────────────
# Training's recipe where it departs from the environment's defaults: a collective drawn
# over the range a pilot flies (the policy must not learn one throttle), and the reward
# without the paper's clip (its gradient vanishes past an error of 3·Ω_max).
TRAIN_RECIPE: dict[str, Any] = {"throttle": (0.5, 0.9), "reward": "unclipped"}
LEAKS = ("integral_leak", "rms_leak")  # in the env only with their field: `TrainConfig.obs_leaks`


def with_env_options(cls: type, recipe: dict[str, Any], exclude: dict[str, str] | None = None,
                     notes: dict[str, str] | None = None) -> type:
    """The dataclass `cls` with one field per command-line option of `EnvConfig` (less `exclude`,
    EnvConfig fields each with the reason), its default the env's unless `recipe` overrides it;
    `notes` adds to an option's help what it means here. `env_options` (on the class) maps each
    added field to its `CommandOption`."""
    options = command_options(recipe, exclude)
    fields = []
    for name, o in options.items():
        meta = {**o.metadata, "help": f"{o.metadata['help']}; {notes[name]}"} if name in (notes or {}) \
            else o.metadata
        fields.append((name, o.hint, field(default=o.default, metadata=meta)))
    made = dataclasses.make_dataclass(cls.__name__, fields, bases=(cls,),
                                      namespace={"__doc__": cls.__doc__, "__module__": cls.__module__})
    made.__qualname__ = cls.__qualname__
    made.env_options = options
    return made


def env_values(cfg: Any) -> dict[str, Any]:
    """The environment options a configuration made by `with_env_options` holds, by EnvConfig field."""
    return {o.field: getattr(cfg, name) for name, o in type(cfg).env_options.items()}


def check_env_options(cfg: Any) -> None:
    """Each option parsed as its command line would (`--throttle 0.7` is 0.7, not [0.7])."""
    for name, o in type(cfg).env_options.items():
        parse = o.metadata.get("parse")
        if parse is not None:
            setattr(cfg, name, parse(getattr(cfg, name)))


def parse_hp(items: list[str] | dict[str, Any] | None) -> dict[str, Any]:
    """`key=value` pairs; values are Python literals (numbers, lists, dicts), else strings."""
    if isinstance(items, dict):
        return dict(items)
    hp: dict[str, Any] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--hp {item!r}: expected key=value")
        try:
            hp[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            hp[key] = value
    return hp


# The parallelism of a command is --jobs; --threads is its former spelling, still accepted.
JOBS_FLAGS = ("--jobs", "--threads")


def option(default: Any, help: str, **argparse_kwargs: Any) -> Any:
    """A field with its command-line description: `help` plus any argparse keyword
    (choices, nargs, metavar), `parse`, applied to the parsed value, and `flags`, the
    option's spellings where they are not the field's name (`env_config.add_option`)."""
    return field(default=default, metadata={"help": help, **argparse_kwargs})


# ── The configuration ──────────────────────────────────────────────────────────────────
@dataclass
class TrainConfig:
    algo: str = option("ppo", "RL algorithm (SB3 / sb3-contrib)", choices=tuple(ALGOS))
    steps: int = option(3_000_000, "environment steps (1 ms each)")
    seed: int = option(0, "seed of the training twins (their commands, drawn airframes and noise) and of "
                          "the networks' initial weights and exploration")
    out: str | None = option(None, "run directory (default runs/ALGO)")
    integral: bool = option(False, "add a leaky integral of the rate error to the observation "
                                   "(rate_error_integral)")
    error_rms: bool = option(False, "add the leaky RMS of the rate error to the observation "
                                    "(rate_error_rms): what lets a policy see that it oscillates")
    motor_output: bool = option(False, "add the previous tick's motor outputs to the observation "
                                       "(motor_output): what --action-rate-penalty's |Δu| depends on")
    rate: bool = option(False, "add the gyro's body rates to the observation (rate): what the body's "
                               "gyroscopic torque depends on")
    loop_delay: bool = option(False, "add the loop's configured delay to the observation (loop_delay: "
                                     "the ESC's and the gyro filters' ticks): what lets the gain fall "
                                     "where the loop is long")
    authority: bool = option(False, "add each axis's angular acceleration per unit of torque command, "
                                    "estimated in flight from the gyro and the rotor speeds (authority): "
                                    "what tells one quad from another")
    squash: bool = option(False, "PPO/TRPO: tanh-squashed actions (gSDE's squash_output); what lets "
                                 "--action-rate-penalty smooth the motors instead of saturating them")
    envs: int | None = option(None, "parallel twins (default: per algorithm)")
    norm_reward: bool | None = option(None, "VecNormalize reward scaling (default: per algorithm)")
    norm_obs: bool = option(True, "VecNormalize observation normalisation (folded into the exported "
                                  "ONNX graph)")
    obs_clip: float = option(10.0, "VecNormalize's clip of the normalised observation, in standard "
                                   "deviations (SB3's 10); 0: none, so the export folds the "
                                   "normalisation into the first layer (about 2 µs less per inference)")
    hp: dict[str, Any] = field(default_factory=dict, metadata={
        "help": "override algorithm hyper-parameters", "nargs": "*", "metavar": "KEY=VALUE",
        "parse": parse_hp})
    checkpoint_every: int = option(1_000_000, "steps between checkpoints")
    eval_every: int = option(0, "steps between in-training evaluations against the PID (0: none)")
    eval_commands: int = option(64, "fixed commands per in-training evaluation")
    eval_episodes: int = option(1000, "final evaluation commands through the firmware loop (0: skip)")
    eval_seed: int = option(1, "seed of the evaluation commands")
    export: str = option("best", "best: the in-training evaluation's best (needs --eval-every); "
                                 "final: the last model", choices=("best", "final"))
    select: str = option("bar", "what `best` means: bar (meeting the shipped policy's bar first, then "
                                "the Error ratio, penalised for motor roughness beyond the bar's 1.5 × "
                                "the PID's) or error (the lowest Error ratio, however rough)", choices=SELECT)
    threads: int = option(0, "torch threads (0: one per CPU this process may use)", flags=JOBS_FLAGS,
                          metavar="JOBS")
    progress: bool = option(True, "progress bar")
    warm_start: str | None = option(
        None, "before RL, fit the actor to a PID preset's outputs on the training flights (behaviour cloning "
              "with DAgger rounds) and the critic to their returns (training.warm_start): pid, pid:paper, or "
              "schedule:NAME|FILE, presets by each drawn airframe's loop delay (training/teachers/)",
        metavar="PRESET")
    init: str | None = option(
        None, "fine-tune: start from a trained run's networks, optimiser state and normalisation statistics "
              "instead of fresh ones: a run directory (its final model) or one checkpoint .zip of the same "
              "algorithm and network sizes, and the same observation or one this run adds fields to "
              "(their inputs start at zero weight: training.init)", metavar="RUN|ZIP")
    warm_start_rounds: int = option(WARM_START_ROUNDS, "warm start: rounds of flights and fits (the first "
                                                       "flown by the teacher, the others by the network)")
    warm_start_steps: int = option(WARM_START_STEPS, "warm start: steps per environment copy in each round")
    caps_temporal: float = option(0.0, "PPO: CAPS temporal smoothness weight λ_T, ‖π(s_t) − π(s_t+1)‖ "
                                        "(training.caps)")
    caps_spatial: float = option(0.0, "PPO: CAPS spatial smoothness weight λ_S, ‖π(s) − π(s̃)‖, "
                                       "s̃ ~ N(s, caps_sigma²)")
    caps_sigma: float = option(0.05, "CAPS spatial noise, in normalised observation units")
    anchor: float = option(0.0, "PPO after --warm-start or --init: weight of the anchor, the mean squared "
                                "difference of the policy's action from the teacher's on the warm start's "
                                "data (after --init: from the loaded policy's own on its flights), in PPO's "
                                "loss (training.regularised_ppo)")
    anchor_from_ticks: int = option(0, "--anchor only on the warm start's samples from airframes whose loop "
                                       "delay (ESC + gyro) is at least this many ticks: hold the policy to "
                                       "the teacher where delay makes it fragile, leave PPO free elsewhere")

    def __post_init__(self) -> None:
        check_env_options(self)
        if self.algo not in ALGOS:
            raise ValueError(f"unknown algorithm {self.algo!r}; choose one of {tuple(ALGOS)}")
        for flag, leak in (("--integral-leak", self.integral_leak), ("--rms-leak", self.rms_leak)):
            if not 0.0 <= leak < 1.0:
                raise ValueError(f"{flag} must be in [0, 1), got {leak}")
        if self.threads < 0:
            raise ValueError(f"--jobs must be >= 0 (0: one per available CPU), got {self.threads}")
        self.threads = self.threads or available_cpus()
        if not (math.isfinite(self.obs_clip) and self.obs_clip >= 0.0):
            raise ValueError(f"--obs-clip must be finite and >= 0 (0: no clip), got {self.obs_clip}")
        if self.integral_leak != DEFAULT_LEAK and not self.integral:
            raise ValueError("--integral-leak sets the integral's leak: it needs --integral")
        if self.rms_leak != DEFAULT_RMS_LEAK and not self.error_rms:
            raise ValueError("--rms-leak sets the RMS's leak: it needs --error-rms")
        if self.reward == "paper" and tuple(self.axis_weights) != (1.0, 1.0, 1.0):
            raise ValueError("axis weights need --reward unclipped")
        if self.select not in SELECT:
            raise ValueError(f"unknown selection {self.select!r}; choose one of {SELECT}")
        if self.reward not in REWARDS:
            raise ValueError(f"unknown reward {self.reward!r}; choose one of {REWARDS}")
        if self.squash and self.algo not in ("ppo", "trpo"):
            raise ValueError(f"--squash is for PPO and TRPO; {self.algo.upper()} squashes already")
        self.axis_weights = tuple(self.axis_weights)
        if self.out is None:
            self.out = f"runs/{self.algo}"
        if self.warm_start is not None:
            if self.algo not in ("ppo", "trpo"):
                raise ValueError(f"--warm-start is for PPO and TRPO (actor-critic), not {self.algo.upper()}")
            from fcemu.training.warm_start_teacher import check_teacher

            check_teacher(self.warm_start)
        if self.init is not None and self.warm_start is not None:
            raise ValueError("--init starts from a trained network; --warm-start would fit a fresh one to a "
                             "teacher first: give one of them")
        if self.warm_start_rounds < 1 or self.warm_start_steps < 1:
            raise ValueError(f"--warm-start-rounds and --warm-start-steps must be >= 1, got "
                             f"{self.warm_start_rounds} and {self.warm_start_steps}")
        if self.anchor and not ((self.warm_start or self.init) and self.algo == "ppo"):
            raise ValueError("--anchor keeps PPO near the warm start's teacher or the --init policy: it "
                             "needs --algo ppo and --warm-start or --init")
        if not (math.isfinite(self.anchor) and self.anchor >= 0.0):
            raise ValueError(f"--anchor must be finite and >= 0, got {self.anchor}")
        if not (math.isfinite(self.action_rate_after) and self.action_rate_after >= 0.0):
            raise ValueError(f"--action-rate-after must be finite and >= 0 (action_rate_after_s), "
                             f"got {self.action_rate_after}")
        if self.action_rate_after and not self.action_rate_penalty:
            raise ValueError("--action-rate-after gates --action-rate-penalty: give the penalty too")
        if self.anchor_from_ticks < 0 or (self.anchor_from_ticks and not (self.anchor and self.warm_start)):
            raise ValueError(f"--anchor-from-ticks must be >= 0 and goes with --anchor after --warm-start, "
                             f"got {self.anchor_from_ticks} with --anchor {self.anchor}")
        if self.caps and self.algo != "ppo":
            raise ValueError(f"CAPS (caps_temporal, caps_spatial) is for PPO, not {self.algo.upper()}")
        if not 0.0 <= self.randomize_share <= 1.0 or (self.randomize_share != 1.0 and self.randomize is None):
            raise ValueError(f"--randomize-share must be in [0, 1] and needs --randomize, "
                             f"got {self.randomize_share}")
        try:
            self.env_config()  # every other check of the environment's options (airframe, ranges, ...)
        except (OSError, KeyError) as exc:
            raise ValueError(f"--airframe {self.airframe}: {exc}") from None

    @property
    def caps(self) -> bool:
        return bool(self.caps_temporal or self.caps_spatial)

    @property
    def obs_fields(self) -> tuple[str, ...]:
        from fcemu.firmware.observation import (
            AUTHORITY,
            FIELDS,
            INTEGRAL,
            LOOP_DELAY,
            MOTOR_OUTPUT,
            RATE,
            RMS,
        )

        return (*FIELDS, *((INTEGRAL,) if self.integral else ()), *((RMS,) if self.error_rms else ()),
                *((MOTOR_OUTPUT,) if self.motor_output else ()), *((RATE,) if self.rate else ()),
                *((LOOP_DELAY,) if self.loop_delay else ()), *((AUTHORITY,) if self.authority else ()))

    @property
    def obs_leaks(self) -> dict[str, float]:
        """The λ of each integrated field in the observation, as `EnvConfig` keywords."""
        return {**({"integral_leak": self.integral_leak} if self.integral else {}),
                **({"rms_leak": self.rms_leak} if self.error_rms else {})}

    @property
    def n_envs(self) -> int:
        return self.envs or ALGOS[self.algo]["envs"]

    @property
    def hyper(self) -> dict[str, Any]:
        refining = (self.warm_start or self.init) and self.algo == "ppo"  # a network that already flies
        warm = {"target_kl": WARM_START_TARGET_KL} if refining else {}
        hp = copy.deepcopy({**ALGOS[self.algo]["hp"], **warm, **self.hp})  # SB3 writes into policy_kwargs
        if self.squash:
            hp["policy_kwargs"] = {**hp.get("policy_kwargs", {}), "squash_output": True}
        return hp

    @property
    def normalise_reward(self) -> bool:
        return ALGOS[self.algo]["norm_reward"] if self.norm_reward is None else self.norm_reward

    def env_kwargs(self) -> dict[str, Any]:
        """The training env's `EnvConfig` keywords: the observation and reward always, the other
        options where they differ from the env's default (so a run's config.json names what it
        changed)."""
        kwargs = {"task": self.task, "memory": self.memory, "obs_fields": self.obs_fields, **self.obs_leaks,
                  "action_mapping": self.action_mapping, "throttle": self.throttle, "reward": self.reward,
                  "axis_weights": tuple(self.axis_weights), "action_rate_penalty": self.action_rate_penalty}
        for name, value in env_values(self).items():
            if name not in kwargs and name not in LEAKS and value != ENV_FIELDS[name].default:
                kwargs[name] = value
        return kwargs

    def env_config(self):
        """The training env's configuration (`sim_bridge.env_config.EnvConfig`)."""
        return EnvConfig(**self.env_kwargs())


TrainConfig = with_env_options(TrainConfig, TRAIN_RECIPE)


# ── The command line, generated from the fields ────────────────────────────────────────
FIELDS = {f.name: f for f in dataclasses.fields(TrainConfig)}
_TYPES = typing.get_type_hints(TrainConfig)


def add_arguments(parser: argparse.ArgumentParser, exclude: tuple[str, ...] = (),
                  defaults: dict[str, Any] | None = None, only_given: bool = False) -> None:
    """One `--flag` per field of `TrainConfig` (minus `exclude`), its help and choices from
    the field's metadata; `defaults` replaces a field's default for this command. With
    `only_given`, an option not on the command line is absent from the namespace (so a
    configuration file can fill it in)."""
    defaults = defaults or {}
    for name, f in FIELDS.items():
        if name in exclude:
            continue
        default = defaults.get(name, f.default_factory() if f.default_factory is not dataclasses.MISSING
                               else f.default)
        add_option(parser, name, _TYPES[name], default, f.metadata, only_given)


def from_args(args: argparse.Namespace, **overrides: Any) -> TrainConfig:
    """The `TrainConfig` an `add_arguments` parser produced; `overrides` win. Bad values
    raise ValueError (the command line turns it into `fcemu: error: ...`)."""
    values: dict[str, Any] = {}
    for name, f in FIELDS.items():
        if name in overrides or not hasattr(args, name):
            continue
        value = getattr(args, name)
        parse = f.metadata.get("parse")
        values[name] = parse(value) if parse is not None else value
    return TrainConfig(**{**values, **overrides})
