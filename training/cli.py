"""`fcemu train` (argparse only: torch loads when a command runs)."""

from __future__ import annotations

import argparse

ALGOS = ("ppo", "trpo", "ddpg", "td3", "sac")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="RL training of a rate controller (SB3 / sb3-contrib)")
    p.add_argument("--algo", choices=ALGOS, default="ppo")
    p.add_argument("--memory", type=int, default=1, help="observation history length m")
    p.add_argument("--squash", action="store_true",
                   help="PPO/TRPO: tanh-squashed actions (gSDE's squash_output); what lets "
                        "--action-rate-penalty smooth the motors instead of saturating them")
    p.add_argument("--integral", action="store_true",
                   help="add a leaky integral of the rate error to the observation (rate_error_integral)")
    p.add_argument("--steps", type=int, default=3_000_000, help="environment steps (1 ms each)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--envs", type=int, default=None, help="parallel twins (default: per algorithm)")
    p.add_argument("--out", default=None, help="run directory (default runs/ALGO)")
    p.add_argument("--task", choices=("episodic", "continuous"), default="episodic")
    p.add_argument("--action-mapping", choices=("gymfc", "throttle"), default="throttle")
    p.add_argument("--throttle", type=float, nargs="+", default=None, metavar="T",
                   help="collective for the throttle mapping: one value, or LO HI drawn per episode "
                        "(default 0.5 0.9)")
    p.add_argument("--action-rate-penalty", type=float, default=0.0,
                   help="weight of Neuroflight's output-oscillation penalty (mean |Δu| per step); "
                        "use with --squash")
    p.add_argument("--reward", choices=("paper", "unclipped"), default="unclipped",
                   help="paper: −clip(Σ|e|/(3·Ω_max), 0, 1); unclipped: the same without the clip")
    p.add_argument("--axis-weights", type=float, nargs=3, default=(1.0, 1.0, 1.0), metavar=("R", "P", "Y"),
                   help="weights of the roll, pitch, yaw error in the unclipped reward")
    p.add_argument("--norm-reward", action=argparse.BooleanOptionalAction, default=None,
                   help="VecNormalize reward scaling (default: per algorithm)")
    p.add_argument("--norm-obs", action=argparse.BooleanOptionalAction, default=True,
                   help="VecNormalize observation normalisation (folded into the exported ONNX graph)")
    p.add_argument("--hp", nargs="*", metavar="KEY=VALUE", help="override algorithm hyper-parameters")
    p.add_argument("--checkpoint-every", type=int, default=1_000_000, help="steps between checkpoints")
    p.add_argument("--eval-every", type=int, default=0,
                   help="steps between in-training evaluations against the PID (0: none)")
    p.add_argument("--export", choices=("best", "final"), default="best",
                   help="best: the in-training evaluation's best (needs --eval-every); final: the last model")
    p.add_argument("--eval-episodes", type=int, default=1000,
                   help="final evaluation commands through the firmware loop (0: skip)")
    p.add_argument("--eval-seed", type=int, default=1)
    p.add_argument("--threads", type=int, default=1, help="torch threads")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.set_defaults(handler="training.train:train_command")

