"""`fcemu bench sim|loop|inference|train` (argparse only: each bench loads what it measures when it runs).

Every bench lives in this package, one module per bench, whichever layer it measures;
`fcemu bench mcu` is the C export's and registers from export/cli.py.
"""

from __future__ import annotations

import argparse
from typing import Any

from fcemu.sim_bridge.cli import fault_spec
from fcemu.sim_bridge.env_config import add_env_arguments
from fcemu.sitl.cli import add_airframe_option, loop_rate, seconds
from fcemu.training import config
from fcemu.training.cli import BENCH_DEFAULTS

JSON_HELP = "print the figures as one JSON object on stdout"


class _BudgetSeconds(argparse.Action):
    """--budget-s S; its former spelling --max-minutes M is M × 60 seconds."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        setattr(namespace, self.dest, values * 60.0 if option_string == "--max-minutes" else values)


def register_bench(bench_sub: argparse._SubParsersAction) -> None:
    sim = bench_sub.add_parser("sim", help="twin, UDP link and environment throughput")
    sim.add_argument("--seconds", type=float, default=2.0,
                     help="wall-clock seconds each figure is measured for (the benchmark's length)")
    sim.add_argument("--envs", type=int, default=256, help="batch size for the vectorised env")
    add_env_arguments(sim, ("airframe",))
    sim.add_argument("--json", action="store_true", help=JSON_HELP)
    sim.set_defaults(handler="fcemu.benchmarks.sim:bench_sim")

    loop = bench_sub.add_parser("loop", help="real-time loop timing: period error, compute, misses")
    loop.add_argument("--controller", default=None, help="pid, pid:<preset> or a policy .onnx")
    loop.add_argument("--seconds", type=seconds, default=10.0,
                      help="seconds of real-time flight per measurement (the benchmark's length)")
    loop.add_argument("--rate", type=loop_rate, action="append",
                      help="loop rate in Hz (repeat to compare rates; default 1000)")
    loop.add_argument("--rig", choices=("free", "rig"), default="rig",
                      help="rig: the vehicle turns on a ball joint at a fixed point; free: it flies")
    loop.add_argument("--mavlink", action="store_true",
                      help="also run with MAVLink telemetry streaming and a peer sending setpoints at 100 Hz")
    loop.add_argument("--fault", type=fault_spec, default=None, metavar="SPEC",
                      help="repeat each measurement with this fault active in the twin (fcemu eval --fault's "
                           "SPEC, e.g. esc-telemetry:stuck); the figures with it go under with_fault")
    loop.add_argument("--json", action="store_true", help=JSON_HELP)
    add_airframe_option(loop)
    loop.set_defaults(handler="fcemu.benchmarks.loop:bench_loop")

    inference = bench_sub.add_parser("inference", help="ONNX policy inference time per tick")
    inference.add_argument("--model", default=None, help="a policy .onnx (default: the shipped policy)")
    inference.add_argument("--samples", type=int, default=20_000, help="inferences timed")
    inference.add_argument("--json", action="store_true", help=JSON_HELP)
    add_airframe_option(inference, "the policy is checked against (envelope), whose rotor speeds it reads")
    inference.set_defaults(handler="fcemu.benchmarks.inference:bench_inference")

    p = bench_sub.add_parser("train", help="training steps/s and wall time until the policy beats the PID")
    config.add_arguments(p, exclude=("eval_seed", "export", "progress"), defaults=BENCH_DEFAULTS)
    p.add_argument("--budget-s", "--max-minutes", dest="budget_s", type=float, default=900.0, metavar="S",
                   action=_BudgetSeconds, help="wall-clock budget of the race against the PID, in seconds")
    p.add_argument("--target", choices=("beat", "bar"), default="beat",
                   help="stop when the Error sum beats the PID's (beat) or meets the deployable bar (bar)")
    p.add_argument("--json", action="store_true", help=JSON_HELP)
    p.set_defaults(handler="fcemu.benchmarks.train:bench_train")
