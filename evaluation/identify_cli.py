"""`fcemu identify`: an airframe file from a PX4 ULog or a Betaflight blackbox log, or from an
identification flight on a twin (flown by fcemu's firmware or by Betaflight's SITL)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from fcemu.sim_bridge.airframe import DEFAULT_AIRFRAME


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("identify", help="an airframe file from a PX4 ULog or a Betaflight blackbox log (rate "
                                        "response, motor lag and delay, rpm, hover, gyro noise); --fly: from"
                                        " a flight on a twin")
    p.add_argument("log", nargs="?", default=None, metavar="LOG.ulg|LOG.BFL",
                   help="the flight log (docs/identify.md: what to log and fly)")
    p.add_argument("--out", required=True, metavar="PATH",
                   help="the airframe file to write (its report.md and rates.png beside it); with --fly "
                        "a folder: flight.ulg, airframe.json, report.md")
    p.add_argument("--base", default=DEFAULT_AIRFRAME, metavar="NAME|FILE",
                   help="the airframe that gives what a log cannot: mass, geometry, k_M, sizes "
                        "(default iris)")
    p.add_argument("--fly", default=None, metavar="NAME|FILE",
                   help="fly the identification flight on this airframe's twin (lockstep, on the rig), keep "
                        "its ULog and identify it: the check against a known answer")
    p.add_argument("--perturb-seed", type=int, default=None, metavar="S",
                   help="with --fly: fly an airframe drawn from its randomisation ranges with seed S "
                        "(written as true_airframe.json) instead")
    p.add_argument("--controller", default="pid",
                   help="with --fly: what flies it (default: its PID; betaflight: Betaflight 4.6's SITL, "
                        "its own blackbox kept as flight.BFL)")
    p.add_argument("--seed", type=int, default=0, help="with --fly: the twin's sensor-noise seed")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(handler="fcemu.evaluation.identify_cli:identify_command")


def _load_base(name: str):
    from fcemu.sim_bridge.airframe import load_airframe

    return load_airframe(name)


def identify_command(args) -> int:
    from fcemu.evaluation.identify_airframe import identified_document, identify, write_airframe
    from fcemu.evaluation.identify_log import read_flight_log
    from fcemu.evaluation.identify_report import write_report
    from fcemu.firmware.errors import UserError

    if (args.log is None) == (args.fly is None):
        raise UserError("fcemu identify takes a LOG or --fly AIRFRAME, one of them")
    if args.fly is None and args.perturb_seed is not None:
        raise UserError("--perturb-seed draws the airframe --fly flies; there is none to draw without --fly")
    base = _load_base(args.base)
    truth = None
    if args.fly is not None:
        out_dir = Path(args.out)
        truth = _flown_airframe(args.fly, args.perturb_seed, out_dir)
        if args.controller == "betaflight":
            log_path = _fly_betaflight(truth, out_dir)
        else:
            from fcemu.evaluation.identify_flight import fly_identification

            log_path = fly_identification(truth, args.controller, seed=args.seed).write(
                out_dir / "flight.ulg", {"ver_hw": f"fcemu SITL {truth.name}"})
        airframe_path = out_dir / "airframe.json"
        name = f"{truth.name}_identified"
    else:
        log_path, airframe_path = Path(args.log), Path(args.out)
        if airframe_path.is_dir():
            raise UserError(f"--out {airframe_path}: a folder; name the airframe file to write")
        out_dir = airframe_path.parent
        name = airframe_path.stem
    log = read_flight_log(log_path)
    ident = identify(log, base, args.base)
    airframe = write_airframe(identified_document(ident, name), airframe_path)
    report, figures = write_report(ident, airframe, airframe_path, out_dir, truth)
    if args.json:
        print(json.dumps(figures))
    else:
        fits = figures["prediction_fit_pct"]
        print(f"identified {airframe_path} from {log_path} ({len(log.t)} samples, "
              f"{'with' if ident.motors.from_rpm else 'without'} ESC rpm); report {report}", file=sys.stderr)
        print(f"tau up {ident.motors.tau_up.text(' s')}, down {ident.motors.tau_down.text(' s')}; "
              f"hover command {ident.hover.value:.3f}; 50 ms-ahead fit "
              + ", ".join(f"{a} {fits['identified'][a]:.1f} % (base {fits['base'][a]:.1f} %)"
                          for a in fits["identified"]))
    return 0


def _fly_betaflight(truth, out_dir: Path) -> Path:
    """The identification flight flown by Betaflight's SITL; its blackbox, and its clock against the
    twin's in betaflight.json."""
    from fcemu.evaluation.identify_betaflight import clock_ratio, fly_identification_betaflight
    from fcemu.firmware.errors import UserError
    from fcemu.sitl.betaflight_process import BetaflightError

    log_path = out_dir / "flight.BFL"
    try:
        traces = fly_identification_betaflight(truth, log_path, out_dir / "betaflight_sitl")
    except BetaflightError as exc:
        raise UserError(str(exc)) from None
    ratio = clock_ratio(log_path)
    (out_dir / "betaflight.json").write_text(json.dumps(
        {"log_s_per_twin_s": round(ratio, 5), "packets": traces.extra["packets"]}, indent=1) + "\n")
    print(f"Betaflight's blackbox {log_path}: its clock ran {ratio:.4f} s per twin second", file=sys.stderr)
    return log_path


def _flown_airframe(name: str, perturb_seed: int | None, out_dir: Path):
    """The airframe --fly flies: the named one, or one drawn from its ranges (kept as true_airframe.json)."""
    from dataclasses import replace

    from fcemu.evaluation.identify_airframe import airframe_document, write_airframe
    from fcemu.evaluation.perturb import perturbed_airframes
    from fcemu.sim_bridge.randomization import RandomizationError, ranges_for

    airframe = _load_base(name)
    if perturb_seed is None:
        return airframe
    try:
        drawn = perturbed_airframes(ranges_for(airframe), 1, perturb_seed)[0]
    except (RandomizationError, ValueError) as exc:
        from fcemu.firmware.errors import UserError

        raise UserError(f"--perturb-seed {perturb_seed}: {exc}") from None
    truth = replace(drawn.airframe, name=f"{airframe.name}_perturbed_{perturb_seed}")
    source = (f"{name} drawn from its randomisation ranges by fcemu identify --fly {name} --perturb-seed "
              f"{perturb_seed}: factors {json.dumps(drawn.factors_json())}")
    write_airframe(airframe_document(truth, source, {}), out_dir / "true_airframe.json")
    return truth
