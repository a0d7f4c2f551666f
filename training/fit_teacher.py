"""`fcemu fit`'s teacher stage: the model-based teacher's speed, then its shape (the share of yaw it
serves first, its braking share, its damping), chosen on the tuning commands, each teacher flown alone
through the action mapping on the nominal twin against the tuned PID (`training.fit` composes the
stages)."""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from fcemu.training.fit_options import FitOptions
from fcemu.training.inversion_teacher import BRAKING_SHARE, DAMPING, YAW_FIRST

AXES = ("roll", "pitch", "yaw")
# The teacher's speed is the airframe's: a slow-motored one rises late at the default, a quick one can
# go faster. Each is flown alone through the action mapping on SPEED_COMMANDS of the tuning commands, on
# the nominal twin. A student is smoother than its teacher, by how much differs per airframe, so the
# teachers whose motors are within SMOOTHNESS_BAR / STUDENT_SMOOTHING × the PID's are admitted
# (`first_teacher` picks among them), and the first one's student judged on the same commands: one
# rougher than the bar allows is taught again by the next slower admitted teacher (docs/results/fit.md).
TEACHER_SPEEDS = (0.5, 0.35, 0.25, 0.18, 0.13, 0.1)  # time constants in motor lags, the default first
SPEED_COMMANDS = 20
# The least share of its teacher's motor roughness a student keeps, per kind of student: one of noisy,
# delayed sensors is smoothed less, since averaging its history cannot remove the noise.
STUDENT_SMOOTHING = {"exact": 0.6, "sensed": 0.8}
# Students fly within a point of their teachers' Error ratio on other commands (docs/results/fit.md),
# so teachers within ERROR_TIE of the least Error are alike to them; ERROR_ROOM under the bar's ratio
# leaves that point and the difference between 20 tuning commands and 50 held out.
ERROR_TIE = 0.01
ERROR_ROOM = 0.03
# The teacher's shape, flown at its chosen speed: the share of yaw it serves first while roll and pitch
# gather speed, and how early it brakes (its braking curve's jerk in shares of the axis's authority per
# motor lag). Either costs some airframes nothing and lowers others' Error and Peaks, so each pair is
# flown and the least Error admitted taken (docs/results/fit.md, the teacher's shape).
YAW_FIRST_CHOICES = (0.0, YAW_FIRST)
BRAKING_CHOICES = (BRAKING_SHARE, 0.3, 0.2)
# Then the chosen shape more damped: it keeps the Error with smoother motors and lower Peaks, rising a
# little later, so it is taken only where the shape's admission (Rise included) allows it and its
# highest Peak is lower (docs/results/fit.md, the teacher's damping).
MORE_DAMPING = 0.85


def student_kind(airframe: Any) -> str:
    """The kind of student the airframe gets: `sensed`, reading SENSED_MEMORY ticks of sensors with
    noise, vibration or delay while its teacher reads the truth, or `exact`, reading what it does."""
    return "sensed" if airframe.gyro_effects or airframe.telemetry_effects else "exact"


def tuning_flight(opts: FitOptions, spec: str, controller: Any = None, fallback: str | None = None,
                  as_given: bool = False) -> Any:
    """`spec` (or the `controller` object) flown on the teacher stage's tuning commands (seed S) on
    the nominal twin (`as_given`: on the airframe with its effects on): its `EvalMetrics`."""
    from dataclasses import replace

    from fcemu.evaluation.metrics import compute_metrics
    from fcemu.evaluation.runner import EvalConfig, run_controller
    from fcemu.sim_bridge.airframe import load_airframe
    from fcemu.training.pid_tune import nominal

    cfg = EvalConfig(episodes=min(SPEED_COMMANDS, opts.episodes), seed=opts.seed, airframe=opts.airframe)
    cfg = replace(cfg, fallback=fallback) if fallback else cfg
    airframe = load_airframe(opts.airframe)
    return compute_metrics(run_controller(spec, cfg, progress=False, controller=controller,
                                          airframe=airframe if as_given else nominal(airframe)))


