"""`fcemu tune`'s command: the tune (`training.pid_tune`), its preset and its summary, and why a
line is not met."""

from __future__ import annotations

import json
import signal
import sys
from pathlib import Path
from typing import Any

from fcemu.firmware.errors import UserError
from fcemu.sim_bridge.airframe import load_airframe
from fcemu.training.options import command_line, from_args
from fcemu.training.pid_search import AXES
from fcemu.training.pid_tune import (
    COST_VERSION,
    REFERENCE,
    SMOOTHNESS_CAP,
    SUCCESS_LINE,
    TIMES_BOUND_LINE,
    Tuner,
)
from fcemu.training.tune_options import TuneCommand, TuneOptions


def failure_reasons(check: dict[str, Any]) -> list[str]:
    """One sentence per line the held-out check does not meet, with the numbers that say why."""
    reasons = []
    lines, tuned = check["lines"], check["tuned"]
    if lines["error_times_bound"]["met"] is False:
        bound = check["bound"]
        split = bound["split_at_optimum"]
        axes = ", ".join(f"{a} {tuned['error'][a]:.1f} vs {split[a]:.1f}" for a in AXES)
        worst = max(AXES, key=lambda a: tuned["error"][a] - split[a])
        reasons.append(f"Error {tuned['error_sum']:.1f} = {tuned['times_bound']:.3f} × the bound "
                       f"{bound['sum']:.1f} (line {TIMES_BOUND_LINE}); per axis, tuned vs the optimum's "
                       f"split: {axes}; most of the excess is on {worst}")
    elif lines["error_times_bound"]["met"] is None:
        reasons.append(f"no bound: {check['bound_refused']}")
    if not lines["success_pct"]["met"]:
        low = [f"{a} {v:.1f} %" for a, v in tuned["success_pct"].items() if v is None or v < SUCCESS_LINE]
        reasons.append(f"Success below {SUCCESS_LINE} % on {', '.join(low)}")
        limits = check["settle_limits"]
        for a, n in limits["unsettleable_commands"].items():
            if n:
                accel = limits["max_angular_acceleration_rad_s2"][a]
                largest = limits["largest_settleable_rad_s"][a]
                reasons.append(f"physics: {a} accelerates at most {accel:.1f} rad/s² (every motor at full "
                               f"thrust or off), so no controller meets Success on a {a} command above "
                               f"{largest:.2f} rad/s; {n} of the {check['episodes']} held-out commands ask "
                               f"for more")
    if not lines["smoothness_noisy_gyro_vs_allowance"]["met"]:
        rough = lines["smoothness_noisy_gyro_vs_allowance"]["value"]
        reasons.append(f"motors {rough:.2f} × the noise allowance on the noisy gyro "
                       f"({check['noise_allowance_us']:.2f} µs; line {SMOOTHNESS_CAP})")
    return reasons


def dumps(preset: dict[str, Any]) -> str:
    """Indented JSON with every list of numbers on one line (the presets' layout)."""
    import re

    text = json.dumps(preset, indent=2)
    flat = re.sub(r"\[\s+([^\[\]{}]*?)\s+\]", lambda m: "[" + re.sub(r"\s+", " ", m.group(1)) + "]", text)
    return flat + "\n"


def airframe_digest(airframe: str) -> str:
    """sha256 of the twin an airframe (a shipped name or a file) builds: every number of it, not its name
    or its citations, so that its file, its shipped name and a copy anywhere give the same digest and
    an edited number another one. A tune records it; `fcemu fit` reuses a tune of the same digest."""
    import dataclasses
    import hashlib

    import numpy as np

    def plain(value: Any) -> Any:
        if isinstance(value, np.ndarray | np.generic):
            return value.tolist()
        raise TypeError(f"cannot digest {type(value).__name__}")

    content = dataclasses.asdict(load_airframe(airframe))
    for label in ("name", "tune_of", "effect_sources"):
        del content[label]
    text = json.dumps(content, sort_keys=True, separators=(",", ":"), default=plain)
    return hashlib.sha256(text.encode()).hexdigest()


