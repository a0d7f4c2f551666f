"""`fcemu bench inference`: the policy's per-tick cost, as the loop pays it."""

from __future__ import annotations

import json
import time

import numpy as np

from fcemu.firmware.airframe_spec import AirframeSpec
from fcemu.firmware.controller import RateSetpoint
from fcemu.firmware.neural import NeuralRateController
from fcemu.firmware.sensors import SensorFrame
from fcemu.sim_bridge.airframe import DEFAULT_AIRFRAME


def measure_inference(model: str, airframe: AirframeSpec, n: int = 20_000, warmup: int = 2_000) -> dict:
    """Median and p99 of one `infer` (onnxruntime only) and of one full `update` (tick cost), in µs,
    on rotor speeds up to `airframe`'s top speed."""
    ctl = NeuralRateController(model, airframe=airframe)
    rng = np.random.default_rng(0)
    obs = rng.standard_normal((n + warmup, ctl.spec.size)).astype(np.float32)
    infer_ns = np.empty(n, dtype=np.int64)
    for i in range(n + warmup):
        t0 = time.perf_counter_ns()
        ctl.infer(obs[i])
        if i >= warmup:
            infer_ns[i - warmup] = time.perf_counter_ns() - t0
    top = airframe.max_rotor_speed
    frames = [SensorFrame(0, rng.uniform(-5, 5, 3), np.array([0, 0, -9.81]), rng.uniform(0, top, 4))
              for _ in range(256)]
    setpoint = RateSetpoint(np.array([1.0, -2.0, 0.5]), 0.6)
    update_ns = np.empty(n, dtype=np.int64)
    for i in range(n + warmup):
        t0 = time.perf_counter_ns()
        ctl.update(setpoint, frames[i % 256], 0.001)
        if i >= warmup:
            update_ns[i - warmup] = time.perf_counter_ns() - t0
    return {"model": model, "median_us": float(np.median(infer_ns)) / 1e3,
            "p99_us": float(np.percentile(infer_ns, 99)) / 1e3,
            "update_median_us": float(np.median(update_ns)) / 1e3,
            "update_p99_us": float(np.percentile(update_ns, 99)) / 1e3, "samples": n}


def bench_inference(args) -> int:
    from fcemu.firmware.controllers import default_controller

    model = args.model or default_controller()
    if not model.endswith(".onnx"):
        raise SystemExit("fcemu bench inference: no policy given and none shipped; pass --model FILE.onnx")
    from fcemu.sim_bridge.airframe_spec import airframe_spec

    r = measure_inference(model, airframe_spec(getattr(args, "airframe", DEFAULT_AIRFRAME)), args.samples)
    print(json.dumps(r) if args.json else
          f"{r['model']}: onnxruntime median {r['median_us']:.1f} µs, p99 {r['p99_us']:.1f} µs; "
          f"full controller update (observation + inference + mapping) median "
          f"{r['update_median_us']:.1f} µs, p99 {r['update_p99_us']:.1f} µs over {r['samples']} samples")
    return 0
