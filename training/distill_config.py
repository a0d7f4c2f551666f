"""`DistillConfig`: the options of `fcemu distill`, and its command line made from them.

The distillation's own options are fields here; the environment's (the airframe, the task,
the ranges the twins are drawn from) are `sim_bridge.env_config.EnvConfig`'s, added by
`training.config.with_env_options` with distillation's recipe (`DISTILL_RECIPE`), less those
the teacher's contract or the student's own options fix (`DISTILL_EXCLUDED`, each with its
reason). This module imports neither torch nor MuJoCo: `fcemu --help` builds every parser.
"""

from __future__ import annotations

import argparse
import dataclasses
import typing
from dataclasses import dataclass, field
from typing import Any

from fcemu.sim_bridge.airframe import load_airframe
from fcemu.sim_bridge.env_config import add_option, own_ranges
from fcemu.training.config import JOBS_FLAGS, option, with_env_options

OWN_RANGES = "own"  # --randomize's default: the airframe's training ranges (`training_ranges`)
# The ranges a student is trained on by default, per airframe: the Iris's default was distilled
# on ESC delays of up to 2 ticks (policies/README.md); another airframe's are its own ranges, or
# the relative ranges built for it (`sim_bridge.env_config.own_ranges`).
TRAINING_RANGES = {"iris": "iris_esc2"}
# The flights' recipe: half the episodes on airframes drawn from the ranges, half nominal.
DISTILL_RECIPE: dict[str, Any] = {"randomize": OWN_RANGES, "randomize_share": 0.5}
TEACHERS_CONTRACT = "the teacher's contract fixes it (its metadata)"
NO_REWARD = "DAgger fits the teacher's actions; no reward is used"
DISTILL_EXCLUDED = {
    "memory": "the student's own --memory; the twins observe the union of both histories",
    "action_mapping": TEACHERS_CONTRACT, "throttle": TEACHERS_CONTRACT,
    "integral_leak": TEACHERS_CONTRACT, "rms_leak": TEACHERS_CONTRACT,
    "reward": NO_REWARD, "axis_weights": NO_REWARD, "action_rate_penalty": NO_REWARD,
    "action_rate_after_s": NO_REWARD,
}


