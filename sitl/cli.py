"""`fcemu betaflight`: real Betaflight SITL flying the twin."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
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
    p.set_defaults(handler="sitl.crosscheck:betaflight_command")
