"""`fcemu train`, `fcemu bench train` and `fcemu sweep` (argparse only: torch loads when a command runs).

Their training options are generated from `training.config.TrainConfig`, declared once there.
"""

from __future__ import annotations

import argparse

from fcemu.training import config, distill_config

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
    p.add_argument("--jobs", "--cpus", dest="cpus", type=int, default=None, metavar="JOBS",
                   help="CPUs the local Ray runs trials on, --cpus-per-trial each (default: all)")
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
    distill_config.register_distill(sub)
    register_tune(sub)
    from fcemu.training import fit

    fit.register(sub)


def register_tune(sub: argparse._SubParsersAction) -> None:
    """`fcemu tune`, its options declared in `training.tune_options`."""
    from fcemu.training.tune_options import register_tune as register

    register(sub)
