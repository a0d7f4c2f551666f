"""How close to `fcemu bound` a Betaflight-style PID gets on an airframe, for each motor-noise allowance.

    .venv/bin/python benchmarks/pid_noise_pareto.py --airframe crazyflie --start runs/tune_cf/pid.json \
        --clean-minutes 14 --noisy-minutes 20 --caps 1.2 4.35 --jobs 2 --out runs/pareto_cf

`fcemu tune` holds the motors on a noisy gyro within `SMOOTHNESS_CAP` × its noise allowance (the
physics start's roughness, at least the Iris tune's), in a budget of minutes. This is the longer
search that says what such a rule costs, with caps stated against the start alone: a
pattern search on the Error alone (3·ΣError/ΣError_start, plus a point per % of Success below
99.8 on an axis), first on the noise-free twin, where only the PID's structure and the physics
limit it, then from that optimum on the 0.01 rad/s noisy gyro once per cap, with the tune's wall
(100 per unit of roughness above the cap × the start's). Its moves are the tune's, with the filters'
bounds wider (`wider`); a yaw D the start lacks starts at `--yaw-d`. Each result
is flown on the held-out commands (seed S + 1) against the bound: DIR/pareto.json has one row per
cap (and the noise-free one), DIR/pid_cap<C>.json each preset. The search stops at its deadline,
so a rerun on another machine may end elsewhere.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from fcemu.evaluation.bound import rig_constants
from fcemu.training.pid_search import CandidatePool, Knob, Move, Score, SearchState, pattern_search
from fcemu.training.pid_tune import SUCCESS_LINE, TIGHT_BOUND, Tuner, cached_bounds
from fcemu.training.tune_options import TuneOptions


def error_cost(s: Score, start: Score, cap: float | None) -> float:
    if not np.all(np.isfinite(s.error)) or np.any(s.not_risen > 0):
        return float("inf")
    failed = float(np.sum(np.maximum(SUCCESS_LINE - s.success_pct, 0.0)))
    wall = 0.0 if cap is None else 100.0 * max(s.smoothness / start.smoothness - cap, 0.0)
    return float(3.0 * s.error.sum() / start.error.sum() + failed + wall)


def wider(knobs: list[Move]) -> list[Move]:
    """The tune's moves, the filters' cut-offs within 5–1000 Hz (Betaflight's gyro_lpf1 reaches 1000),
    so that what the search finds is not where the tune's box ends (its gains' box is already wide)."""
    def widened(k: Move) -> Move:
        if isinstance(k, Knob) and k.setting.endswith("lowpass_hz"):
            return Knob(k.name, k.setting, k.axis, k.step, 5.0, 1000.0)
        return k

    return [widened(k) for k in knobs]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pid_noise_pareto.py", description=__doc__.splitlines()[0])
    p.add_argument("--airframe", required=True)
    p.add_argument("--start", help="preset to start from (default: the tune's physics start)")
    p.add_argument("--clean-minutes", type=float, default=14.0)
    p.add_argument("--noisy-minutes", type=float, default=20.0)
    p.add_argument("--caps", type=float, nargs="+", default=[1.2])
    p.add_argument("--yaw-d", type=float, default=0.03, help="yaw D to start from where the start has none")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)

    tuner = Tuner(TuneOptions(airframe=args.airframe, jobs=args.jobs))
    start = json.loads(Path(args.start).read_text()) if args.start else tuner.start
    if start["pid"]["kd"][2] <= 0.0:
        start["pid"]["kd"][2] = args.yaw_d
    knobs = wider(tuner.knobs)
    args.out.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    with CandidatePool(tuner.airframe, tuner.opts.gyro_noise, args.jobs) as pool:
        bound = float(cached_bounds(rig_constants(tuner.airframe), tuner.held_out,
                                    lambda: pool.bounds(tuner.held_out, tight=TIGHT_BOUND))[0][:, 0].mean())
        noisy_ref = pool.scores([tuner.start], True, tuner.held_out)[0].smoothness

        def search(preset: dict[str, Any], cap: float | None, minutes: float) -> dict[str, Any]:
            noisy = cap is not None
            ref = pool.scores([tuner.start], noisy, tuner.tuning)[0]
            first = pool.scores([preset], noisy, tuner.tuning)[0]
            state = SearchState(preset, first, error_cost(first, ref, cap))
            state = pattern_search(state, knobs, pool, noisy, tuner.tuning, lambda s: error_cost(s, ref, cap),
                                   time.monotonic() + 60.0 * minutes, 1000,
                                   progress=lambda line: print(line, file=sys.stderr, flush=True),
                                   label="noise-free" if cap is None else f"cap {cap:g}")
            clean, rough = pool.scores([state.preset], False, tuner.held_out)[0], \
                pool.scores([state.preset], True, tuner.held_out)[0]
            row = {"cap": cap, "error_sum": round(float(clean.error.sum()), 1),
                   "times_bound": round(float(clean.error.sum()) / bound, 3), "held_out": clean.to_json(),
                   "noisy_gyro_smoothness_us": round(rough.smoothness, 3),
                   "noisy_gyro_vs_start": round(rough.smoothness / noisy_ref, 2),
                   "flights": state.evaluations, "minutes": minutes}
            name = "pid_noise_free.json" if cap is None else f"pid_cap{cap:g}.json"
            (args.out / name).write_text(json.dumps(state.preset, indent=2) + "\n")
            print(f"{'noise-free' if cap is None else f'cap {cap:g}'}: {row['error_sum']} = "
                  f"{row['times_bound']} × the bound {bound:.1f}, motors on the noisy gyro "
                  f"{row['noisy_gyro_vs_start']} × the start's", file=sys.stderr, flush=True)
            rows.append(row)
            return state.preset

        optimum = search(start, None, args.clean_minutes)
        for cap in args.caps:
            search(optimum, cap, args.noisy_minutes)
    summary = {"airframe": tuner.airframe.name, "bound": round(bound, 2), "seed": tuner.opts.seed,
               "held_out_seed": tuner.opts.seed + 1, "rows": rows}
    (args.out / "pareto.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
