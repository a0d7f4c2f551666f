"""`fcemu sitl`, `fcemu bench loop`, `fcemu bench inference`."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    sitl = sub.add_parser("sitl", help="fly the twin with the firmware loop (software in the loop)")
    sitl.add_argument("--controller", default=None,
                      help="pid, pid:<preset> or a policy .onnx (default: the shipped policy)")
    sitl.add_argument("--rig", choices=("free", "rig"), default="free")
    sitl.add_argument("--speed", choices=("realtime", "max"), default="realtime",
                      help="realtime: 1 tick per period of wall time; max: lockstep, as fast as it goes")
    sitl.add_argument("--duration", type=float, default=None, help="seconds of flight (default: forever)")
    sitl.add_argument("--rate", type=float, default=1000.0, help="loop rate in Hz")
    sitl.add_argument("--quiet", action="store_true", help="no live status line")
    sitl.set_defaults(handler="firmware.sitl:sitl_command")


def register_bench(bench_sub: argparse._SubParsersAction) -> None:
    loop = bench_sub.add_parser("loop", help="real-time loop timing: period error, compute, misses")
    loop.add_argument("--controller", default=None, help="pid, pid:<preset> or a policy .onnx")
    loop.add_argument("--seconds", type=float, default=10.0)
    loop.add_argument("--rate", type=float, action="append",
                      help="loop rate in Hz (repeat to compare rates; default 1000)")
    loop.add_argument("--rig", choices=("free", "rig"), default="rig")
    loop.add_argument("--json", action="store_true")
    loop.set_defaults(handler="firmware.bench:bench_loop")

    inference = bench_sub.add_parser("inference", help="ONNX policy inference time per tick")
    inference.add_argument("--model", default=None, help="a policy .onnx (default: the shipped policy)")
    inference.add_argument("--samples", type=int, default=20_000)
    inference.add_argument("--json", action="store_true")
    inference.set_defaults(handler="firmware.inference_bench:bench_inference")
