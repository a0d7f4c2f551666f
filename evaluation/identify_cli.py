"""`fcemu identify`: an airframe file from a PX4 ULog or a Betaflight blackbox log, or from an
identification flight on a twin (flown by fcemu's firmware or by Betaflight's SITL)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from fcemu.sim_bridge.airframe import DEFAULT_AIRFRAME

# Typical seconds on 2 cores, for the estimate of the time left: per second flown, the firmware loop
# with its ULog recorder; per second of log, writing, reading and fitting it; per flight of the
# closed-loop refinement; the report. The stages in CALIBRATED are scaled by the pace the finished
# ones showed.
FLY_S_PER_S = 0.1
FIT_S_PER_S = 0.15
REFINE_S_PER_FLIGHT = 0.3
REPORT_S = 1.0
CALIBRATED = frozenset({"fly", "fit", "refine", "report"})


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("identify", help="an airframe file from a PX4 ULog or a Betaflight blackbox log (rate "
                                        "response, motor lag and delay, rpm, hover, gyro noise); --fly: from"
                                        " a flight on a twin")
    p.add_argument("log", nargs="*", metavar="LOG.ulg|LOG.BFL",
                   help="the flight logs of one quad, each flight of each used "
                        "(docs/identify.md: what to log and fly)")
    p.add_argument("--out", required=True, metavar="PATH",
                   help="the airframe file to write (its report.md and rates.png beside it, and for a "
                        "Betaflight log its own tune as pid_log.json); with --fly a folder: flight.ulg, "
                        "airframe.json, report.md")
    add_span_option(p, "identify from this stretch only (leave the rest for `fcemu replay` to check)")
    p.add_argument("--no-refine", dest="refine", action="store_false",
                   help="a Betaflight log: skip flying the twin with the log's own tune to refine it "
                        "(docs/identify.md: about a minute on 2 cores)")
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
    p.add_argument("--seed", type=int, default=0, help="with --fly: seed of the twin's sensor noise")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(handler="fcemu.evaluation.identify_cli:identify_command")


def add_span_option(p: argparse.ArgumentParser, purpose: str) -> None:
    p.add_argument("--span", type=parse_span, default=None, metavar="START:END",
                   help=f"seconds into the flight, either end may be left empty: {purpose}")


def parse_span(text: str) -> tuple[float | None, float | None]:
    start, sep, end = text.partition(":")
    try:
        span = (float(start) if start else None, float(end) if end else None)
    except ValueError:
        span = None
    if not sep or span is None or (None not in span and span[1] <= span[0]):
        raise argparse.ArgumentTypeError(f"{text!r}: give START:END in seconds, "
                                         "END after START (e.g. 0:60 or 60:)")
    return span


def _load_base(name: str):
    from fcemu.sim_bridge.airframe import load_airframe

    return load_airframe(name)


def _say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _fly_stages(truth, controller: str):
    """The stages of `identify --fly`, each's seconds expected from the flight's length."""
    from fcemu.evaluation.identify_closed_loop import planned_flights
    from fcemu.evaluation.identify_flight import excitation
    from fcemu.evaluation.progress import Stages

    flight_s = len(excitation(1000.0, truth.hover_throttle())[0]) / 1000.0
    if controller != "betaflight":
        return Stages({"fly": FLY_S_PER_S * flight_s, "fit": FIT_S_PER_S * flight_s, "report": REPORT_S},
                      _say, calibrate=CALIBRATED), flight_s
    from fcemu.evaluation.identify_betaflight import SPEED

    # Betaflight's SITL flies against the wall clock, at the same pace on any machine.
    return Stages({"fly": flight_s / SPEED, "fit": FIT_S_PER_S * flight_s,
                   "refine": REFINE_S_PER_FLIGHT * planned_flights(truth), "report": REPORT_S},
                  _say, calibrate=CALIBRATED - {"fly"}), flight_s


def identify_command(args) -> int:
    from fcemu.evaluation.identify_airframe import identified_document, identify, write_airframe
    from fcemu.evaluation.identify_report import write_report
    from fcemu.evaluation.progress import Stages
    from fcemu.firmware.errors import UserError

    if bool(args.log) == (args.fly is not None):
        raise UserError("fcemu identify takes a LOG or --fly AIRFRAME, one of them")
    if args.fly is None and args.perturb_seed is not None:
        raise UserError("--perturb-seed draws the airframe --fly flies; there is none to draw without --fly")
    base = _load_base(args.base)
    truth = flown_by = None
    if args.fly is not None:
        out_dir = Path(args.out)
        truth = _flown_airframe(args.fly, args.perturb_seed, out_dir)
        stages, flight_s = _fly_stages(truth, args.controller)
        stages.start("fly", f"flying the identification flight on {truth.name}'s twin ({flight_s:.0f} s of "
                            f"flight, {'Betaflight' if args.controller == 'betaflight' else 'lockstep'})")
        if args.controller == "betaflight":
            log_path = _fly_betaflight(truth, out_dir)
        else:
            from fcemu.evaluation.identify_flight import fly_identification, identification_controller

            controller, flown_by = identification_controller(truth, args.controller, out_dir)
            log_path = fly_identification(truth, controller, seed=args.seed).write(
                out_dir / "flight.ulg", {"ver_hw": f"fcemu SITL {truth.name}"})
        stages.start("fit", f"identifying the twin from {log_path}")
        airframe_path = out_dir / "airframe.json"
        name = f"{truth.name}_identified"
    else:
        airframe_path = Path(args.out)
        if airframe_path.is_dir():
            raise UserError(f"--out {airframe_path}: a folder; name the airframe file to write")
        out_dir = airframe_path.parent
        name = airframe_path.stem
        # Quiet until the log is read and fitted: a log that cannot be is refused in one line.
        stages = Stages({}, _say, calibrate=CALIBRATED)
        stages.start("fit", None)
    from fcemu.evaluation.flight_logs import read_flight_logs
    from fcemu.evaluation.identify_log import joined
    from fcemu.evaluation.replay import span_of

    log = span_of(joined(read_flight_logs(args.log or [log_path])), args.span)
    log_path = log.path
    if args.fly is None:
        stages.expect("fit", FIT_S_PER_S * float(log.t[-1] - log.t[0]))
    ident = identify(log, base, args.base)
    document = identified_document(ident, name)
    airframe = write_airframe(document, airframe_path)
    refinement = None
    if log.header is not None:
        refinement = _refined(log, document, airframe_path, out_dir, args.refine, stages)
        airframe = write_airframe(document if refinement is None else refinement[1], airframe_path)
        refinement = None if refinement is None else refinement[0]
    stages.expect("report", REPORT_S)
    stages.start("report", "writing the report" if args.fly is not None or refinement is not None else None)
    report, figures = write_report(ident, airframe, airframe_path, out_dir, truth, flown_by=flown_by,
                                   refinement=refinement)
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


def refined_with_progress(log, airframe, controller: str, stream=None):
    """`identify_closed_loop.refine`, its flights counted on stderr (a bar on a terminal, else a line at
    each quarter) with the time left: the seconds per flight so far times the most flights left."""
    from fcemu.evaluation.identify_closed_loop import planned_flights, refine
    from fcemu.evaluation.progress import Counted

    least = float("inf")
    with Counted("closed-loop refinement", planned_flights(airframe), "flight", stream) as count:
        def progress(done: int, planned: int, mismatch: float) -> None:
            nonlocal least
            least = min(least, mismatch)
            count.update(done, planned, f"least mismatch {least:.4f}")

        return refine(log, airframe, controller, progress)


def _refined(log, document: dict, airframe_path: Path, out_dir: Path, refine: bool, stages):
    """The log's own tune written as pid_log.json; with `refine`, (the refinement, the refined file)."""
    from fcemu.evaluation.identify_blackbox import own_tune
    from fcemu.evaluation.identify_closed_loop import STRETCH_S, planned_flights, refined_document
    from fcemu.sim_bridge.airframe import load_airframe

    tune_path = out_dir / "pid_log.json"
    tune = own_tune(log)
    tune_path.write_text(json.dumps(tune, indent=2) + "\n")
    print(f"the log's own tune: {tune_path} (what fcemu's PID does not model is listed in it)",
          file=sys.stderr)
    if not refine:
        stages.skip("refine")
        return None
    airframe = load_airframe(airframe_path)
    planned = planned_flights(airframe)
    stages.expect("refine", REFINE_S_PER_FLIGHT * planned)
    stages.expect("report", REPORT_S)
    stages.start("refine", f"refining the twin in closed loop: the log's own tune flies it on "
                           f"{STRETCH_S:g} s of the log, {planned} flights at most")
    refinement = refined_with_progress(log, airframe, f"pid:{tune_path}")
    return refinement, refined_document(document, refinement, log.name)


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
