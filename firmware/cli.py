"""`fcemu sitl`, `fcemu demo`, `fcemu bench loop`, `fcemu bench inference`."""

from __future__ import annotations

import argparse
import math


def _speed(text: str) -> str:
    from firmware.sitl import parse_speed

    try:
        parse_speed(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def _loop_rate(text: str) -> float:
    try:
        rate = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(rate) or not 0 < rate <= 100_000 or 1e6 % rate:
        raise argparse.ArgumentTypeError(f"{text!r}: the loop rate must divide one second into whole "
                                         "microseconds (e.g. 500, 1000, 2000)")
    return rate


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: must be a finite number of seconds >= 0")
    return value


def _peer(text: str) -> str:
    from firmware.mavlink.bridge import parse_peer

    try:
        parse_peer(text, "peer")
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def add_mavlink_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("MAVLink")
    g.add_argument("--gcs", type=_peer, default="127.0.0.1:14550",
                   help="ground station peer host:port[:signed]")
    g.add_argument("--offboard", type=_peer, default="127.0.0.1:14540",
                   help="offboard API peer host:port[:signed]")
    g.add_argument("--peer", type=_peer, action="append", help="another peer host:port[:signed] (repeatable)")
    g.add_argument("--sysid", type=int, default=1, choices=range(1, 256), metavar="1..255")
    g.add_argument("--tlog", default=None, help="record every frame in and out to this .tlog")
    g.add_argument("--signing-key", default=None,
                   help="MAVLink 2 signing key file (32 bytes, 64 hex digits or a passphrase); required "
                        "on the peers marked :signed, or on all of them if none is marked")
    g.add_argument("--params", default=None,
                   help="parameter file (default ~/.local/share/fcemu/params.json; '' for none)")


def register(sub: argparse._SubParsersAction) -> None:
    sitl = sub.add_parser("sitl", help="fly the twin with the firmware loop (software in the loop)")
    sitl.add_argument("--controller", default=None,
                      help="pid, pid:<preset> or a policy .onnx (default: the shipped policy)")
    sitl.add_argument("--rig", choices=("free", "rig"), default="free")
    sitl.add_argument("--speed", type=_speed, default="realtime",
                      help="realtime, max (lockstep, as fast as it goes) or N for N× real time")
    sitl.add_argument("--duration", type=_seconds, default=None, help="seconds of flight (default: forever)")
    sitl.add_argument("--rate", type=_loop_rate, default=1000.0, help="loop rate in Hz")
    sitl.add_argument("--quiet", action="store_true", help="no live status line")
    sitl.add_argument("--no-mavlink", action="store_true", help="fly the scripted doublets, no MAVLink")
    add_mavlink_options(sitl)
    sitl.set_defaults(handler="firmware.sitl:sitl_command")

    demo = sub.add_parser("demo", help="SITL flown by the bundled pymavlink script: take-off, flip, land")
    demo.add_argument("--controller", default=None, help="pid, pid:<preset> or a policy .onnx")
    demo.add_argument("--speed", type=_speed, default="3", help="N× real time (default 3)")
    demo.add_argument("--out", default="runs/demo", help="where the plot, tlog and summary go")
    demo.add_argument("--json", action="store_true")
    demo.set_defaults(handler="firmware.demo:demo_command")


def register_bench(bench_sub: argparse._SubParsersAction) -> None:
    loop = bench_sub.add_parser("loop", help="real-time loop timing: period error, compute, misses")
    loop.add_argument("--controller", default=None, help="pid, pid:<preset> or a policy .onnx")
    loop.add_argument("--seconds", type=_seconds, default=10.0)
    loop.add_argument("--rate", type=_loop_rate, action="append",
                      help="loop rate in Hz (repeat to compare rates; default 1000)")
    loop.add_argument("--rig", choices=("free", "rig"), default="rig")
    loop.add_argument("--mavlink", action="store_true",
                      help="also run with MAVLink telemetry streaming and a peer sending setpoints at 100 Hz")
    loop.add_argument("--json", action="store_true")
    loop.set_defaults(handler="firmware.bench:bench_loop")

    inference = bench_sub.add_parser("inference", help="ONNX policy inference time per tick")
    inference.add_argument("--model", default=None, help="a policy .onnx (default: the shipped policy)")
    inference.add_argument("--samples", type=int, default=20_000)
    inference.add_argument("--json", action="store_true")
    inference.set_defaults(handler="firmware.inference_bench:bench_inference")