@dataclass
class DistillConfig:
    teacher: str = option(None, "the teacher: a policy (.onnx made by `fcemu export`), or `inversion` (the "
                                "airframe's model inverted; `inversion:K`: its time constant in motor lags; "
                                "`inversion:K:Z`: and its damping ratio; `inversion:K:Z:Y`: and the share "
                                "of yaw it serves first; `inversion:K:Z:Y:J`: and its braking share)")
    out: str = option("runs/distill", "run directory")
    memory: int | None = option(None, "the student's history length (default: the teacher's)")
    fields: tuple[str, ...] | None = option(
        None, "the student's observation fields, rate_error rotor_speed first (default: the teacher's)",
        nargs="+", metavar="FIELD")
    net_arch: tuple[int, ...] = option((8, 32, 32), "the student's hidden layers, tanh (a narrow first layer "
                                                    "reads a long history cheaply)", nargs="+", metavar="H")
    rounds: int = option(8, "DAgger rounds; the teacher flies the first")
    steps: int = option(1000, "steps per twin and round")
    envs: int = option(64, "twins stepped together")
    beta: float = option(0.5, "the teacher flies an episode of round r with probability β^r")
    fit_steps: int = option(1500, "Adam steps after each round, three times as many after the last")
    batch_size: int = option(4096, "samples per Adam step")
    learning_rate: float = option(1e-3, "Adam's, cosine-decayed in each fit")
    smoothness: float = option(0.0, "weight of the mean squared change of the student's action from one "
                                    "step to the next in the loss")
    gain_weight: float = option(
        0.1, "weight of the gain match: each sample is also nudged along the student's inputs and the change "
             "of the student's action fitted to the teacher's, so the student's slopes match, not only its "
             "values (0: off)", metavar="W")
    gain_step: float = option(0.2, "the nudge, in standard deviations of each input", metavar="S")
    # Off by default: a one-step student cannot tell from its late gyro what the teacher saw on
    # time. A student with a history of several ticks can, so the default policy's recipe
    # (policies/README.md) and `fcemu fit` on late or noisy sensors turn it on.
    privileged: bool = option(
        False, "where the twins' gyro or ESC telemetry is late or lossy, the teacher reads the readings as "
               "sampled and the student its own (off: both read the firmware's); the model-based teacher "
               "`inversion` reads the true rates and rotor speeds, without noise or vibration either")
    per_twin: bool = option(
        False, "the model-based teacher (`inversion`) built for each twin's airframe as drawn this episode "
               "(its motors, delays and damping), not once for --airframe; without the gain match. Always "
               "so with --airframe-pool")
    foreign_teacher: bool = option(False, "distil a teacher made for another airframe than --airframe "
                                          "(its fcemu.airframe); refused unless given")
    seed: int = option(0, "seed of the twins (their commands, drawn airframes and noise), of which "
                          "episodes the teacher flies, and of the student's initial weights and batches")
    threads: int = option(0, "torch threads (0: one per CPU this process may use)", flags=JOBS_FLAGS,
                          metavar="JOBS")
    progress: bool = option(True, "progress bar")
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        from fcemu.training.config import check_env_options

        if self.teacher is None:
            raise ValueError("a distillation needs its teacher (.onnx)")
        check_env_options(self)
        for name in ("fields", "net_arch"):  # a command line and JSON give lists
            if isinstance(getattr(self, name), list):
                setattr(self, name, tuple(getattr(self, name)))

    def ranges(self) -> str | None:
        """The ranges the twins draw from: `--randomize`, or by default the airframe's training ranges
        (none where the twins fly a pool of quads, each as it is)."""
        if self.airframe_pool is not None and self.randomize == OWN_RANGES:
            return None
        if self.randomize != OWN_RANGES:
            return self.randomize
        return training_ranges(self.airframe)


_SHIPPED = ", ".join(f"{airframe}: {ranges}" for airframe, ranges in TRAINING_RANGES.items())
DistillConfig = with_env_options(DistillConfig, DISTILL_RECIPE, DISTILL_EXCLUDED, notes={
    "randomize": f"{OWN_RANGES}: the airframe's training ranges ({_SHIPPED}; another airframe's own)"})
FIELDS = {f.name: f for f in dataclasses.fields(DistillConfig) if f.name not in ("teacher", "extra")}


def training_ranges(airframe: str) -> str:
    """The ranges a student for `airframe` is trained on unless told: `TRAINING_RANGES`, else its own."""
    try:
        name = load_airframe(airframe).name
    except (OSError, ValueError, KeyError) as exc:
        raise ValueError(f"--airframe {airframe}: {exc}") from None
    return TRAINING_RANGES.get(name) or own_ranges(airframe)


def register_distill(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("distill", help="fit a compact student policy to a teacher .onnx by DAgger on the "
                                       "randomised twins; a `fcemu train`-style run directory")
    p.add_argument("teacher", help=DistillConfig.__dataclass_fields__["teacher"].metadata["help"])
    hints = typing.get_type_hints(DistillConfig)
    for name, f in FIELDS.items():
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        add_option(p, name, hints[name], default, f.metadata)
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.set_defaults(handler="fcemu.training.distill:distill_command")


def from_args(args: argparse.Namespace) -> DistillConfig:
    """The `DistillConfig` `register_distill`'s parser produced."""
    values = {}
    for name, f in FIELDS.items():
        parse = f.metadata.get("parse")
        values[name] = parse(getattr(args, name)) if parse is not None else getattr(args, name)
    return DistillConfig(teacher=args.teacher, **values)