def tune(opts: TuneOptions, log: Any = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """(the tuned preset with its "tuning" record, the summary `--json` prints)."""
    tuner = Tuner(opts, log)
    tuned, record, check = tuner.run()
    wall = round(tuner.elapsed(), 1)
    command = command_line("fcemu tune", opts)
    summary = {"airframe": opts.airframe, "airframe_sha256": airframe_digest(opts.airframe),
               "cost_version": COST_VERSION, "command": command,
               "physics": tuner.physics.to_json(),
               "reference": {"airframe": REFERENCE[0], "preset": REFERENCE[1],
                             "physics": tuner.ref_physics.to_json()},
               "gyro_noise": opts.gyro_noise, "smoothness_cap": SMOOTHNESS_CAP, **record,
               "held_out": check, "meets_lines": check["meets_lines"], "fails": failure_reasons(check),
               "time_s": {"bound": check["wall_s"]["bound"],
                          "bound_charged": check["wall_s"]["bound_charged"],
                          **{s["stage"]: s["wall_s"] for s in record["stages"]},
                          "check": check["wall_s"]["flights"], "total": wall},
               "budget_s": opts.budget_s}
    preset = {"name": tuner.start["name"],
              "description": (f"PID tuned for the {tuner.airframe.name} twin by `{command}`: the Iris tune "
                              "carried over by the loop's physics, then searched on the noise-free twin and "
                              "with a noisy gyro. Gains in GymFC units: see firmware/pid.py."),
              "pid": tuned["pid"], "mixer": tuned["mixer"],
              "tuning": {k: summary[k] for k in ("airframe", "airframe_sha256", "cost_version", "command",
                                                 "seed", "episodes", "gyro_noise", "smoothness_cap", "stages",
                                                 "tuning_set", "held_out", "time_s")}}
    return preset, summary


STEP_PLOT = "tune_step_response.png"  # beside fit's step_response.png in a shared folder


def _axes(values: dict[str, float | None], fmt: str = ".1f") -> str:
    return " / ".join("—" if values[a] is None else format(values[a], fmt) for a in AXES)


def write_report(summary: dict[str, Any], out: Path, plot: Path | None) -> Path:
    """DIR/tune_report.md: the held-out lines, the tuned PID beside its start and the Iris tune, its step
    responses (`plot`, beside it), the times, and how to fly it."""
    check, times = summary["held_out"], summary["time_s"]
    flown = (("tuned", "tuned_noisy_gyro"), ("start", "start_noisy_gyro"), ("pid_iris", None))
    verdict = "meets every line" if summary["meets_lines"] else "fails: " + "; ".join(summary["fails"])
    bound = check["bound"]

    def row(label: str, cell: Any) -> str:
        cells = (cell(check[k], noisy and check[noisy]) for k, noisy in flown)
        return f"| {label} | {' | '.join(cells)} |"

    lines = [f"# `fcemu tune` for {summary['airframe']}", "", "```", summary["command"], "```", "",
             f"The tuned PID (`{summary['preset']}`) **{verdict}**, on {check['episodes']} held-out "
             f"command{'' if check['episodes'] == 1 else 's'} (seed {check['seed']}).", "",
             "| held out | tuned | start (the Iris tune carried over) | the Iris tune |",
             "|---|---:|---:|---:|",
             row("Error sum", lambda s, n: f"{s['error_sum']:.1f}"
                 + ("" if s.get("times_bound") is None else f" ({s['times_bound']:.3f} × the bound)")),
             row("Error r / p / y", lambda s, n: _axes(s["error"])),
             row("Rise ms r / p / y", lambda s, n: _axes(s["rise_ms"])),
             row("Peak % r / p / y", lambda s, n: _axes(s["peak_pct"])),
             row("Success % r / p / y", lambda s, n: _axes(s["success_pct"])),
             row("motors µs/step, noise-free / noisy gyro",
                 lambda s, n: f"{s['smoothness_us']:.2f}" + (f" / {n['smoothness_us']:.2f}" if n else "")),
             "",
             "Lower bound on the Error (`fcemu bound`, from rest): "
             + (f"{bound['sum']:.1f}." if bound else f"not available ({check.get('bound_refused')})."), ""]
    if plot is not None:
        lines += ["## Step responses", "",
                  "Per axis, the held-out command of median size on that axis, flown again by the tuned PID "
                  "on the noise-free twin: its setpoint, the ±10 % band Success judges from 0.5 s on, and "
                  "the rate.", "", f"![Step responses of the tuned PID]({plot.name})", ""]
    stages = " | ".join(f"{times.get(k, 0.0):.0f} s"
                        for k in ("bound", "clean", "noisy_gyro", "check", "total"))
    lines += ["## Time", "", "| bound | clean | noisy gyro | check | total |", "|---:|---:|---:|---:|---:|",
              f"| {stages} |", "", "## Fly it", "", "```",
              f"fcemu sitl --airframe {summary['airframe']} --controller pid:{summary['preset']}",
              f"fcemu eval --airframe {summary['airframe']} --controller pid:{summary['preset']}", "```", ""]
    path = out / "tune_report.md"  # a fit into the same folder writes report.md
    path.write_text("\n".join(lines), encoding="utf-8")
    return path


def step_plot(opts: TuneOptions, preset: dict[str, Any], out: Path) -> Path:
    """DIR/tune_step_response.png: the tuned PID's step responses on the held-out commands."""
    from fcemu.evaluation.step_plots import plot_steps
    from fcemu.training.pid_tune import held_out_steps

    traces = held_out_steps(opts, preset)
    return plot_steps({f"held out (seed {opts.seed + 1})": {"tuned PID": traces}}, out / STEP_PLOT,
                      f"{opts.airframe}: the tuned PID's step responses", episodes=range(len(AXES)))


def _exit_on_sigterm(signum: int, frame: Any) -> None:
    raise SystemExit(128 + signum)


def checked_airframe_and_out(command: str, airframe: str, out_dir: str) -> Path:
    """The airframe loads and the output directory is writable (made if missing), or one line."""
    try:
        load_airframe(airframe)
    except (FileNotFoundError, ValueError, KeyError, json.JSONDecodeError) as exc:
        raise UserError(f"{command}: cannot load airframe {airframe!r}: {exc}") from None
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        reason = exc.strerror or exc
        raise UserError(f"{command}: --out {out} is not a writable directory: {reason}") from None
    return out


def tune_command(args: Any) -> int:
    """`fcemu tune`: tune, write DIR/pid.json, report on stderr (and one JSON object on stdout)."""
    if args.budget_s <= 0 or min(args.episodes, args.check_episodes, args.rounds) < 1 or args.jobs < 0:
        raise UserError("tune: --budget-s must be > 0, --episodes, --check-episodes and --rounds ≥ 1, "
                        "--jobs ≥ 0")
    command = from_args(TuneCommand, args)
    out = checked_airframe_and_out("tune", args.airframe, command.out)
    opts = from_args(TuneOptions, args)
    before = signal.signal(signal.SIGTERM, _exit_on_sigterm)  # so the workers are stopped with the tune
    try:
        preset, summary = tune(opts, log=lambda line: print(line, file=sys.stderr, flush=True))
    finally:
        signal.signal(signal.SIGTERM, before)
    path = out / "pid.json"
    path.write_text(dumps(preset))
    summary["preset"] = str(path)
    summary["report"] = str(write_report(summary, out, step_plot(opts, preset, out)))
    (out / "tune.json").write_text(json.dumps(summary, indent=2) + "\n")
    verdict = "meets every line" if summary["meets_lines"] else "fails: " + "; ".join(summary["fails"])
    print(f"wrote {path} and {summary['report']} in {summary['time_s']['total']:.0f} s; held out: {verdict}",
          file=sys.stderr)
    if command.json:
        print(json.dumps(summary))
    return 0
