#!/usr/bin/env python3
"""Offboard attitude rates with MAVSDK-Python (4.x, the native binding): connect, arm, start
offboard with a setpoint already streaming (PX4's rule), step through body-rate setpoints, and
measure how the vehicle's rates follow them through MAVSDK's own telemetry; then end offboard
the canonical way, `offboard.stop()` (the vehicle goes to HOLD), and LAND.

    fcemu sitl --controller pid --rig rig       # ball-joint rig: rotates freely, cannot fly away
    python examples/mavsdk_offboard_rates.py

On the free rig (the default of `fcemu sitl`) it takes off at hover thrust while it steps, holds
its altitude and position in HOLD, and lands at the end. MAVSDK 4 runs the MAVSDK core inside
the Python process (no mavsdk_server); the vehicle sends to UDP 14540 for an offboard API, where
this script listens.

Options: --connect (default udpin://0.0.0.0:14540), --rate deg/s, --hold s per step,
--thrust (default: hover), --summary FILE.json.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
import time

from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.offboard import AttitudeRate, OffboardAsync
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

HOVER = 0.745  # Iris hover throttle


def steps(rate: float) -> list[tuple[float, float, float]]:
    """Roll, pitch, yaw (deg/s): each axis out and back, so the attitude ends near where it began."""
    out = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            r = [0.0, 0.0, 0.0]
            r[axis] = sign * rate
            out.append((r[0], r[1], r[2]))
    return out


async def wait_until(stream, predicate, timeout: float):
    async def first():
        async for value in stream:
            if predicate(value):
                return value
    return await asyncio.wait_for(first(), timeout)


async def fly(url: str, rate: float, hold: float, thrust: float) -> dict:
    config = Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)
    async with Mavsdk(config) as mavsdk:
        await mavsdk.add_any_connection(url)
        system = await mavsdk.first_autopilot(timeout_s=30.0)
        if system is None:
            raise RuntimeError(f"no autopilot on {url}")
        action, offboard, telemetry = ActionAsync(system), OffboardAsync(system), TelemetryAsync(system)
        await wait_until(telemetry.subscribe_health(), lambda h: h.is_armable, timeout=15.0)

        # Follow the vehicle's body rates as MAVSDK reports them (ATTITUDE, 50 Hz).
        current: list[tuple[float, float, float] | None] = [None]
        samples: list[tuple[float, tuple, tuple]] = []  # (time, setpoint deg/s, measured deg/s)

        async def record():
            async for w in telemetry.subscribe_attitude_angular_velocity_body():
                if current[0] is not None:
                    measured = (w.roll_rad_s, w.pitch_rad_s, w.yaw_rad_s)
                    samples.append((time.monotonic(), current[0], tuple(math.degrees(v) for v in measured)))

        recorder = asyncio.create_task(record())
        try:
            await offboard.set_attitude_rate(AttitudeRate(0.0, 0.0, 0.0, 0.0))  # before arming and start
            await action.arm()
            await wait_until(telemetry.subscribe_armed(), bool, timeout=10.0)
            await offboard.set_attitude_rate(AttitudeRate(0.0, 0.0, 0.0, thrust))
            await offboard.start()
            await asyncio.sleep(hold)  # spin up
            results = []
            for sp in steps(rate):
                current[0] = None
                await offboard.set_attitude_rate(AttitudeRate(*sp, thrust))
                await asyncio.sleep(hold / 2)  # let it settle, then measure the second half
                start = time.monotonic()
                current[0] = sp
                await asyncio.sleep(hold / 2)
                got = [m for t, s, m in samples if s == sp and t >= start]
                mean = tuple(sum(m[i] for m in got) / len(got) for i in range(3)) if got else None
                results.append({"setpoint_deg_s": sp, "samples": len(got),
                                "measured_deg_s": None if mean is None else [round(v, 2) for v in mean]})
            current[0] = None
            await offboard.set_attitude_rate(AttitudeRate(0.0, 0.0, 0.0, thrust))
            mode_in_offboard = (await telemetry.flight_mode()).name
            await offboard.stop()  # HOLD
            mode_after_stop = (await wait_until(telemetry.subscribe_flight_mode(),
                                                lambda m: m.name == "HOLD", timeout=5.0)).name
            await asyncio.sleep(hold)
            await action.land()
            await wait_until(telemetry.subscribe_armed(), lambda armed: not armed, timeout=40.0)
        finally:
            recorder.cancel()
    worst = max((max(abs(m - s) for m, s in zip(r["measured_deg_s"], r["setpoint_deg_s"], strict=True))
                 for r in results if r["measured_deg_s"] is not None), default=math.inf)
    return {"steps": results, "worst_error_deg_s": round(worst, 2), "mode_during": mode_in_offboard,
            "mode_after_stop": mode_after_stop,
            "completed": all(r["measured_deg_s"] is not None for r in results)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--connect", default="udpin://0.0.0.0:14540")
    ap.add_argument("--rate", type=float, default=60.0, help="step size, deg/s")
    ap.add_argument("--hold", type=float, default=1.0, help="seconds per step")
    ap.add_argument("--thrust", type=float, default=HOVER)
    ap.add_argument("--summary", default=None, help="write the result to this .json")
    args = ap.parse_args(argv)
    summary = asyncio.run(fly(args.connect, args.rate, args.hold, args.thrust))
    if args.summary:
        with open(args.summary, "w") as f:
            json.dump(summary, f, indent=1)
    print(json.dumps(summary))
    return 0 if summary["completed"] else 1


if __name__ == "__main__":
    sys.exit(main())
