"""`fcemu sitl`, `fcemu demo` and `fcemu betaflight` (argparse only: MuJoCo loads when a command runs)."""

from __future__ import annotations

import argparse
import math


def _speed(text: str) -> str:
    from sitl.sitl import parse_speed

    try:
        parse_speed(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def loop_rate(text: str) -> float:
    try:
        rate = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(rate) or not 0 < rate <= 100_000 or 1e6 % rate:
        raise argparse.ArgumentTypeError(f"{text!r}: the loop rate must divide one second into whole "
                                         "microseconds (e.g. 500, 1000, 2000)")
    return rate


def seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: must be a finite number of seconds >= 0")
    return value


def _instance(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if not 0 <= value <= 254:  # system id 1+N must be a MAVLink system id, 1..255
        raise argparse.ArgumentTypeError(f"{text!r}: the instance must be in 0..254")
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
    g.add_argument("-i", "--instance", type=_instance, default=0, metavar="N",
                   help="vehicle instance, as PX4 SITL's -i: system id 1+N, offboard peer port 14540+N, "
                        "its own parameter file; the GCS port stays 14550 (default 0)")
    g.add_argument("--gcs", type=_peer, default=None,
                   help="ground station peer host:port[:signed] (default 127.0.0.1:14550)")
    g.add_argument("--offboard", type=_peer, default=None,
                   help="offboard API peer host:port[:signed] (default 127.0.0.1:14540+N)")
    g.add_argument("--peer", type=_peer, action="append", help="another peer host:port[:signed] (repeatable)")
    g.add_argument("--sysid", type=int, default=None, choices=range(1, 256), metavar="1..255",
                   help="MAVLink system id (default 1+N)")
    g.add_argument("--tlog", default=None, help="record every frame in and out to this .tlog")
    g.add_argument("--signing-key", default=None,
                   help="MAVLink 2 signing key file (32 bytes, 64 hex digits or a passphrase); required "
                        "on the peers marked :signed, or on all of them if none is marked")
    g.add_argument("--params", default=None,
                   help="parameter file (default ~/.local/share/fcemu/params.json, params-N.json for "
                        "instance N; '' for none)")


def register(sub: argparse._SubParsersAction) -> None:
    sitl = sub.add_parser("sitl", help="fly the twin with the firmware loop (software in the loop)")
    sitl.add_argument("--controller", default=None,
                      help="pid, pid:<preset> or a policy .onnx (default: the shipped policy)")
    sitl.add_argument("--rig", choices=("free", "rig"), default="free")
    sitl.add_argument("--speed", type=_speed, default="realtime",
                      help="realtime, max (lockstep, as fast as it goes) or N for N× real time")
    sitl.add_argument("--duration", type=seconds, default=None, help="seconds of flight (default: forever)")
    sitl.add_argument("--rate", type=loop_rate, default=1000.0, help="loop rate in Hz")
    sitl.add_argument("--quiet", action="store_true", help="no live status line")
    sitl.add_argument("--no-mavlink", action="store_true", help="fly the scripted doublets, no MAVLink")
    add_mavlink_options(sitl)
    sitl.set_defaults(handler="sitl.sitl:sitl_command")

    demo = sub.add_parser("demo", help="SITL flown by the bundled pymavlink script: take-off, flip, land")
    demo.add_argument("--controller", default=None, help="pid, pid:<preset> or a policy .onnx")
    demo.add_argument("--speed", type=_speed, default="3", help="N× real time (default 3)")
    demo.add_argument("--out", default="runs/demo", help="where the plot, tlog and summary go")
    demo.add_argument("--json", action="store_true")
    demo.set_defaults(handler="sitl.demo:demo_command")

    p = sub.add_parser("betaflight", help="real Betaflight 4.6 SITL flies seeded rate steps on the rig "
                                          "(--crosscheck: against fcemu's pid:betaflight)")
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--seed", type=int, default=0, help="the evaluator's command seed (as fcemu eval)")
    p.add_argument("--episode-s", type=float, default=1.0)
    p.add_argument("--rig", choices=("rig", "free"), default="rig",
                   help="rig: seeded steps on the ball joint; free: take-off, doublets and descent, "
                        "all from RC sticks")
    p.add_argument("--duration", type=float, default=8.0, help="--rig free: seconds of flight")
    p.add_argument("--crosscheck", action="store_true",
                   help="also fly fcemu's pid:betaflight preset on the same commands and compare")
    p.add_argument("--speed", type=float, default=1.0,
                   help="pace of the twin against wall time (Betaflight follows the FDM timestamps)")
    p.add_argument("--rate-dps", type=float, default=400.0,
                   help="Betaflight's linear ACTUAL rate at full stick, deg/s (the stick resolution)")
    p.add_argument("--run-dir", default=None, help="where the SITL keeps eeprom.bin and its log "
                                                   "(default: a fresh temporary directory)")
    p.add_argument("--out", default=None, help="--crosscheck: write the report (Markdown, JSON, plot) here")
    p.add_argument("--save-traces", metavar="FILE.npz", help="save Betaflight's traces (fcemu eval's format)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(handler="evaluation.betaflight_crosscheck:betaflight_command")