def flown_figures(m: Any) -> dict[str, Any]:
    """What the stage reads of a flight: Error sum, motor roughness, Rise on roll and pitch, Peaks."""
    from fcemu.evaluation.bar import error_sum

    return {"error_sum": round(error_sum(m), 2), "smoothness": round(m.stat("smoothness", "roll").mean, 3),
            "rise_ms": [round(m.stat("rise_ms", a).mean, 1) for a in AXES[:2]],
            "peak_pct": [round(m.stat("peak_pct", a).mean, 1) for a in AXES]}


Flight = tuple[FitOptions, str | dict[str, Any], Any]  # (opts, `pid:FILE` or a teacher's kwargs, airframe)


def _flight_figures(job: Flight) -> dict[str, Any]:
    """One flight of the stage (a worker process's job): a PID preset's, `pid:FILE`, where the airframe
    is None; else a teacher's on that airframe, the spec its `InversionTeacher` keyword arguments."""
    from fcemu.training.inversion_teacher import InversionController, InversionTeacher

    opts, spec, airframe = job
    if airframe is None:
        return flown_figures(tuning_flight(opts, spec))
    teacher = InversionTeacher(airframe, **spec)
    return flown_figures(tuning_flight(opts, "inversion", InversionController(teacher, mapped=True)))


Flights = Callable[[list[Flight]], list[dict[str, Any]]]


@contextmanager
def stage_flights(jobs: int):
    """`fly(jobs)`: the figures of independent flights, `jobs` worker processes at a time (in this one
    where 1): a stage's speeds and shapes are a dozen flights of 20 commands, each on one core."""
    if jobs <= 1:
        yield lambda work: [_flight_figures(job) for job in work]
        return
    with ProcessPoolExecutor(jobs, mp_context=mp.get_context("spawn")) as pool:
        yield lambda work: list(pool.map(_flight_figures, work))


def teacher_stage(opts: FitOptions, pid: Path, log: Any) -> dict[str, Any]:
    """The teacher's time constant in motor lags (`TEACHER_SPEEDS`), then its shape (`shape_choice`:
    the share of yaw it serves first and its braking share; `damping_choice`: its damping ratio; each
    unless given), on the tuning commands; the flights of each step `opts.jobs` at a time."""
    with stage_flights(opts.jobs) as fly:
        return _teacher_stage(opts, pid, log, fly)


def _teacher_stage(opts: FitOptions, pid: Path, log: Any, fly: Flights) -> dict[str, Any]:
    from fcemu.evaluation.bar import SMOOTHNESS_BAR
    from fcemu.sim_bridge.airframe import load_airframe
    from fcemu.training.pid_tune import nominal

    loaded = load_airframe(opts.airframe)
    student, airframe = student_kind(loaded), nominal(loaded)
    given = {"yaw_first": opts.yaw_first or 0.0, "braking": opts.braking or BRAKING_SHARE}
    given |= {} if opts.damping is None else {"damping": opts.damping}
    ref, *speeds = fly([(opts, f"pid:{pid}", None)]
                       + [(opts, {"lag_multiple": m, **given}, airframe) for m in TEACHER_SPEEDS])
    limit = SMOOTHNESS_BAR / STUDENT_SMOOTHING[student] * ref["smoothness"]
    flown = [{"lag_multiple": m, **f} for m, f in zip(TEACHER_SPEEDS, speeds, strict=True)]
    for f in flown:
        log(f"  teacher at {f['lag_multiple']:g} motor lags: Error {f['error_sum']:.1f}, motors "
            f"{f['smoothness']:.2f}, Rise {'/'.join(map(str, f['rise_ms']))} ms (the PID "
            f"{ref['error_sum']:.1f}, {ref['smoothness']:.2f}, {'/'.join(map(str, ref['rise_ms']))})")
    admitted = [f for f in flown if f["smoothness"] <= limit] or flown[:1]
    first = first_teacher(admitted, ref)
    slower = [f["lag_multiple"] for f in admitted if f["lag_multiple"] > first["lag_multiple"]]
    record = {"lag_multiple": first["lag_multiple"], "order": [first["lag_multiple"], *sorted(slower)],
              "flown": flown, "pid_error_sum": ref["error_sum"], "pid_smoothness": ref["smoothness"],
              "pid_rise_ms": ref["rise_ms"], "pid_peak_pct": ref["peak_pct"], "student": student,
              "commands": min(SPEED_COMMANDS, opts.episodes), "yaw_first": given["yaw_first"],
              "braking": given["braking"], "damping": given.get("damping", DAMPING), "shapes": [],
              "dampings": []}
    chosen = first
    if opts.yaw_first is None or opts.braking is None:
        record |= shape_choice(opts, airframe, first, ref, limit, log, fly)
        chosen = next((f for f in record["shapes"] if (f["yaw_first"], f["braking"])
                       == (record["yaw_first"], record["braking"])), first)
    if opts.damping is None:
        record |= damping_choice(opts, airframe, record, chosen, first, ref, limit, log, fly)
    return record


