"""`fcemu replay`: a flight log's own flight flown again on a twin, and the twin judged against it."""

from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
from pathlib import Path

from fcemu.evaluation.identify_cli import add_span_option


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay",
                       help="fly a log's own setpoints and throttle on a twin and compare twin and log "
                            "(tracking, step response, 50 ms-ahead fit)")
    p.add_argument("log", metavar="LOG.BFL|LOG.ulg",
                   help="the flight log (best one the twin was not identified "
                        "from, or --span a stretch it was not)")
    p.add_argument("--airframe", required=True, metavar="NAME|FILE",
                   help="the twin to fly (fcemu identify's file)")
    p.add_argument("--controller", default=None, metavar="C",
                   help="what flies the twin (default: the log's own tune: pid_log.json beside the airframe "
                        "file, else read from the log's header; or pid, pid:FILE, a policy)")
    p.add_argument("--base", default=None, metavar="NAME|FILE",
                   help="the airframe whose 50 ms-ahead fit is shown beside the twin's (default: the one the "
                        "airframe was identified on)")
    p.add_argument("--flight", type=int, default=None, metavar="N",
                   help="which flight (arming) of a file that holds several, from 1 (default: the longest)")
    add_span_option(p, "replay this stretch only")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="write replay.json, replay.png, step_response.png "
                        "and the tune flown (pid_log.json) here (default: none; nothing written)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(handler="fcemu.evaluation.replay_cli:replay_command")


def _base_of(airframe_path: str) -> str:
    """The base airframe an identified file names in its source, else iris."""
    try:
        source = json.loads(Path(airframe_path).read_text()).get("source", "")
    except (OSError, ValueError):
        return "iris"
    found = re.search(r"on the base airframe (\S+?)\.(?:\s|$)", source)
    return found.group(1) if found else "iris"


def _flight(path: Path, index: int | None):
    from fcemu.evaluation.flight_logs import read_flight_logs
    from fcemu.evaluation.identify_log import LogError

    flights = read_flight_logs([path])
    if index is None:
        return max(flights, key=lambda log: len(log.t))
    if not 1 <= index <= len(flights):
        raise LogError(f"{path}: --flight {index}; it holds {len(flights)} flight{'s' * (len(flights) != 1)}")
    return flights[index - 1]


def replay_command(args) -> int:
    from fcemu.evaluation.replay import compare, comparison_json, fly_log, span_of
    from fcemu.evaluation.replay_plots import plot_replay, plot_steps
    from fcemu.firmware.errors import UserError
    from fcemu.sim_bridge.airframe import load_airframe

    airframe = load_airframe(args.airframe)
    base_name = args.base or (_base_of(args.airframe) if Path(args.airframe).is_file() else "iris")
    base = load_airframe(base_name)
    log = span_of(_flight(Path(args.log), args.flight), args.span)
    out = Path(args.out) if args.out else None
    scratch = tempfile.TemporaryDirectory()
    controller = args.controller
    beside = Path(args.airframe).parent / "pid_log.json"
    if controller is None and Path(args.airframe).is_file() and beside.is_file():
        controller = f"pid:{beside}"  # the tune fcemu identify read from the quad's log
    elif controller is None:
        if log.header is None:
            raise UserError(f"{args.log}: no Betaflight header, so no tune of its own: give --controller")
        from fcemu.evaluation.identify_blackbox import own_tune

        tune_path = (out or Path(scratch.name)) / "pid_log.json"
        tune_path.parent.mkdir(parents=True, exist_ok=True)
        tune_path.write_text(json.dumps(own_tune(log), indent=2) + "\n")
        controller = f"pid:{tune_path}"
    print(f"replaying {log.t[-1]:.1f} s of {log.name} on {airframe.name} flown by {controller}",
          file=sys.stderr)
    flown = fly_log(log, airframe, controller)
    axes = compare(log, flown, airframe, base)
    result = {"log": str(args.log), "flight": log.title or None, "span_s": [0.0, round(float(log.t[-1]), 3)],
              "airframe": str(args.airframe), "base": base_name, "controller": controller,
              "axes": comparison_json(axes)}
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        result["plots"] = [str(plot_replay(flown, log.name, out / "replay.png")),
                           str(plot_steps(axes, log.name, out / "step_response.png"))]
        (out / "replay.json").write_text(json.dumps(result, indent=1) + "\n")
    scratch.cleanup()
    if args.json:
        print(json.dumps(result))
    else:
        for axis, c in result["axes"].items():
            lg, tw = c["log"], c["twin"]
            print(f"{axis:5s} tracking RMS log {lg['tracking_rms_rad_s']:.3f} "
                  f"twin {tw['tracking_rms_rad_s']:.3f} "
                  f"rad/s; step peak {lg['step_peak']} / {tw['step_peak']}, rise {lg['step_rise_ms']} / "
                  f"{tw['step_rise_ms']} ms; 50 ms-ahead fit {c['prediction_fit_pct']:.1f} % "
                  f"(base {c['base_prediction_fit_pct']:.1f} %)")
    return 0
