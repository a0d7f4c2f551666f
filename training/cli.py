"""`fcemu train`, `fcemu bench train` and `fcemu sweep` (argparse only: torch loads when a command runs).

Their training options are generated from `training.config.TrainConfig`, declared once there.
"""

from __future__ import annotations

import argparse

from fcemu.training import config

# What `fcemu bench train` runs unless told otherwise: the shipped run's length (it sets
# the learning-rate decay; the race usually ends first), evaluations every 250 k steps,
# no checkpoints and no final evaluation.
BENCH_DEFAULTS = {"steps": 10_000_000, "eval_every": 250_000, "checkpoint_every": 10**9, "eval_episodes": 0}
# A sweep's trials evaluate in training (what early stopping and the choice of the best
# read); only the best trial's policy is flown through the firmware loop.
SWEEP_DEFAULTS = {"eval_every": 250_000, "eval_episodes": 0}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="RL training of a rate controller (SB3 / sb3-contrib)")
    config.add_arguments(p)
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.set_defaults(handler="fcemu.training.train:train_command")

    p = sub.add_parser("sweep", help="many training runs over seeds and settings on Ray Tune, "
                                     "locally or on a cluster")
    p.add_argument("--seeds", default=None, help="seeds: 0-4, 0,2,5 or a mix (default 0)")
    p.add_argument("--out", default=None, help="sweep directory; an interrupted sweep there resumes "
                                               "(default runs/sweep)")
    p.add_argument("--hp", nargs="*", default=[], metavar="KEY=V1,V2",
                   help="search space: each value of each key (a `fcemu train` option such as "
                        "action_rate_penalty, else an algorithm hyper-parameter) is tried with each seed")
    p.add_argument("--config", default=None, help="YAML file: seeds, space (KEY: [values]) and any "
                                                  "`fcemu train` option; the command line wins")
    p.add_argument("--address", default=None, help="join this Ray cluster (e.g. ray://head:10001 or "
                                                   "auto) instead of starting Ray on this machine")
    p.add_argument("--cpus", type=int, default=None, help="CPUs of the local Ray (default: all)")
    p.add_argument("--cpus-per-trial", type=int, default=1, help="CPUs per trial (also its torch threads)")
    p.add_argument("--gpus-per-trial", type=float, default=None,
                   help="GPUs per trial (default: none; the 64×64 networks train on the CPU)")
    p.add_argument("--grace", type=int, default=None,
                   help="ASHA: in-training evaluations before a trial can be stopped "
                        "(default: a quarter of the run)")
    p.add_argument("--no-early-stop", action="store_true", help="run every trial to the end")
    p.add_argument("--best-episodes", type=int, default=1000,
                   help="commands of the best policy's evaluation through the firmware loop")
    p.add_argument("--perturb", type=int, default=0, metavar="N",
                   help="fly each trial's policy, and the PID once, on N airframes drawn from the "
                        "--randomize ranges (default iris), as `fcemu eval --perturb N` does, and "
                        "judge each by the deployable bar's perturbed lines (default 0: not flown)")
    p.add_argument("--perturb-seed", type=int, default=0, metavar="S",
                   help="seed of the perturbed airframes (a stream training never draws from)")
    p.add_argument("--perturb-episodes", type=int, default=100, metavar="E",
                   help="commands flown on each perturbed airframe (the bar's commands, seed 7)")
    config.add_arguments(p, exclude=("seed", "out", "hp", "threads", "progress"), defaults=SWEEP_DEFAULTS,
                         only_given=True)
    p.add_argument("--json", action="store_true", help="print one JSON object: trials and the best")
    p.set_defaults(handler="fcemu.training.sweep:sweep_command")
    register_distill(sub)


def register_distill(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("distill", help="fit a compact student policy to a teacher .onnx by DAgger on the "
                                       "randomised twins; a `fcemu train`-style run directory")
    p.add_argument("teacher", help="the teacher policy (.onnx made by `fcemu export`)")
    p.add_argument("--out", default="runs/distill", help="run directory (default runs/distill)")
    p.add_argument("--memory", type=int, default=None,
                   help="the student's history length (default: the teacher's)")
    p.add_argument("--fields", nargs="+", default=None, metavar="FIELD",
                   help="the student's observation fields, rate_error rotor_speed first "
                        "(default: the teacher's)")
    p.add_argument("--net-arch", nargs="+", type=int, default=[8, 32, 32], metavar="H",
                   help="the student's hidden layers, tanh (default 8 32 32: a narrow first layer reads a "
                        "long history cheaply)")
    p.add_argument("--rounds", type=int, default=8,
                   help="DAgger rounds; the teacher flies the first (default 8)")
    p.add_argument("--steps", type=int, default=1000, help="steps per twin and round (default 1000)")
    p.add_argument("--envs", type=int, default=64, help="twins stepped together (default 64)")
    p.add_argument("--beta", type=float, default=0.5,
                   help="the teacher flies an episode of round r with probability β^r (default 0.5)")
    p.add_argument("--fit-steps", type=int, default=1500,
                   help="Adam steps after each round, three times as many after the last (default 1500)")
    p.add_argument("--batch-size", type=int, default=4096, help="samples per Adam step (default 4096)")
    p.add_argument("--learning-rate", type=float, default=1e-3, help="Adam's, cosine-decayed in each fit")
    p.add_argument("--smoothness", type=float, default=0.0,
                   help="weight of the mean squared change of the student's action from one step to the "
                        "next in the loss (default 0)")
    p.add_argument("--gain-weight", type=float, default=0.1, metavar="W",
                   help="weight of the gain match: each sample is also nudged along the student's inputs and "
                        "the change of the student's action fitted to the teacher's, so the student's slopes "
                        "match, not only its values (default 0.1; 0: off)")
    p.add_argument("--gain-step", type=float, default=0.2, metavar="S",
                   help="the nudge, in standard deviations of each input (default 0.2)")
    p.add_argument("--task", default="episodic", choices=("episodic", "continuous"), help="the flights")
    p.add_argument("--randomize", default="iris_esc2", metavar="NAME|FILE",
                   help="the twins' airframe ranges, as `fcemu train --randomize` (default iris_esc2; none: "
                        "the nominal Iris)")
    p.add_argument("--randomize-share", type=float, default=0.5,
                   help="the share of episodes drawn from the ranges (default 0.5)")
    p.add_argument("--seed", type=int, default=0, help="seed of the twins, the mixture and the network")
    p.add_argument("--threads", type=int, default=0,
                   help="torch threads (0: one per CPU this process may use)")
    p.add_argument("--progress", action=argparse.BooleanOptionalAction, default=True, help="progress bar")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.set_defaults(handler="fcemu.training.distill:distill_command")


def user_error(message: str) -> int:
    """`fcemu: error: ...` on one line, exit status 2."""
    import sys

    print(f"fcemu: error: {message}", file=sys.stderr)
    return 2