def first_teacher(admitted: list[dict[str, Any]], pid: dict[str, Any]) -> dict[str, Any]:
    """Error and Rise are lines of the bar, not scores. The slowest (smoothest) teacher within
    `ERROR_TIE` of the least Error, unless it rises later than the PID on roll or pitch (`rise_ms`,
    means); then, of the faster ones whose Error leaves `ERROR_ROOM` under the bar's ratio, the
    slowest that rises in time (the smoothest meeting both lines: its student is the likeliest to
    keep the motor line), or the fastest where none does."""
    from fcemu.evaluation.bar import ERROR_RATIO_BAR

    def in_time(f: dict[str, Any]) -> bool:
        return all(t <= p for t, p in zip(f["rise_ms"], pid["rise_ms"], strict=True))

    least = min(f["error_sum"] for f in admitted)
    best = max((f for f in admitted if f["error_sum"] <= (1.0 + ERROR_TIE) * least),
               key=lambda f: f["lag_multiple"])
    if in_time(best):
        return best
    roomy = [f for f in admitted if f["lag_multiple"] < best["lag_multiple"]
             and f["error_sum"] <= (ERROR_RATIO_BAR - ERROR_ROOM) * pid["error_sum"]]
    rising = [f for f in roomy if in_time(f)]
    if rising:
        return max(rising, key=lambda f: f["lag_multiple"])
    return min(roomy, key=lambda f: f["lag_multiple"]) if roomy else best


def shape_choice(opts: FitOptions, airframe: Any, without: dict[str, Any], pid: dict[str, Any],
                 limit: float, log: Any, fly: Flights) -> dict[str, Any]:
    """The chosen teacher flown again with each pair of `YAW_FIRST_CHOICES` and `BRAKING_CHOICES` (a
    given one held); the least Error of those `shape_admitted` is taken where it is lower than the
    teacher's as the speed stage flew it by more than `ERROR_TIE`."""
    from itertools import product

    damping = {} if opts.damping is None else {"damping": opts.damping}
    base = (opts.yaw_first or 0.0, opts.braking or BRAKING_SHARE)
    yaws = YAW_FIRST_CHOICES if opts.yaw_first is None else (opts.yaw_first,)
    brakes = BRAKING_CHOICES if opts.braking is None else (opts.braking,)
    shapes = [pair for pair in product(yaws, brakes) if pair != base]
    speed = {"lag_multiple": without["lag_multiple"], **damping}
    flights = fly([(opts, {**speed, "yaw_first": yaw_first, "braking": braking}, airframe)
                   for yaw_first, braking in shapes])
    flown = []
    for (yaw_first, braking), figures in zip(shapes, flights, strict=True):
        flown.append({"yaw_first": yaw_first, "braking": braking, **figures,
                      "admitted": shape_admitted(figures, without, pid, limit)})
        log(f"  {yaw_first:g} of yaw first, braking {braking:g}: Error {figures['error_sum']:.1f} against "
            f"{without['error_sum']:.1f}, motors {figures['smoothness']:.2f}, Rise "
            f"{'/'.join(map(str, figures['rise_ms']))} ms, Peak {'/'.join(map(str, figures['peak_pct']))} %"
            + ("" if flown[-1]["admitted"] else " (not admitted)"))
    best = min((f for f in flown if f["admitted"]), key=lambda f: f["error_sum"], default=None)
    if best is None or best["error_sum"] >= (1.0 - ERROR_TIE) * without["error_sum"]:
        best = dict(zip(("yaw_first", "braking"), base, strict=True))
    return {"yaw_first": best["yaw_first"], "braking": best["braking"], "shapes": flown}


