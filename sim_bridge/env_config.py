"""`EnvConfig`: every option of the rate-control task, declared once, with its command line.

Each field carries its command-line description (help, the value's type on a command
line, argparse's choices, nargs, metavar, and a `parse` of the raw value), or the reason
it has none (`excluded`). `fcemu train`, `sweep`, `bench train` and `distill` generate
their environment options from these fields (`training.config.env_options`), and `fcemu
eval`, `bound` and `bench sim` their `--airframe` (`add_env_arguments`), so a new task
option is added here and nowhere else. Where a command's default differs from the
environment's (a training recipe), the command says so in one mapping of overrides.

This module imports neither MuJoCo nor Gymnasium: the command lines are built from it.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from fcemu.firmware.action import ACTION_MAPPINGS, DEFAULT_ACTION_MAPPING
from fcemu.firmware.observation import DEFAULT_LEAK, DEFAULT_RMS_LEAK, FIELDS, ObservationSpec
from fcemu.sim_bridge.airframe import DEFAULT_AIRFRAME, Airframe, load_airframe
from fcemu.sim_bridge.randomization import (
    BUS_PARAMETERS,
    RELATIVE,
    Randomization,
    randomization_path,
    ranges_for,
)
from fcemu.sim_bridge.reward import REWARDS, UNWEIGHTED, RateReward
from fcemu.sim_bridge.sensor_model import SensorNoise
from fcemu.sim_bridge.tasks import HOLD_S, OMEGA_MAX, REST_S, TRAINING_TASKS

TASKS = TRAINING_TASKS
RANDOMIZE_KEYS = ("mass", "inertia", "kf", "km")  # also the draw order
DEFAULT_EPISODE_S = {"episodic": 1.0, "continuous": 10.0}


def parse_throttle(value: Any) -> Any:
    """A command line's one value or LO HI as a float or a (LO, HI) pair; anything else as it is."""
    if not isinstance(value, list | tuple):
        return value
    if len(value) not in (1, 2):
        raise ValueError(f"--throttle takes one value or LO HI, not {len(value)} values")
    return float(value[0]) if len(value) == 1 else (float(value[0]), float(value[1]))


def parse_ranges(value: Any) -> Any:
    """`--randomize none` is no randomisation."""
    return None if value == "none" else value


def env_option(default: Any, help: str, cli: Any = None, excluded: str | None = None,
               name: str | None = None, **argparse_kwargs: Any) -> Any:
    """A task option: its default and help, and either `cli`, the type its value has on a
    command line (with any argparse keyword and `parse`), or why no command line takes it
    (`excluded`). `name`: the option's name on command lines where it differs."""
    if (cli is None) == (excluded is None):
        raise TypeError("an option is either on the command line (cli=TYPE) or excluded with a reason")
    meta = {"help": help, "cli": cli, "excluded": excluded, "name": name, **argparse_kwargs}
    return field(default=default, metadata={k: v for k, v in meta.items() if v is not None})


