"""`fcemu bound`: the lower bound on the evaluator's commands (`evaluation.bound`), and each
--controller's Error against it."""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from fcemu.evaluation.bound import error_bounds, rig_constants, tail_axes
from fcemu.evaluation.metrics import AXES, compute_metrics
from fcemu.evaluation.runner import EvalConfig, run_controller
from fcemu.firmware.errors import UserError
from fcemu.firmware.timing import available_cpus
from fcemu.sim_bridge.tasks import episodic_commands


def bound_command(args) -> int:
    """`fcemu bound`: the bound on the evaluator's commands, and each --controller's Error against it."""
    if args.episodes < 1 or args.horizon < 3 or args.gyro_passes < 0 or args.jobs < 0:
        raise UserError("bound: --episodes must be ≥ 1, --horizon ≥ 3, --gyro-passes and --jobs ≥ 0")
    rig = rig_constants(args.airframe)  # refuses an airframe the programme does not model, before any work
    progress = sys.stderr.isatty() and not args.json
    commands = episodic_commands(args.seed, args.episodes)
    t0 = time.perf_counter()
    found = error_bounds(commands, args.horizon, args.gyro_passes, args.jobs or available_cpus(), progress,
                         args.airframe)
    per_command = np.array([b.bound for b in found])
    split = np.array([b.split for b in found]).mean(axis=0)
    tails = tail_axes(rig, args.horizon)
    out: dict = {"episodes": args.episodes, "seed": args.seed, "horizon": args.horizon,
                 "tail_axes": [AXES[j] for j in tails],
                 "airframe": args.airframe, "bound_sum": round(float(per_command.mean()), 2),
                 "split_at_optimum": {a: round(float(v), 2) for a, v in zip(AXES, split, strict=True)},
                 "without_gyro_sum": round(float(np.mean([b.without_gyro for b in found])), 2),
                 "gyro_passes": args.gyro_passes, "wall_s": round(time.perf_counter() - t0, 1),
                 "controllers": []}
    if args.gyro_passes:
        out["estimate_sum"] = round(float(np.mean([b.estimate for b in found])), 2)
    from fcemu.evaluation.evaluate import fallback_for

    cfg = EvalConfig(task="episodic", episodes=args.episodes, seed=args.seed, airframe=args.airframe,
                     fallback=fallback_for(args.airframe, args.fallback, args.controller or []))
    for spec in args.controller or []:
        traces = run_controller(spec, cfg, progress=progress)
        m = compute_metrics(traces)
        error = {a: round(m.stat("error", a).mean, 2) for a in AXES}
        total = sum(error.values())
        covered = np.abs(traces.setpoint - traces.rate)  # the samples the bound is of: the horizon's, and
        covered[:, args.horizon:, [j for j in range(3) if j not in tails]] = 0.0  # the tail's
        covered_error = covered.sum(axis=(1, 2))
        out["controllers"].append({"controller": spec, "error": error, "error_sum": round(total, 2),
                                   "times_bound": round(total / out["bound_sum"], 4),
                                   "below_bound": int((covered_error < per_command).sum())})
    if args.json:
        print(json.dumps(out))
        return 0
    tail = f" ({'/'.join(out['tail_axes'])} to the episode's end)" if tails else ""
    print(f"lower bound on the Error, {args.episodes} commands (seed {args.seed}), "
          f"horizon {args.horizon} steps{tail}, nominal {args.airframe}: {out['bound_sum']:.1f}")
    print("  the optimum's split over roll/pitch/yaw (not a bound per axis): "
          + "/".join(f"{v:.1f}" for v in split))
    extra = (f"; with its own trajectory's gyroscopic term {out['estimate_sum']:.1f}"
             if args.gyro_passes else "")
    print(f"  estimates, not bounds: without the gyroscopic term {out['without_gyro_sum']:.1f}{extra}")
    for c in out["controllers"]:
        print(f"{c['controller']:>32}: error " + "/".join(f"{v:.1f}" for v in c["error"].values())
              + f" (sum {c['error_sum']:.1f}) = {c['times_bound']:.3f} × the bound; "
              f"below it on {c['below_bound']} of {args.episodes} commands")
    return 0
