"""`fcemu fit`: from an airframe to its tuned PID, a policy that beats it, and the report.

    fcemu fit --airframe racer5 --out runs/fit_racer5 --json

Top to bottom, one stage each:

1. **The PID**: DIR/pid.json where `fcemu tune` wrote it for this airframe (by the digest of the
   airframe it records), tuned on purpose; else a shipped airframe named by name has its shipped
   tune (`firmware/presets/`), the PID `--controller pid` flies on it, so the policy meets the
   opponent a user has; `--pid` names another. Otherwise (an airframe file, or `--tune`) `fcemu
   tune` (`training.pid_tune`) on the tuning commands (seed S), with the `--tune-budget-s` share of
   the time: DIR/pid.json and DIR/tune.json. Either way `fcemu bound`'s lower bound on the held-out
   commands (seed S + 1) is solved, or read from its cache.
2. **The teacher**: the airframe's model inverted tick by tick (`training.inversion_teacher`);
   nothing to train. Its speed, then its shape (a share of yaw served first, its braking share,
   its damping), are chosen on the tuning commands, each flown alone through the action mapping
   against the tuned PID (`training.fit_teacher`: Error, Rise and Peak as the bar's lines), and its
   student's motors judged there.
3. **The policy**: a student fitted to the teacher by DAgger on the airframe's twins
   (`fcemu distill inversion`), nominal and drawn from the airframe's ranges; where the sensors
   are not the truth the teacher reads the truth and the student `SENSED_MEMORY` ticks; exported
   as DIR/policy.onnx with the airframe, its envelope and its fallback PID (pid.json beside it) in
   its metadata.
4. **The check**: the policy and the tuned PID on the same held-out commands, against the bar
   for an airframe of one's own (`evaluation.bar.airframe_bar_verdict`), the bound, and the
   policy's time on an STM32F405 (`fcemu bench mcu`, when the Cortex-M tools are installed).

DIR/report.md is the page to read; DIR/fit.json (and stdout with `--json`) has every figure.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from fcemu.firmware.errors import UserError
from fcemu.training.fit_options import STUDENT_STEPS, FitCommand, FitOptions, shipped_pid
from fcemu.training.options import add_arguments, from_args

# The student's recipe for the inversion teacher: half the episodes start in flight, as the check's second
# task does; no gain match, whose nudges straddle the saturation's kinks. Episodes last the check's whole
# second, so a student sees a saturated yaw settle as Success judges it (docs/results/fit.md).
STUDENT_RECIPE = {"learning_rate": 3e-3, "gain_weight": 0.0, "inflight_share": 0.5}
# Where the sensors are not the truth the teacher reads the true rates and rotor speeds, and the student
# its last SENSED_MEMORY ticks of sensors, so it can average the noise its teacher never saw. Four ticks
# of the 48-48 network fit an F405's budget; eight do not (docs/results/fit.md).
SENSED_MEMORY = 4
# A student is judged on SPEED_COMMANDS and checked on the held-out ones, where its motors' ratio to
# the PID's moves by a few percent: one is kept only within this share of the bar's motor line.
STUDENT_MOTOR_MARGIN = 0.95


def tune_stage(opts: FitOptions, out: Path, log: Any) -> dict[str, Any]:
    from fcemu.training.pid_tune_cli import dumps, tune
    from fcemu.training.tune_options import TuneOptions

    tune_opts = TuneOptions(airframe=opts.airframe, seed=opts.seed, episodes=opts.episodes,
                            check_episodes=opts.episodes, budget_s=opts.tune_budget_s, jobs=opts.jobs)
    preset, summary = tune(tune_opts, log=lambda line: log("  tune " + line))
    (out / "pid.json").write_text(dumps(preset))
    summary["preset"] = str(out / "pid.json")
    (out / "tune.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def given_pid_stage(opts: FitOptions, out: Path, log: Any) -> dict[str, Any]:
    """A PID already tuned for the airframe (`--pid`, or DIR/pid.json itself): copied to DIR/pid.json;
    the held-out bound is solved (or read from the tune's cache) as the tune would."""
    from fcemu.evaluation.bound import error_bounds, rig_constants
    from fcemu.firmware.pid_controller import load_preset
    from fcemu.sim_bridge.airframe import load_airframe
    from fcemu.sim_bridge.tasks import episodic_commands
    from fcemu.training.pid_tune import TIGHT_BOUND, cached_bounds
    from fcemu.training.pid_tune_cli import dumps

    try:
        preset = load_preset(opts.pid)
    except (ValueError, KeyError, TypeError, OSError) as exc:
        raise UserError(f"fit: --pid {opts.pid}: {exc}") from None
    if not is_own_pid(opts.pid, out):  # the tune's own file kept as it wrote it
        (out / "pid.json").write_text(dumps(preset))
    commands = episodic_commands(opts.seed + 1, opts.episodes)
    bound = None
    try:
        rig = rig_constants(load_airframe(opts.airframe))
    except UserError as exc:
        log(f"  no bound: {exc}")
    else:
        def solve() -> list[Any]:
            log(f"  bound: solving {len(commands)} linear programmes")
            return error_bounds(commands, jobs=opts.jobs, airframe=opts.airframe, tight=TIGHT_BOUND)

        bound = {"sum": round(float(cached_bounds(rig, commands, solve)[0][:, 0].mean()), 2)}
    return {"held_out": {"bound": bound}, "meets_lines": None, "fails": [], "time_s": None,
            "given": opts.pid}


def student_smoothness(opts: FitOptions, spec: str, pid: Path, as_given: bool) -> float:
    """`spec`'s motor roughness (µs/step) on the speed stage's tuning commands: on the nominal twin, or
    (`as_given`) on the airframe as the check flies it, its sensors and effects on."""
    from fcemu.training.fit_teacher import tuning_flight

    m = tuning_flight(opts, spec, fallback=f"pid:{pid}", as_given=as_given)
    return round(m.stat("smoothness", "roll").mean, 3)


def taught_student(opts: FitOptions, speed: dict[str, Any] | None, out: Path, log: Any) -> dict[str, Any]:
    """The student of the first teacher in the speed stage's order whose student's motors pass the bar
    on the tuning commands (the last one tried otherwise); with the speed given, that teacher's. Its
    `speed` is the speed stage's, with the time constant taught and every student tried.

    The student's motors are judged against the PID's on the twin the bar's check flies: where the
    sensors are not the truth (a `sensed` student's airframe: a noisy, late gyro), both are flown on
    it, since noise moves the PID's roughness far more than the nominal twin shows (a drawn quad's
    PID: 1.3 µs a step there, 12 on its own twin) and a student judged on the nominal twin was
    refused where the check passed it."""
    from fcemu.evaluation.bar import SMOOTHNESS_BAR
    from fcemu.sim_bridge.airframe import load_airframe
    from fcemu.training.fit_teacher import student_kind

    if speed is None:
        return {**distill_stage(opts, out), "speed": None}
    as_given = student_kind(load_airframe(opts.airframe)) == "sensed"
    pid = out / "pid.json"
    pid_rough = student_smoothness(opts, f"pid:{pid}", pid, True) if as_given else speed["pid_smoothness"]
    limit = STUDENT_MOTOR_MARGIN * SMOOTHNESS_BAR * pid_rough
    tried = []
    for multiple in speed["order"]:
        student = distill_stage(replace(opts, lag_multiple=multiple), out)
        rough = student_smoothness(opts, student["policy"], pid, as_given)
        tried.append({"lag_multiple": multiple, "student_smoothness": rough, "pid_smoothness": pid_rough})
        if rough <= limit:
            break
        log(f"  the student of {multiple:g} motor lags: motors {rough:.2f}, over {limit:.2f}"
            + ("; the next slower teacher" if multiple != speed["order"][-1] else ""))
    student["speed"] = {**speed, "lag_multiple": tried[-1]["lag_multiple"], "tried": tried}
    return student


def distill_stage(opts: FitOptions, out: Path) -> dict[str, Any]:
    from fcemu.export.onnx_export import record_metadata
    from fcemu.firmware.contract import FALLBACK_META
    from fcemu.sim_bridge.airframe import load_airframe
    from fcemu.training.distill import INVERSION, distill
    from fcemu.training.distill_config import DistillConfig
    from fcemu.training.fit_teacher import student_kind
    from fcemu.training.inversion_teacher import BRAKING_SHARE, DAMPING, LAG_MULTIPLE

    fields = [opts.lag_multiple, None if opts.damping == DAMPING else opts.damping, opts.yaw_first or None,
              None if opts.braking in (None, BRAKING_SHARE) else opts.braking]
    while fields and fields[-1] is None:
        fields.pop()
    if fields and fields[0] is None:
        fields[0] = LAG_MULTIPLE
    teacher = ":".join([INVERSION, *("" if f is None else f"{f:g}" for f in fields)])
    airframe = load_airframe(opts.airframe)
    kind = student_kind(airframe)
    sensed = kind == "sensed"
    cfg = DistillConfig(teacher=teacher, out=str(out / "student"), airframe=opts.airframe,
                        net_arch=opts.net_arch, rounds=opts.rounds, envs=opts.envs,
                        steps=opts.steps or STUDENT_STEPS[kind],
                        fit_steps=opts.fit_steps, seed=opts.seed, threads=opts.jobs, progress=opts.progress,
                        privileged=sensed, memory=SENSED_MEMORY if sensed else None, **STUDENT_RECIPE)
    summary = distill(cfg)
    policy = out / "policy.onnx"
    policy.write_bytes(Path(summary["export"]["out"]).read_bytes())
    # the PID beside it flies when it faults, without a --fallback to name it
    record_metadata(policy, {FALLBACK_META: "pid.json"})
    return {"teacher": teacher, "rounds": opts.rounds, "net_arch": list(opts.net_arch),
            "teacher_reads_truth": sensed, "memory": cfg.memory or 1,
            "inputs": summary["inputs"], "steps": cfg.steps, "env_steps": summary["env_steps"],
            "imitation_mse": summary["history"][-1]["imitation_mse"], "policy": str(policy)}


def check_stage(opts: FitOptions, policy: Path, pid: Path, bound_sum: float | None,
                out: Path) -> dict[str, Any]:
    from fcemu.evaluation.bar import airframe_bar_verdict
    from fcemu.evaluation.metrics import compute_metrics
    from fcemu.evaluation.runner import EvalConfig, run_controller
    from fcemu.evaluation.step_plots import plot_steps
    from fcemu.training.fit_report import STEP_PLOT, metrics_json

    mcu_us, mcu_note = None, "not measured (--no-mcu)"
    if opts.mcu:
        from fcemu.export.c.build import CExportError
        from fcemu.export.c.target import bench_mcu, missing_tools

        missing = missing_tools()
        if missing:
            mcu_note = f"not measured: {', '.join(missing)} not installed (make mcu-tools)"
        else:
            try:
                mcu_us = float(bench_mcu(str(policy), str(out / "mcu"))["est_us_at_168mhz"])
                mcu_note = "fcemu bench mcu: the cycle-level estimate at 168 MHz"
            except CExportError as exc:
                mcu_note = f"not measured: {exc}"
    tasks, flown = {}, {}
    for task, title in (("episodic", "from rest"), ("inflight", "in flight, from hover")):
        cfg = EvalConfig(task=task, episodes=opts.episodes, seed=opts.seed + 1, airframe=opts.airframe,
                         fallback=f"pid:{pid}")
        policy_flown = run_controller(str(policy), cfg, progress=False)
        pid_flown = run_controller(f"pid:{pid}", cfg, progress=False)
        flown[title] = {"PID": pid_flown, "policy": policy_flown}
        pol, ref = compute_metrics(policy_flown), compute_metrics(pid_flown)
        verdict = airframe_bar_verdict(pol, ref, bound_sum if task == "episodic" else None, mcu_us)
        tasks[task] = {"policy": metrics_json(pol), "pid": metrics_json(ref), "bar": verdict}
    plot = plot_steps(flown, out / STEP_PLOT, f"{opts.airframe}: the policy and the PID on held-out "
                                              f"commands (seed {opts.seed + 1})")
    return {"seed": opts.seed + 1, "episodes": opts.episodes, "bound_sum": bound_sum, "mcu_us_f405": mcu_us,
            "mcu_note": mcu_note, "tasks": tasks, "step_plot": plot.name,
            "meets_bar": all(t["bar"]["meets_bar"] for t in tasks.values())}


def fit(opts: FitOptions, log: Any = None) -> dict[str, Any]:
    """The three stages and the check; the summary written as DIR/fit.json and DIR/report.md."""
    from fcemu.training.fit_progress import fit_stages
    from fcemu.training.fit_report import command_line, write_report
    from fcemu.training.fit_teacher import teacher_stage
    from fcemu.training.inversion_teacher import BRAKING_SHARE, DAMPING

    log = log or (lambda line: None)
    out = Path(opts.out)
    t0 = time.monotonic()
    stages = fit_stages(opts, log)
    times: dict[str, float] = {}
    if opts.pid is None:
        stages.start("tune", f"tuning the PID for {opts.airframe} in {opts.tune_budget_s:.0f} s, the bound "
                             "included")
        tuned = tune_stage(opts, out, log)
        stages.finish()
        stages.note(f"PID: {tuned['held_out']['tuned']['error_sum']:.1f} on the held-out commands")
    else:
        given = (f"the PID tuned in {opts.pid} by fcemu tune: not tuned again" if is_own_pid(opts.pid, out)
                 else f"the PID: {opts.pid}")
        stages.start("tune", f"{given} (--tune to tune one anew)")
        tuned = given_pid_stage(opts, out, log)
    times["tune"] = round(time.monotonic() - t0, 1)
    speed = None
    if opts.lag_multiple is None:
        stages.start("teacher", "choosing the teacher's speed on the tuning commands")
        t = time.monotonic()
        speed = teacher_stage(opts, out / "pid.json", log)
        times["teacher"] = round(time.monotonic() - t, 1)
    if speed is not None:
        opts = replace(opts, yaw_first=speed["yaw_first"], braking=speed["braking"], damping=speed["damping"])
    first = opts.lag_multiple if speed is None else speed["lag_multiple"]
    stages.start("policy", f"fitting the policy to the model-based teacher ({first:g} motor lags, "
                           f"{opts.yaw_first or 0.0:g} of yaw first, braking "
                           f"{opts.braking or BRAKING_SHARE:g}, damping {opts.damping or DAMPING:g})")
    t = time.monotonic()
    student = taught_student(opts, speed, out, log)
    opts = replace(opts, lag_multiple=student["speed"]["lag_multiple"]) if speed else opts
    times["policy"] = round(time.monotonic() - t, 1)
    stages.start("check", f"policy written ({student['inputs']} inputs); checking it against the PID")
    t = time.monotonic()
    bound = tuned["held_out"].get("bound")
    check = check_stage(opts, Path(student["policy"]), out / "pid.json", bound and bound["sum"], out)
    times["check"] = round(time.monotonic() - t, 1)
    times["total"] = round(time.monotonic() - t0, 1)
    summary = {"airframe": opts.airframe, "command": command_line(opts), "pid": str(out / "pid.json"),
               "policy": student["policy"], "tune": {"meets_lines": tuned["meets_lines"], "given": opts.pid,
                                                      "fails": tuned["fails"], "time_s": tuned["time_s"]},
               "student": student, "check": check, "meets_bar": check["meets_bar"], "time_s": times}
    (out / "fit.json").write_text(json.dumps(summary, indent=2) + "\n")
    write_report(summary, out / "report.md")
    return summary


def is_own_pid(pid: str, out: Path) -> bool:
    """`pid` is DIR/pid.json itself."""
    return Path(pid).resolve() == (out / "pid.json").resolve()


def tuned_in(out: Path, airframe: str) -> str | None:
    """DIR/pid.json where `fcemu tune` (or an earlier fit) tuned it for this airframe: the digest of the
    airframe it records is this one's (a file, its shipped name or a copy of it alike); where it records
    none, its airframe's name or string is this one's."""
    from fcemu.sim_bridge.airframe import load_airframe
    from fcemu.training.pid_tune_cli import airframe_digest

    path = out / "pid.json"
    try:
        tuning = json.loads(path.read_text()).get("tuning", {})
        tuned_for, digest = tuning.get("airframe"), tuning.get("airframe_sha256")
    except (OSError, ValueError, AttributeError):
        return None
    if digest is not None:
        return str(path) if digest == airframe_digest(airframe) else None
    return str(path) if tuned_for in (airframe, load_airframe(airframe).name) else None


def refuse_props_out(airframe: str) -> None:
    """A fit makes a policy, and a policy flies props in only: refused before the tune's minutes."""
    from fcemu.firmware.controllers import PROPS_OUT
    from fcemu.sim_bridge.airframe_spec import airframe_spec

    try:
        spec = airframe_spec(airframe)
    except (OSError, ValueError, KeyError):
        return  # `checked_airframe_and_out` says why it does not load
    if spec.props_out:
        raise UserError(f"fit: {spec.name}'s {PROPS_OUT}; fly its PID (`fcemu tune --airframe {airframe} "
                        "--out DIR`)")


def fit_command(args: Any) -> int:
    import importlib.util

    from fcemu.training.pid_tune_cli import checked_airframe_and_out

    if importlib.util.find_spec("torch") is None:  # before the tune's minutes, not after them
        raise ModuleNotFoundError("the policy is trained with torch", name="torch")
    if args.tune_budget_s <= 0 or min(args.episodes, args.rounds, args.steps or 1, args.envs, args.fit_steps,
                                      *args.net_arch) < 1:
        raise UserError("fit: --tune-budget-s must be > 0; --episodes, --rounds, --steps, --envs, "
                        "--fit-steps and --net-arch ≥ 1")
    if args.damping is not None and not args.damping > 0.0:
        raise UserError("fit: --damping must be > 0")
    if args.yaw_first is not None and not 0.0 <= args.yaw_first <= 1.0:
        raise UserError("fit: --yaw-first must be in [0, 1]")
    if args.braking is not None and not args.braking > 0.0:
        raise UserError("fit: --braking must be > 0")
    command = from_args(FitCommand, args)
    if args.pid and command.tune:
        raise UserError("fit: --pid or --tune, not both")
    refuse_props_out(args.airframe)
    out = checked_airframe_and_out("fit", args.airframe, args.out)
    # the folder's own tune before the shipped one: it was tuned for this airframe on purpose
    pid = args.pid or (None if command.tune else tuned_in(out, args.airframe) or shipped_pid(args.airframe))
    opts = from_args(FitOptions, args, out=str(out), pid=pid, progress=sys.stderr.isatty())
    summary = fit(opts, log=lambda line: print(line, file=sys.stderr, flush=True))
    verdict = "meets the bar" if summary["meets_bar"] else "does not meet the bar (see report.md)"
    print(f"wrote {summary['pid']}, {summary['policy']} and {out / 'report.md'} in "
          f"{summary['time_s']['total']:.0f} s; the policy {verdict}", file=sys.stderr)
    if command.json:
        print(json.dumps(summary))
    return 0


def register(sub: Any) -> None:
    p = sub.add_parser("fit", help="from an airframe to its tuned PID, a policy that beats it, and a report")
    add_arguments(p, FitOptions, FitCommand)
    p.set_defaults(handler="fcemu.training.fit:fit_command")
