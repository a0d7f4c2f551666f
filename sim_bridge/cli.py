"""`fcemu twin ...`."""

from __future__ import annotations

import argparse

from fcemu.sim_bridge.airframe import DEFAULT_AIRFRAME


def fault_spec(text: str):
    """--fault SPEC as a Fault (`fcemu twin serve`, `fcemu bench loop`); argparse names a bad one on one
    line."""
    from fcemu.sim_bridge.fault_spec import parse_fault
    from fcemu.sim_bridge.faults import FaultSpecError

    try:
        return parse_fault(text)
    except FaultSpecError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def register(sub: argparse._SubParsersAction) -> None:
    twin = sub.add_parser("twin", help="the digital twin on its own")
    twin_sub = twin.add_subparsers(dest="twin_command", required=True, metavar="WHAT")

    serve = twin_sub.add_parser("serve", help="run the twin as a UDP lockstep simulator")
    serve.add_argument("--host", default="127.0.0.1", help="the address to listen on")
    serve.add_argument("--port", type=int, default=9002, help="the UDP port to listen on (0: a free one)")
    serve.add_argument("--rig", choices=("rig", "free"), default="rig",
                       help="rig: the vehicle turns on a ball joint at a fixed point; free: it flies")
    serve.add_argument("--airframe", default=DEFAULT_AIRFRAME, metavar="NAME|FILE",
                       help="the airframe the twin simulates: sim_bridge/airframes/NAME.json or a file")
    serve.add_argument("--quiet", action="store_true", help="no periodic status line")
    serve.add_argument("--fault", type=fault_spec, action="append", default=None, metavar="SPEC",
                       help="inject this fault from the first frame of every session (repeatable), as "
                            "fcemu eval --fault: TARGET:KIND[:VALUE], e.g. esc-telemetry:1:off, "
                            "gyro:delayed:5ms, esc-telemetry:burst:20ms@1%%")
    serve.add_argument("--json", action="store_true",
                       help="print the summary when it stops (steps, resets, bad packets) as one JSON object "
                            "on stdout; the line saying where it listens goes to stderr")
    serve.set_defaults(handler="fcemu.sim_bridge.twin_server:serve_command")

    draw = twin_sub.add_parser("draw", help="airframe files drawn from the distribution of quads one policy "
                                             "is trained and judged across (20 g to 3 kg)")
    draw.add_argument("--seed", type=int, default=0, help="the draw: the same seed writes the same airframes")
    draw.add_argument("--count", type=int, default=20, help="how many airframes")
    draw.add_argument("--out", required=True, help="the folder the airframe files are written to")
    draw.add_argument("--json", action="store_true",
                      help="print each airframe's drawn figures (mass, thrust-to-weight, arm, motor lag, "
                           "delays) and its file as one JSON object on stdout")
    draw.set_defaults(handler="fcemu.sim_bridge.airframe_draw:draw_command")

    demo = twin_sub.add_parser("demo", help="open-loop showcase: hover, then roll/pitch/yaw")
    demo.add_argument("--out", default="out/twin_demo.png", help="where to write the plot")
    demo.add_argument("--json", action="store_true",
                      help="print the figures (hover, each axis's response) as one JSON object on stdout")
    demo.set_defaults(handler="fcemu.sim_bridge.showcase:main")

