"""`fcemu tune`'s command: the tune (`training.pid_tune`), its preset and its summary, and why a
line is not met."""

from __future__ import annotations

import json
import signal
import sys
from pathlib import Path
from typing import Any

from fcemu.firmware.errors import UserError
from fcemu.firmware.timing import available_cpus
from fcemu.sim_bridge.airframe import load_airframe
from fcemu.training.pid_search import AXES
from fcemu.training.pid_tune import (
    COST_VERSION,
    REFERENCE,
    SMOOTHNESS_CAP,
    SUCCESS_LINE,
    TIMES_BOUND_LINE,
    TuneOptions,
    Tuner,
)


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


def tune(opts: TuneOptions, log: Any = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """(the tuned preset with its "tuning" record, the summary `--json` prints)."""
    tuner = Tuner(opts, log)
    tuned, record, check = tuner.run()
    wall = round(tuner.elapsed(), 1)
    command = (f"fcemu tune --airframe {opts.airframe} --seed {opts.seed} --episodes {opts.episodes} "
               f"--check-episodes {opts.check_episodes} --rounds {opts.rounds} --budget-s {opts.budget_s:g} "
               f"--jobs {opts.jobs}")
    summary = {"airframe": opts.airframe, "cost_version": COST_VERSION, "command": command,
               "physics": tuner.physics.to_json(),
               "reference": {"airframe": REFERENCE[0], "preset": REFERENCE[1],
                             "physics": tuner.ref_physics.to_json()},
               "gyro_noise": opts.gyro_noise, "smoothness_cap": SMOOTHNESS_CAP, **record,
               "held_out": check, "meets_lines": check["meets_lines"], "fails": failure_reasons(check),
               "time_s": {"bound": check["wall_s"]["bound"],
                          **{s["stage"]: s["wall_s"] for s in record["stages"]},
                          "check": check["wall_s"]["flights"], "total": wall},
               "budget_s": opts.budget_s}
    preset = {"name": tuner.start["name"],
              "description": (f"PID tuned for the {tuner.airframe.name} twin by `{command}`: the Iris tune "
                              "carried over by the loop's physics, then searched on the noise-free twin and "
                              "with a noisy gyro. Gains in GymFC units: see firmware/pid.py."),
              "pid": tuned["pid"], "mixer": tuned["mixer"],
              "tuning": {k: summary[k] for k in ("airframe", "cost_version", "command", "seed", "episodes",
                                                 "gyro_noise", "smoothness_cap", "stages", "tuning_set",
                                                 "held_out", "time_s")}}
    return preset, summary


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
    out = checked_airframe_and_out("tune", args.airframe, args.out)
    jobs = args.jobs or available_cpus()
    opts = TuneOptions(args.airframe, args.seed, args.episodes, args.check_episodes, args.budget_s, jobs,
                       args.rounds)
    before = signal.signal(signal.SIGTERM, _exit_on_sigterm)  # so the workers are stopped with the tune
    try:
        preset, summary = tune(opts, log=lambda line: print(line, file=sys.stderr, flush=True))
    finally:
        signal.signal(signal.SIGTERM, before)
    path = out / "pid.json"
    path.write_text(dumps(preset))
    summary["preset"] = str(path)
    (out / "tune.json").write_text(json.dumps(summary, indent=2) + "\n")
    verdict = "meets every line" if summary["meets_lines"] else "fails: " + "; ".join(summary["fails"])
    print(f"wrote {path} in {summary['time_s']['total']:.0f} s; held out: {verdict}", file=sys.stderr)
    if args.json:
        print(json.dumps(summary))
    return 0
