"""`fcemu bench loop` and `fcemu bench inference`: the firmware's timing budget, measured."""

from __future__ import annotations

import json
import sys

from firmware.sitl import build_sitl


def measure_loop(controller: str, seconds: float, rate_hz: float, rig: str = "rig") -> dict:
    """Fly the scripted doublets in real time and return DESIGN.md's `bench loop` figures."""
    sitl = build_sitl(controller, rig=rig, rate_hz=rate_hz, realtime=True)
    stats = sitl.loop.run(seconds)
    return {"rate_hz": rate_hz, "seconds": seconds, "controller": controller, **stats.summary(),
            "controller_faults": sum(sitl.loop.faults.values())}


def bench_loop(args) -> int:
    from firmware.controllers import default_controller

    controller = args.controller or default_controller()
    rates = args.rate or [1000.0]
    results = []
    for rate in rates:
        if not args.json:
            print(f"running {controller} at {rate:.0f} Hz for {args.seconds:g} s ...", file=sys.stderr)
        results.append(measure_loop(controller, args.seconds, rate, args.rig))
    if args.json:
        print(json.dumps(results[0] if len(results) == 1 else results))
        return 0
    for r in results:
        pe, cu = r["period_error_us"], r["compute_us"]
        miss_pct = 100.0 * r["deadline_misses"] / max(r["ticks"], 1)
        print(f"{r['rate_hz']:6.0f} Hz  ticks {r['ticks']:7d}  misses {r['deadline_misses']:5d} "
              f"({miss_pct:.3f}%)  period error µs p50/p99/p99.9/max {pe['p50']:.0f}/{pe['p99']:.0f}/"
              f"{pe['p999']:.0f}/{pe['max']:.0f}  compute µs {cu['p50']:.0f}/{cu['p99']:.0f}/"
              f"{cu['p999']:.0f}/{cu['max']:.0f}")
    return 0