@dataclass(frozen=True)
class EnvConfig:
    """Everything that defines a task; shared by the single and the batched environment."""

    task: str = env_option("episodic", "the task flown: episodic (a step from rest per episode) or "
                                       "continuous (pulse schedules)", cli=str, choices=TASKS)
    memory: int = env_option(1, "observation history length m", cli=int)
    action_mapping: str = env_option(DEFAULT_ACTION_MAPPING, "how the 4 actions become motor commands",
                                     cli=str, choices=ACTION_MAPPINGS)
    throttle: float | tuple[float, float] | None = env_option(
        None, "collective for the throttle mapping: one value, or LO HI drawn per episode (none: the "
              "airframe's hover throttle)", cli=float | tuple[float, float] | None, nargs="+", metavar="T",
        parse=parse_throttle)
    episode_s: float | None = env_option(None, "episode length in s (default: 1 s episodic, 10 s continuous)",
                                         cli=float | None)
    noise: SensorNoise | None = env_option(  # noqa: RUF009 (a field specifier, as dataclasses.field)
        None, "sensor noise (None: the airframe's own gyro noise)",
        excluded="an object, not a value: the airframe file's gyro_noise_std sets it, and --randomize ranges "
                 "redraw it per episode")
    # key -> ± fraction, or ranges (a `sim_bridge.randomization` file, e.g. "iris"); redrawn per episode
    randomize: Mapping[str, float] | Randomization | str | Path | None = env_option(  # noqa: RUF009
        None, "domain randomisation: draw each episode's airframe (mass, inertia, motor constants, latency, "
              "noise, damping, battery) from ranges, a shipped name (iris: "
              "sim_bridge/airframes/iris.randomization.json) or a file; none: the nominal airframe",
        cli=str | None, metavar="NAME|FILE", parse=parse_ranges)
    omega_max: float = env_option(OMEGA_MAX, "the commands' bound on each body rate, rad/s (the paper's)",
                                  cli=float)
    action_rate_penalty: float = env_option(0.0, "weight of Neuroflight's output-oscillation penalty "
                                                 "(mean |Δu| per step); use with --squash", cli=float)
    airframe: Airframe | str = env_option(  # noqa: RUF009
        DEFAULT_AIRFRAME, "airframe to fly: sim_bridge/airframes/NAME.json (e.g. iris_realistic, every "
                          "effect on) or a path", cli=str, metavar="NAME|FILE")
    dt: float = env_option(0.001, "physics step, s",
                           excluded="the firmware's 1 kHz loop: an exported policy's contract fixes it")
    hold_s: tuple[float, float] = env_option(HOLD_S, "continuous task: how long a command is held, drawn "
                                                     "from LO..HI s", cli=tuple[float, float],
                                             metavar=("LO", "HI"))
    rest_s: tuple[float, float] | None = env_option(
        REST_S, "continuous task: how long the setpoint rests at zero between commands, drawn from LO..HI s",
        cli=tuple[float, float], metavar=("LO", "HI"))
    obs_fields: tuple[str, ...] = env_option(
        FIELDS, "firmware.observation fields, e.g. + rate_error_integral",
        excluded="each command builds it from its own flags: train's --integral, --error-rms, "
                 "--motor-output, --loop-delay; distill's --fields")
    reward: str = env_option("paper", "paper: −clip(Σ|e|/(3·Ω_max), 0, 1); unclipped: the same without "
                                      "the clip", cli=str, choices=REWARDS)
    axis_weights: tuple[float, float, float] = env_option(
        UNWEIGHTED, "weights of the roll, pitch, yaw error in the unclipped reward",
        cli=tuple[float, float, float], metavar=("R", "P", "Y"))
    relative_error: float = env_option(
        0.0, "unclipped reward: weight K of the error relative to the command's step, "
             "−K·Σ w·|e|/(|e0| + 0.1 rad/s)/3, e0 the error when the command began (the Success metric's "
             "scale: a small step's steady residual counts as much as a large step's)", cli=float)
    integral_leak: float = env_option(DEFAULT_LEAK, "the integral's λ per step (time constant 1/(1 − λ) "
                                                    "steps); λ → 1 approaches a true integrator", cli=float)
    rms_leak: float = env_option(DEFAULT_RMS_LEAK, "the RMS's μ per step (time constant 1/(1 − μ) steps)",
                                 cli=float)
    inflight_share: float = env_option(
        0.0, "episodic task: the share of episodes that start in flight, every rotor at the speed the "
             "episode's throttle commands (as `fcemu eval --task inflight`); the others start from rest",
        cli=float)
    randomize_share: float = env_option(1.0, "with --randomize: the share of episodes drawn from the ranges; "
                                             "the others fly the nominal airframe", cli=float)
    airframe_pool: tuple[Airframe, ...] | str | None = env_option(
        None, "fly many quads: each episode's airframe drawn from a pool (draw:COUNT:SEED: COUNT quads of "
              "`fcemu twin draw`'s distribution; a folder of airframe files; files separated by commas), "
              "each with its own sensor effects; rotor speeds observed as shares of each one's top speed. "
              "--airframe is then only the reference the twins are built from",
        cli=str | None, metavar="draw:COUNT:SEED|DIR|FILES", parse=parse_ranges)
    # the action-rate penalty only once the setpoint has been held this long (s): a settled
    # response must be quiet, a step may be sharp (0: every step, Neuroflight's penalty)
    action_rate_after_s: float = env_option(
        0.0, "apply --action-rate-penalty only once the setpoint has been held this many seconds: quiet "
             "when settled, free in a step (0: every step)", cli=float, name="action_rate_after")

    def __post_init__(self) -> None:
        if self.task not in TASKS:
            raise ValueError(f"unknown task {self.task!r}; choose one of {TASKS}")
        if self.action_mapping not in ACTION_MAPPINGS:
            raise ValueError(f"unknown action mapping {self.action_mapping!r}; known: {ACTION_MAPPINGS}")
        if not isinstance(self.airframe, Airframe):
            object.__setattr__(self, "airframe", load_airframe(self.airframe))
        if isinstance(self.randomize, str | Path):  # relative ranges are built for the airframe
            object.__setattr__(self, "randomize", ranges_for(self.airframe, self.randomize))
        if not isinstance(self.randomize, Randomization):
            unknown = set(self.randomize or {}) - set(RANDOMIZE_KEYS)
            if unknown:
                raise ValueError(f"cannot randomise {sorted(unknown)}; known: {RANDOMIZE_KEYS}")
            if any(not 0.0 <= f < 1.0 for f in (self.randomize or {}).values()):
                raise ValueError(
                    f"randomisation fractions must be in [0, 1), got {dict(self.randomize or {})}")
        if not 0.0 <= self.inflight_share <= 1.0:
            raise ValueError(f"inflight_share is a share of episodes in [0, 1], got {self.inflight_share}")
        if not 0.0 <= self.randomize_share <= 1.0:
            raise ValueError(f"the randomised share of episodes must be in [0, 1], "
                             f"got {self.randomize_share}")
        if self.randomize_share < 1.0 and not isinstance(self.randomize, Randomization):
            raise ValueError("a randomised share below 1 needs randomisation ranges (e.g. randomize='iris')")
        if isinstance(self.randomize, Randomization):
            self.randomize.check_airframe(self.airframe)
        if isinstance(self.airframe_pool, str | Path):
            from fcemu.sim_bridge.airframe_draw import airframe_pool

            object.__setattr__(self, "airframe_pool", airframe_pool(str(self.airframe_pool)))
        if isinstance(self.airframe_pool, list):
            object.__setattr__(self, "airframe_pool", tuple(self.airframe_pool))
        if self.airframe_pool is not None:
            self._check_pool()
        if self.noise is None and self.base_airframe.gyro_noise_std:  # the airframe's own gyro noise
            object.__setattr__(self, "noise", SensorNoise(gyro_std=self.base_airframe.gyro_noise_std))
        throttle = parse_throttle(self.throttle)
        if throttle is None:
            throttle = self.base_airframe.hover_throttle()
        object.__setattr__(self, "throttle", throttle)
        for name in ("obs_fields", "hold_s", "rest_s"):  # gym.make and JSON give lists
            if isinstance(getattr(self, name), list):
                object.__setattr__(self, name, tuple(getattr(self, name)))
        if self.n_steps < 1:
            raise ValueError(f"episode_s={self.episode_s} is shorter than one step of {self.dt} s")
        object.__setattr__(self, "axis_weights", self.rate_reward.axis_weights)  # validates the reward
        if not (math.isfinite(self.action_rate_after_s) and self.action_rate_after_s >= 0.0):
            raise ValueError(f"action_rate_after_s must be finite and >= 0, got {self.action_rate_after_s}")

    def _check_pool(self) -> None:
        if not self.airframe_pool:
            raise ValueError("an airframe pool needs at least one airframe")
        if self.randomize:
            raise ValueError("an airframe pool draws each episode's airframe: give it or --randomize ranges, "
                             "not both")
        pwm = (self.base_airframe.motor.pwm_min, self.base_airframe.motor.pwm_max)
        odd = [a.name for a in self.airframe_pool if (a.motor.pwm_min, a.motor.pwm_max) != pwm]
        if odd:
            raise ValueError(f"the pool's airframes share the reference's PWM range {pwm[0]:g}-{pwm[1]:g} "
                             f"µs; {', '.join(odd[:3])} do not")

    def _pool_has(self, effect: Any) -> bool:
        """Whether some airframe of the pool has `effect` (a predicate of an airframe)."""
        return any(effect(a) for a in self.airframe_pool or ())

    @property
    def base_airframe(self) -> Airframe:
        assert isinstance(self.airframe, Airframe)
        return self.airframe

    @property
    def n_steps(self) -> int:
        return round((self.episode_s or DEFAULT_EPISODE_S[self.task]) / self.dt)

    @property
    def observation_spec(self) -> ObservationSpec:
        return ObservationSpec(memory=self.memory, fields=tuple(self.obs_fields),
                               rotor_speed_scale=1.0 / self.base_airframe.motor.max_rotor_speed,
                               integral_leak=self.integral_leak, rms_leak=self.rms_leak,
                               per_airframe_rotor_speed=self.airframe_pool is not None)

    @property
    def noisy(self) -> bool:
        """Whether an episode draws sensor noise: the configured noise, or a randomised gyro noise."""
        return (self.noise is not None and self.noise.enabled) or self.draws_gyro_noise

    @property
    def late_sensors(self) -> bool:
        """Whether some episode's gyro or ESC telemetry reaches the firmware late or lossy: only then
        is there an observation of the readings as sampled to keep (`RateTask`'s `on_time_view`)."""
        late = BUS_PARAMETERS | {"gyro_delay_ticks"}
        drawn = isinstance(self.randomize, Randomization) and any(key in self.randomize for key in late)
        base = self.base_airframe
        return (drawn or bool(base.gyro_delay_ticks) or base.telemetry_effects
                or self._pool_has(lambda a: a.gyro_delay_ticks or a.telemetry_effects))

    @property
    def loses_telemetry(self) -> bool:
        """Whether some episode's ESC telemetry may lose frames (each episode then draws a seed for it)."""
        drawn = isinstance(self.randomize, Randomization) and "esc_telemetry_loss" in self.randomize
        pool = self._pool_has(lambda a: a.esc_telemetry_loss)
        return drawn or bool(self.base_airframe.esc_telemetry_loss) or pool

    @property
    def draws_gyro_noise(self) -> bool:
        """The randomisation draws each episode's gyro noise (it replaces `noise.gyro_std`)."""
        drawn = isinstance(self.randomize, Randomization) and self.randomize.draws_gyro_noise
        return drawn or self._pool_has(lambda a: a.gyro_noise_std)

    @property
    def gyro_is_not_rate(self) -> bool:
        """Whether some episode's gyro may read other than the rate: noise, vibration or delay."""
        drawn = isinstance(self.randomize, Randomization) and self.randomize.draws_gyro_effects
        pool = self._pool_has(lambda a: a.gyro_effects)
        return self.noisy or self.base_airframe.gyro_effects or drawn or pool

    def episode_noise(self, airframe: Airframe) -> SensorNoise | None:
        """The sensor noise of an episode flying `airframe` (a draw of the randomisation)."""
        if not self.draws_gyro_noise:
            return self.noise
        return replace(self.noise or SensorNoise(), gyro_std=airframe.gyro_noise_std)

    @property
    def rate_reward(self) -> RateReward:
        return RateReward(self.reward, self.axis_weights, self.action_rate_penalty, self.omega_max,
                          self.relative_error)


