"""`fcemu eval`: the paper's metrics for one or more controllers, side by side; `fcemu bound`."""

from __future__ import annotations

import argparse

from fcemu.sim_bridge.env_config import add_env_arguments
from fcemu.sim_bridge.tasks import EVAL_TASKS


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eval", help="the paper's metrics for --controller pid|FILE.onnx (repeatable)")
    p.add_argument("--controller", action="append", default=None,
                   help="default, pid, pid:<preset> or a policy .onnx; repeat to compare (default: pid). "
                        "default: what the firmware flies without --controller, per airframe")
    p.add_argument("--episodes", type=int, default=1000, help="commands flown by each controller")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the commands, and of the twin's sensor noise and the faults' times: the "
                        "same seed flies the same")
    p.add_argument("--task", choices=EVAL_TASKS, default="episodic",
                   help="episodic: steps from rest (the paper); inflight: the same steps from steady "
                        "hover, after a warm-up; continuous: pulse schedules")
    p.add_argument("--episode-s", type=float, default=None,
                   help="episode length (default 1 s episodic and inflight, 10 s continuous)")
    p.add_argument("--throttle", type=float, default=None, help="collective 0..1 (default: hover)")
    add_env_arguments(p, ("airframe",))
    p.add_argument("--twin", default=None, metavar="NAME|FILE",
                   help="the airframe the twin flies, where the firmware is set up for --airframe: e.g. the "
                        "true quad behind a file `fcemu identify` wrote, with a policy fitted on that file")
    p.add_argument("--fallback", default=None, metavar="PID",
                   help="the PID a policy hands over to when its input is unhealthy, e.g. pid:DIR/pid.json "
                        "for one `fcemu tune` wrote (default: the one the policy names, as `fcemu fit`'s "
                        "does its pid.json; else pid, the airframe's own tune, else the one pid:FILE "
                        "flown as a --controller)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.add_argument("--report", metavar="DIR", help="write a Markdown report with figures into DIR")
    p.add_argument("--save-traces", metavar="FILE.npz", help="save the traces (one file per controller)")
    p.add_argument("--perturb", type=int, default=0, metavar="N",
                   help="also fly the same commands on N airframes drawn from the randomisation ranges")
    p.add_argument("--perturb-seed", type=int, default=0, metavar="S",
                   help="seed of the perturbed airframes (a stream training never draws from)")
    p.add_argument("--perturb-only", type=int, nargs="+", default=None, metavar="I",
                   help="fly only these of the --perturb N airframes, by index (as the report numbers them): "
                        "a chosen few of a draw, e.g. the ones a controller found hardest")
    p.add_argument("--ranges", default=None, metavar="NAME|FILE",
                   help="randomisation ranges for --perturb: a shipped name or a file (default: the "
                        "airframe's own, iris for the Iris, else the ranges relative to any airframe, "
                        "relative, built for it)")
    p.add_argument("--fault", action="append", default=None, metavar="SPEC",
                   help="also fly the same commands with this fault injected at a seeded time of each "
                        "episode (repeatable): TARGET:KIND[:VALUE], e.g. gyro:stuck, gyro:spikes, "
                        "esc-telemetry:delayed:5ms, motor:2:thrust=0.7, battery:wrong=0.75, "
                        "payload:mass=30%%")
    p.set_defaults(handler="fcemu.evaluation.evaluate:eval_command")
    register_bound(sub)


def register_bound(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bound", help="a lower bound on the Error any controller can reach on the nominal "
                                     "twin (linear programmes per command)")
    p.add_argument("--episodes", type=int, default=200, help="commands the bound is solved for")
    p.add_argument("--seed", type=int, default=0, help="seed of the commands, as fcemu eval's")
    p.add_argument("--horizon", type=int, default=400, help="steps optimised; later error counts as 0")
    add_env_arguments(p, ("airframe",), notes={"airframe": "one with any effect on (e.g. iris_realistic) is "
                                                           "refused: the programme does not model them"})
    p.add_argument("--gyro-passes", type=int, default=0,
                   help="also re-solve with the previous solution's gyroscopic term "
                        "(an estimate, not a bound)")
    p.add_argument("--jobs", type=int, default=0,
                   help="worker processes solving the programmes (0: one per CPU this process may use)")
    p.add_argument("--controller", action="append", default=None,
                   help="also fly pid, pid:<preset> or FILE.onnx on the same commands and compare")
    p.add_argument("--fallback", default=None, metavar="PID",
                   help="the PID a policy hands over to (default as fcemu eval's: the one the policy names, "
                        "else pid, the airframe's own tune, else the one pid:FILE flown as a --controller)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(handler="fcemu.evaluation.bound_cli:bound_command")
