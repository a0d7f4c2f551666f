"""`fcemu bench sim`: how fast the twin steps, in-process and over the lockstep link.

Each figure is one entry in `MEASUREMENTS`: a name (the JSON key) and a function
`(args) -> float` whose docstring's first line describes it in the table. Adding a
figure is adding one line there.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from collections.abc import Callable
from typing import TypeVar

import numpy as np
from tqdm import tqdm

from fcemu.sim_bridge.airframe import load_airframe
from fcemu.sim_bridge.link import UdpTwinClient, spawn_server
from fcemu.sim_bridge.twin import Twin

T = TypeVar("T")
_CHUNK = 256  # calls between clock reads and progress updates
_WARMUP_CALLS = 500
SITL_PID = "pid:iris"


def rate_per_s(call: Callable[[T], object], arg: T, seconds: float, label: str) -> float:
    """Calls per second of `call(arg)`, run for `seconds` of wall time after a short warm-up."""
    for _ in range(_WARMUP_CALLS):
        call(arg)
    calls = 0
    start = now = time.perf_counter()
    deadline = start + seconds
    with tqdm(desc=label, unit=" calls", unit_scale=True, file=sys.stderr, leave=False,
              disable=None) as progress:
        while now < deadline:
            for _ in range(_CHUNK):
                call(arg)
            calls += _CHUNK
            progress.update(_CHUNK)
            now = time.perf_counter()
    return calls / (now - start)


def _hover_pwm(airframe: str) -> np.ndarray:
    return np.full(4, load_airframe(airframe).hover_pwm())


def twin_steps_per_s(args: argparse.Namespace) -> float:
    """Twin.step in this process (ball-joint rig, hover PWM)"""
    twin = Twin(args.airframe, rig="rig")
    twin.reset(seed=0)
    return rate_per_s(twin.step, _hover_pwm(args.airframe), args.seconds, "twin.step")


def udp_steps_per_s(args: argparse.Namespace) -> float:
    """lockstep round trips over loopback UDP to `fcemu twin serve` in another process"""
    proc, address = spawn_server(rig="rig", airframe=args.airframe)
    try:
        with UdpTwinClient(*address) as client:
            client.reset(seed=0)
            return rate_per_s(client.pwm_write, _hover_pwm(args.airframe), args.seconds, "udp lockstep")
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def env_steps_per_s(args: argparse.Namespace) -> float:
    """RateControlEnv.step, one Gymnasium environment (episodic task)"""
    from fcemu.benchmarks.env import env_steps_per_s as measure

    return measure(seconds=args.seconds, airframe=args.airframe)


def vec_env_steps_per_s(args: argparse.Namespace) -> float:
    """BatchedRateEnv, aggregate environment steps over --envs twins in one call"""
    from fcemu.benchmarks.env import vec_env_steps_per_s as measure

    return measure(n_envs=args.envs, seconds=args.seconds, airframe=args.airframe)


def sitl_lockstep_ticks_per_s(args: argparse.Namespace) -> float:
    """firmware loop ticks (PID + mixer + twin) in lockstep, as `fcemu sitl --speed max`"""
    from fcemu.firmware.loop import ScriptedCommander
    from fcemu.sitl.sitl import build_sitl

    # The Iris's tune on any airframe (on the Iris, "pid"): the figure is the loop's compute, which
    # the gains do not change, and an airframe nobody tuned still has a figure.
    sitl = build_sitl(SITL_PID, rig="rig", realtime=False, airframe=args.airframe,
                      commander=ScriptedCommander([(0.0, (1.0, -1.0, 0.5), 0.7)], controller=SITL_PID))
    start = time.perf_counter()
    end = start + args.seconds
    sitl.loop.run(should_stop=lambda: time.perf_counter() > end)
    return sitl.loop.stats.ticks / (time.perf_counter() - start)


MEASUREMENTS: dict[str, Callable[[argparse.Namespace], float]] = {
    "twin_steps_per_s": twin_steps_per_s,
    "udp_steps_per_s": udp_steps_per_s,
    "env_steps_per_s": env_steps_per_s,
    "vec_env_steps_per_s": vec_env_steps_per_s,
    "sitl_lockstep_ticks_per_s": sitl_lockstep_ticks_per_s,
}


def bench_sim(args: argparse.Namespace) -> int:
    results = {name: round(measure(args), 1) for name, measure in MEASUREMENTS.items()}
    if args.json:
        print(json.dumps(results))
        return 0
    width = max(len(name) for name in results)
    print(f"fcemu bench sim: {args.seconds:g} s per figure")
    for name, value in results.items():
        about = (MEASUREMENTS[name].__doc__ or "").strip().splitlines()[0]
        print(f"  {name:<{width}}  {value:>12,.0f}  {about}")
    return 0