# ── The command line, from the fields ──────────────────────────────────────────────────
@dataclass(frozen=True)
class CommandOption:
    """One `EnvConfig` field as a command line takes it."""

    field: str  # EnvConfig's name
    name: str  # the command line's (and a configuration's) name: --name-with-dashes
    hint: Any  # the value's type on a command line
    default: Any
    metadata: Mapping[str, Any]  # help, argparse keywords, parse

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")


ENV_FIELDS = {f.name: f for f in dataclasses.fields(EnvConfig)}
EXCLUDED = {name: f.metadata["excluded"] for name, f in ENV_FIELDS.items() if "excluded" in f.metadata}


def command_options(recipe: Mapping[str, Any] | None = None,
                    exclude: Mapping[str, str] | None = None) -> dict[str, CommandOption]:
    """The command-line options of `EnvConfig`, by their command-line name: the environment's
    default unless `recipe` (by EnvConfig field) overrides it, less the fields `exclude` names
    (each with the reason this command leaves it out)."""
    recipe, exclude = dict(recipe or {}), dict(exclude or {})
    unknown = (set(recipe) | set(exclude)) - set(ENV_FIELDS)
    if unknown:
        raise KeyError(f"not EnvConfig fields: {sorted(unknown)}")
    out = {}
    for name, f in ENV_FIELDS.items():
        if name in EXCLUDED or name in exclude:
            continue
        meta = {k: v for k, v in f.metadata.items() if k in ("help", "choices", "nargs", "metavar", "parse")}
        option = CommandOption(name, f.metadata.get("name", name), f.metadata["cli"],
                               recipe.get(name, f.default), meta)
        out[option.name] = option
    return out