def damping_choice(opts: FitOptions, airframe: Any, shape: dict[str, Any], chosen: dict[str, Any],
                   without: dict[str, Any], pid: dict[str, Any], limit: float, log: Any,
                   fly: Flights) -> dict[str, Any]:
    """The chosen shape (`chosen`, its figures as flown) flown again at `MORE_DAMPING`: taken where it
    is `shape_admitted`, its Error within `ERROR_TIE` of the chosen shape's, and its highest Peak lower.
    A tie on Error is no reason to overshoot more: the Peaks are what the twin's effects move."""
    figures, = fly([(opts, {"lag_multiple": without["lag_multiple"], "damping": MORE_DAMPING,
                            "yaw_first": shape["yaw_first"], "braking": shape["braking"]}, airframe)])
    admitted = shape_admitted(figures, without, pid, limit)
    taken = admitted and more_damped_taken(figures, chosen)
    log(f"  damping {MORE_DAMPING:g}: Error {figures['error_sum']:.1f} against {chosen['error_sum']:.1f}, "
        f"motors {figures['smoothness']:.2f}, Rise {'/'.join(map(str, figures['rise_ms']))} ms, Peak "
        f"{'/'.join(map(str, figures['peak_pct']))} % against {'/'.join(map(str, chosen['peak_pct']))}"
        + ("" if admitted else " (not admitted)") + (" (taken)" if taken else ""))
    flown = {"damping": MORE_DAMPING, **figures, "admitted": admitted}
    return {"damping": MORE_DAMPING if taken else DAMPING, "dampings": [flown]}


def more_damped_taken(flown: dict[str, Any], chosen: dict[str, Any]) -> bool:
    """An admitted, more damped teacher replaces the chosen shape's where its Error is within
    `ERROR_TIE` of it and its highest Peak is lower."""
    return (flown["error_sum"] <= (1.0 + ERROR_TIE) * chosen["error_sum"]
            and max(flown["peak_pct"]) < max(chosen["peak_pct"]))


def shape_admitted(flown: dict[str, Any], without: dict[str, Any], pid: dict[str, Any], limit: float) -> bool:
    """A shape keeps the teacher's motors admitted (`limit`), rises on roll and pitch no later than the
    PID or, where the teacher as flown did not, than it, and lifts no axis's Peak past both the bar's
    room over the PID's and the teacher's own as flown."""
    from fcemu.evaluation.bar import PEAK_MARGIN_PCT

    rises = all(r <= max(w, p) for r, w, p in zip(flown["rise_ms"], without["rise_ms"], pid["rise_ms"],
                                                  strict=True))
    peaks = all(p <= max(w, r + PEAK_MARGIN_PCT)
                for p, w, r in zip(flown["peak_pct"], without["peak_pct"], pid["peak_pct"], strict=True))
    return flown["smoothness"] <= limit and rises and peaks
