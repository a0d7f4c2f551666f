"""`fcemu sitl`, `fcemu demo` and `fcemu betaflight` (argparse only: MuJoCo loads when a command runs)."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import TypeVar

from fcemu.sim_bridge.airframe import DEFAULT_AIRFRAME

T = TypeVar("T", int, float)


def _number(convert: type[T], ok: Callable[[T], bool], requirement: str) -> Callable[[str], T]:
    """An argparse `type`: `convert` the text, then insist on `ok`; each failure one line naming the text."""
    kind = "a whole number" if convert is int else "a number"

    def parse(text: str) -> T:
        try:
            value = convert(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not {kind}: {text!r}") from None
        if not ok(value):
            raise argparse.ArgumentTypeError(f"{text!r}: {requirement}")
        return value

    return parse


def _accepted_by(check: Callable[[str], object]) -> Callable[[str], str]:
    """An argparse `type` keeping the text once `check` accepts it; its ValueError is the error."""

    def parse(text: str) -> str:
        try:
            check(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
        return text

    return parse


def _check_speed(text: str) -> None:
    from fcemu.sitl.sitl import parse_speed

    parse_speed(text)


def _check_peer(text: str) -> None:
    from fcemu.sitl.sitl_args import checked_peer

    checked_peer(text, "peer")


loop_rate = _number(float, lambda rate: math.isfinite(rate) and 0 < rate <= 100_000 and not 1e6 % rate,
                    "the loop rate must divide one second into whole microseconds (e.g. 500, 1000, 2000)")
seconds = _number(float, lambda value: math.isfinite(value) and value >= 0,
                  "must be a finite number of seconds >= 0")
# System id 1+N must be a MAVLink system id, 1..255.
_instance = _number(int, lambda value: 0 <= value <= 254, "the instance must be in 0..254")
_speed = _accepted_by(_check_speed)
_positive_seconds = _number(float, lambda value: math.isfinite(value) and value > 0,
                            "must be a finite number of seconds > 0")
# Betaflight stores rc_rate and srate in units of 10 deg/s, 1..255.
_rate_dps = _number(float, lambda value: value % 10 == 0 and 10 <= value <= 2550,
                    "must be a multiple of 10 deg/s in 10..2550")
_peer = _accepted_by(_check_peer)


def add_airframe_option(p: argparse.ArgumentParser, what: str = "the twin flies and the firmware is "
                        "configured for (its PID tune, health rules, hover throttle)") -> None:
    p.add_argument("--airframe", default=DEFAULT_AIRFRAME, metavar="NAME|FILE",
                   help=f"the airframe {what}: sim_bridge/airframes/NAME.json or a file")


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
                      help="pid, pid:<preset> or a policy .onnx (default: `default`, the shipped policy "
                           "where it holds the airframe, else its PID; on a loop over 3 ticks, its "
                           "tune for latency)")
    sitl.add_argument("--fallback", default=None,
                      help="under a policy, the PID it hands over to and CTRL_SEL=0 selects: pid (the "
                           "airframe's own tune) or pid:<preset|FILE> (default: the one the policy names, "
                           "as `fcemu fit`'s does its DIR/pid.json, else pid)")
    sitl.add_argument("--rig", choices=("free", "rig"), default="free",
                      help="free: the vehicle flies; rig: it turns on a ball joint at a fixed point")
    sitl.add_argument("--speed", type=_speed, default="realtime",
                      help="realtime, max (lockstep, as fast as it goes) or N for N× real time")
    sitl.add_argument("--duration", type=seconds, default=None,
                      help="the flight's length in simulated seconds, not a budget (default: until Ctrl-C)")
    sitl.add_argument("--rate", type=loop_rate, default=1000.0, help="loop rate in Hz")
    sitl.add_argument("--quiet", action="store_true", help="no live status line")
    sitl.add_argument("--no-mavlink", action="store_true", help="fly the scripted doublets, no MAVLink")
    sitl.add_argument("--ulog", default=None, metavar="FILE.ulg",
                      help="write the flight's PX4 ULog here when it ends (gyro, rate setpoints, motor "
                           "commands and outputs, ESC rpm at the loop rate; docs/identify.md)")
    sitl.add_argument("--json", action="store_true",
                      help="print the summary at the end as one JSON object on stdout (the live status line "
                           "stays on stderr)")
    add_airframe_option(sitl)
    add_mavlink_options(sitl)
    sitl.set_defaults(handler="fcemu.sitl.sitl:sitl_command")

    demo = sub.add_parser("demo", help="SITL flown by the bundled pymavlink script: take-off, flip, land")
    demo.add_argument("--controller", default=None, help="pid, pid:<preset> or a policy .onnx")
    demo.add_argument("--speed", type=_speed, default="3", help="N× real time (default 3)")
    demo.add_argument("--out", default="runs/demo", help="where the plot, tlog and summary go")
    demo.add_argument("--json", action="store_true", help="print the summary as one JSON object on stdout")
    demo.set_defaults(handler="fcemu.sitl.demo:demo_command")

    p = sub.add_parser("betaflight", help="real Betaflight 4.6 SITL flies seeded rate steps on the rig "
                                          "(--crosscheck: against fcemu's pid:betaflight, or with "
                                          "--firmware, a policy built into Betaflight against fcemu)")
    p.add_argument("--episodes", type=int, default=10, help="--rig rig: commands flown")
    p.add_argument("--seed", type=int, default=0, help="seed of the commands, as fcemu eval's")
    p.add_argument("--episode-s", type=_positive_seconds, default=1.0, help="--rig rig: seconds per command")
    p.add_argument("--rig", choices=("rig", "free"), default="rig",
                   help="rig: seeded steps on the ball joint; free: take-off, doublets and descent, "
                        "all from RC sticks")
    p.add_argument("--duration", type=_positive_seconds, default=8.0,
                   help="--rig free: the flight's length in seconds, not a budget")
    p.add_argument("--crosscheck", action="store_true",
                   help="also fly fcemu's pid:betaflight preset on the same commands and compare")
    p.add_argument("--speed", type=float, default=0.25,
                   help="pace of the twin against wall time (Betaflight follows the FDM timestamps): "
                        "episodes on the rig measure the SITL's clock against the twin's, and a PID run "
                        "drifting more than 5 %% (median episode) or 15 %% (any) is refused")
    p.add_argument("--firmware", default=None, metavar="DIR",
                   help="a Betaflight built with a policy (`fcemu export POLICY --target betaflight --out "
                        "DIR`): it flies with NEURAL on (--crosscheck: against fcemu flying the same C "
                        "policy; --rig free: PID take-off, NEURAL on in the air, off to land)")
    p.add_argument("--rate-dps", type=_rate_dps, default=400.0,
                   help="Betaflight's linear ACTUAL rate at full stick, deg/s (the stick resolution)")
    p.add_argument("--run-dir", default=None, help="where the SITL keeps eeprom.bin and its log "
                                                   "(default: a fresh temporary directory)")
    p.add_argument("--out", default=None, help="--crosscheck: write the report (Markdown, JSON, plot) into "
                                                "this folder (default: none; the summary is printed only)")
    p.add_argument("--save-traces", metavar="FILE.npz", help="save Betaflight's traces (fcemu eval's format)")
    p.add_argument("--blackbox", metavar="FILE.BFL",
                   help="keep Betaflight's own blackbox (blackbox_device VIRTUAL, every PID loop): its logs, "
                        "one per arming, joined in FILE (fcemu identify reads it)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    add_airframe_option(p, "the twin flies (Betaflight's motor_poles and fcemu's controllers are for it)")
    p.set_defaults(handler="fcemu.evaluation.betaflight_crosscheck:betaflight_command")