def scalar(hint: Any) -> tuple[Any, bool]:
    """The argparse type of a hint, and whether it is optional (`X | None`)."""
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        return scalar(args[0])[0], type(None) in typing.get_args(hint)
    if typing.get_origin(hint) is tuple:
        return args[0], False
    if typing.get_origin(hint) is dict:  # KEY=VALUE items, parsed by the field's `parse`
        return str, False
    return hint, False


def add_option(parser: argparse.ArgumentParser | argparse._ArgumentGroup, name: str, hint: Any, default: Any,
               metadata: Mapping[str, Any], only_given: bool = False) -> None:
    """`--name` for a value of type `hint`: its help and argparse keywords from `metadata`,
    the default shown in the help. `metadata["flags"]` spells the option otherwise: its name
    first, then former spellings still accepted. With `only_given`, an option not on the
    command line is absent from the namespace."""
    meta = {k: v for k, v in metadata.items() if k not in ("parse", "flags")}
    kind, _ = scalar(hint)
    flags = metadata.get("flags", ("--" + name.replace("_", "-"),))
    if kind is bool:
        if default is not None and "%(default)" not in meta["help"]:
            meta["help"] += f" (default: {'on' if default else 'off'})"
        parser.add_argument(*flags, dest=name, action=argparse.BooleanOptionalAction,
                            default=argparse.SUPPRESS if only_given else default, **meta)
        return
    if typing.get_origin(hint) is tuple:
        meta.setdefault("nargs", len(typing.get_args(hint)))
    if default not in (None, (), [], {}) and "%(default)" not in meta["help"]:
        shown = " ".join(map(str, default)) if isinstance(default, tuple) else default
        meta["help"] += f" (default: {shown})"
    parser.add_argument(*flags, dest=name, type=kind, default=argparse.SUPPRESS if only_given else default,
                        **meta)


def add_env_arguments(parser: argparse.ArgumentParser, names: tuple[str, ...],
                      defaults: Mapping[str, Any] | None = None,
                      notes: Mapping[str, str] | None = None) -> None:
    """The `EnvConfig` options `names` (command-line names) on a command that takes only those,
    e.g. `fcemu eval --airframe`; `notes` adds to an option's help what it means there."""
    options = command_options()
    for name in names:
        option = options[name]
        meta = dict(option.metadata)
        if notes and name in notes:
            meta["help"] = f"{meta['help']}; {notes[name]}"
        add_option(parser, name, option.hint, (defaults or {}).get(name, option.default), meta)


def own_ranges(airframe: str | Path | Airframe) -> str:
    """The ranges `airframe` is randomised over unless told: its own `<name>.randomization.json`
    where one is shipped (the Iris's), else the ranges relative to any airframe, built for it
    (`sim_bridge.randomization.ranges_for`)."""
    name = (airframe if isinstance(airframe, Airframe) else load_airframe(airframe)).name
    return name if randomization_path(name).exists() else RELATIVE
