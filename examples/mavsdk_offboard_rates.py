#!/usr/bin/env python3
"""Offboard attitude rates with MAVSDK-Python (4.x, the native binding): connect, arm, start
offboard with a setpoint already streaming (PX4's rule), step through body-rate setpoints, and
measure how the vehicle's rates follow them through MAVSDK's own telemetry; then end offboard
the canonical way, `offboard.stop()` (the vehicle goes to HOLD), and LAND.

    fcemu sitl --controller pid                 # the free rig: it climbs to 3 m first
    fcemu sitl --controller pid --rig rig       # ball-joint rig: rotates freely, cannot fly away
    python examples/mavsdk_offboard_rates.py

On the free rig (the default of `fcemu sitl`; the vehicle reports a local position) it climbs to
3 m before the first step, holds that altitude with the thrust through every step, levels and
brakes between axes, then ends with HOLD and LAND. On the rig it steps at hover thrust. MAVSDK 4
runs the MAVSDK core inside the Python process (no mavsdk_server); the vehicle sends to UDP 14540
for an offboard API, where this script listens.

Exit status 0 only when the vehicle followed: every step measured, the vehicle still in OFFBOARD
at the end, and each step's mean body rate within --max-error deg/s (default 10) of its setpoint
on every axis; 1 otherwise, with the reason on stderr.

Options: --connect (default udpin://0.0.0.0:14540), --rate deg/s, --hold s per step,
--thrust (hover, default 0.745), --max-error deg/s, --summary FILE.json.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
import time
from pathlib import Path

from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.offboard import AttitudeRate, OffboardAsync
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

HOVER = 0.745  # Iris hover throttle
MAX_ERROR_DEG_S = 10.0  # a step's mean body rate further from its setpoint, on any axis: not followed
TAKEOFF_ALTITUDE_M = 3.0
TAKEOFF_S = 5.0  # climb for 2 s, then settle at the take-off altitude
LEVEL_S = 1.5  # between axes on the free rig: level, brake, back to the altitude
CONTROL_PERIOD_S = 0.02
G = 9.81


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


async def within(awaitable, what: str, timeout: float = 10.0):
    """`awaitable`, or a RuntimeError naming `what` after `timeout` s: a call the vehicle never answers
    ends the script with the step it hung on instead of hanging it."""
    try:
        return await asyncio.wait_for(awaitable, timeout)
    except TimeoutError:
        raise RuntimeError(f"no answer to {what} in {timeout:g} s") from None


def clamp(value: float, limit: float) -> float:
    return max(-limit, min(limit, value))


class Pilot:
    """Sends the offboard setpoints. On the ball-joint rig the thrust stays fixed; on the free rig
    (the vehicle reports a local position) this is the outer loop a companion computer adds: thrust
    holds the altitude through every step, and between axes the rates level the vehicle and brake it."""

    def __init__(self, offboard: OffboardAsync, telemetry: TelemetryAsync, thrust: float) -> None:
        self.offboard, self.telemetry, self.hover = offboard, telemetry, thrust
        self.attitude = None  # EulerAngle, degrees
        self.state = None  # PositionVelocityNed
        self.altitude_sp = self.climb_sp = 0.0
        self.z_integral = 0.0
        self.yaw0: float | None = None
        self._tasks: list[asyncio.Task] = []

    async def start(self, position_timeout: float = 3.0) -> bool:
        """Follow attitude and position; True when the vehicle reports a position (the free rig)."""
        async def attitude():
            async for a in self.telemetry.subscribe_attitude_euler():
                self.attitude = a

        async def position():
            async for pv in self.telemetry.subscribe_position_velocity_ned():
                self.state = pv

        self._tasks = [asyncio.create_task(attitude()), asyncio.create_task(position())]
        deadline = time.monotonic() + position_timeout
        while self.state is None and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        return self.state is not None

    def stop(self) -> None:
        for task in self._tasks:
            task.cancel()

    @property
    def airborne(self) -> bool:
        return self.state is not None

    def altitude(self) -> float:
        return -self.state.position.down_m if self.state is not None else 0.0

    def thrust(self, dt: float) -> float:
        """Altitude hold: PD on height and climb rate plus an integrator, through the tilt."""
        if self.state is None or self.attitude is None:
            return self.hover
        error = self.altitude_sp - self.altitude()
        self.z_integral = clamp(self.z_integral + 0.3 * error * dt, 1.5)
        climb = -self.state.velocity.down_m_s
        accel_up = 1.5 * error + 2.0 * (self.climb_sp - climb) + self.z_integral  # m/s² on top of gravity
        roll, pitch = math.radians(self.attitude.roll_deg), math.radians(self.attitude.pitch_deg)
        tilt = max(0.5, math.cos(roll) * math.cos(pitch))
        # Thrust grows with rotor speed squared, and throttle sets rotor speed: hence the root.
        return max(0.05, min(1.0, self.hover * math.sqrt(max(0.0, 1.0 + accel_up / G) / tilt)))

    def level_rates(self) -> tuple[float, float, float]:
        """deg/s back to level, leaning against the horizontal velocity, heading held."""
        a, v = self.attitude, self.state.velocity
        if a is None:
            return (0.0, 0.0, 0.0)
        if self.yaw0 is None:
            self.yaw0 = a.yaw_deg
        yaw = math.radians(a.yaw_deg)
        forward = v.north_m_s * math.cos(yaw) + v.east_m_s * math.sin(yaw)
        right = -v.north_m_s * math.sin(yaw) + v.east_m_s * math.cos(yaw)
        roll_sp, pitch_sp = clamp(-4.0 * right, 15.0), clamp(4.0 * forward, 15.0)
        yaw_error = (a.yaw_deg - self.yaw0 + 180.0) % 360.0 - 180.0
        return (clamp(4.0 * (roll_sp - a.roll_deg), 120.0), clamp(4.0 * (pitch_sp - a.pitch_deg), 120.0),
                clamp(-2.0 * yaw_error, 60.0))

    async def fly(self, seconds: float, rates: tuple[float, float, float] | None = None) -> None:
        """`rates` (deg/s) for `seconds`; None: level (free rig) or zero rates (rig)."""
        if not self.airborne:
            setpoint = AttitudeRate(*(rates or (0.0, 0.0, 0.0)), self.hover)
            await within(self.offboard.set_attitude_rate(setpoint), "a setpoint")
            await asyncio.sleep(seconds)
            return
        end = time.monotonic() + seconds
        while (now := time.monotonic()) < end:
            sp = rates if rates is not None else self.level_rates()
            setpoint = AttitudeRate(*sp, self.thrust(CONTROL_PERIOD_S))
            await within(self.offboard.set_attitude_rate(setpoint), "a setpoint")
            await asyncio.sleep(min(CONTROL_PERIOD_S, end - now))

    async def take_off(self, altitude: float) -> None:
        """Climb to `altitude` level; RuntimeError if the vehicle does not get there."""
        start = time.monotonic()
        while (elapsed := time.monotonic() - start) < TAKEOFF_S:
            self.altitude_sp = altitude * min(1.0, elapsed / 2.0)
            self.climb_sp = altitude / 2.0 if elapsed < 2.0 else 0.0
            await self.fly(CONTROL_PERIOD_S)
        if self.altitude() < 0.7 * altitude:
            raise RuntimeError(f"did not climb: {self.altitude():.2f} m after {TAKEOFF_S:g} s, "
                               f"{altitude:g} m asked")


async def fly(url: str, rate: float, hold: float, thrust: float) -> dict:
    config = Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)
    async with Mavsdk(config) as mavsdk:
        await within(mavsdk.add_any_connection(url), f"the connection {url}")
        system = await mavsdk.first_autopilot(timeout_s=30.0)
        if system is None:
            raise RuntimeError(f"no autopilot on {url}")
        action, offboard, telemetry = ActionAsync(system), OffboardAsync(system), TelemetryAsync(system)
        await wait_until(telemetry.subscribe_health(), lambda h: h.is_armable, timeout=15.0)
        pilot = Pilot(offboard, telemetry, thrust)
        airborne = await pilot.start()

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
            idle = 0.0 if airborne else thrust
            # a setpoint streams before arming and before offboard starts
            await within(offboard.set_attitude_rate(AttitudeRate(0.0, 0.0, 0.0, idle)), "a setpoint")
            await within(action.arm(), "arm")
            await wait_until(telemetry.subscribe_armed(), bool, timeout=10.0)
            await within(offboard.set_attitude_rate(AttitudeRate(0.0, 0.0, 0.0, idle)), "a setpoint")
            await within(offboard.start(), "offboard start")
            if airborne:
                await pilot.take_off(TAKEOFF_ALTITUDE_M)
            else:
                await pilot.fly(hold)  # spin up
            results = []
            for i, sp in enumerate(steps(rate)):
                current[0] = None
                await pilot.fly(hold / 2, sp)  # let it settle, then measure the second half
                start = time.monotonic()
                current[0] = sp
                await pilot.fly(hold / 2, sp)
                current[0] = None
                got = [m for t, s, m in samples if s == sp and t >= start]
                mean = tuple(sum(m[i] for m in got) / len(got) for i in range(3)) if got else None
                results.append({"setpoint_deg_s": sp, "samples": len(got),
                                "measured_deg_s": None if mean is None else [round(v, 2) for v in mean]})
                if airborne and i % 2:  # each axis out and back, then level before the next
                    await pilot.fly(LEVEL_S)
            await pilot.fly(0.1)
            mode_in_offboard = (await within(telemetry.flight_mode(), "the flight mode")).name
            altitude_before_stop = round(pilot.altitude(), 2)
            await within(offboard.stop(), "offboard stop")  # HOLD
            mode_after_stop = (await wait_until(telemetry.subscribe_flight_mode(),
                                                lambda m: m.name == "HOLD", timeout=5.0)).name
            await asyncio.sleep(hold)
            await within(action.land(), "land")
            await wait_until(telemetry.subscribe_armed(), lambda armed: not armed, timeout=40.0)
        finally:
            recorder.cancel()
            pilot.stop()
    worst = max((max(abs(m - s) for m, s in zip(r["measured_deg_s"], r["setpoint_deg_s"], strict=True))
                 for r in results if r["measured_deg_s"] is not None), default=math.inf)
    return {"steps": results, "worst_error_deg_s": round(worst, 2), "rig": "free" if airborne else "rig",
            "altitude_before_stop_m": altitude_before_stop if airborne else None,
            "mode_during": mode_in_offboard, "mode_after_stop": mode_after_stop,
            "completed": all(r["measured_deg_s"] is not None for r in results)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--connect", default="udpin://0.0.0.0:14540")
    ap.add_argument("--rate", type=float, default=60.0, help="step size, deg/s")
    ap.add_argument("--hold", type=float, default=1.0, help="seconds per step")
    ap.add_argument("--thrust", type=float, default=HOVER, help="hover thrust 0..1")
    ap.add_argument("--max-error", type=float, default=MAX_ERROR_DEG_S,
                    help="deg/s: a step whose mean body rate is further than this from its setpoint, on any "
                         f"axis, was not followed, and the script exits 1 (default {MAX_ERROR_DEG_S:g})")
    ap.add_argument("--summary", default=None, help="write the result to this .json")
    args = ap.parse_args(argv)
    try:
        summary = asyncio.run(fly(args.connect, args.rate, args.hold, args.thrust))
    except (RuntimeError, TimeoutError) as exc:
        print(f"{Path(sys.argv[0]).name}: {exc or type(exc).__name__}", file=sys.stderr)
        return 1
    summary["max_error_deg_s"] = args.max_error
    summary["followed"] = (summary["completed"] and summary["mode_during"] == "OFFBOARD"
                           and summary["worst_error_deg_s"] <= args.max_error)
    if args.summary:
        with open(args.summary, "w") as f:
            json.dump(summary, f, indent=1)
    print(json.dumps(summary))
    if not summary["followed"]:
        mode = summary["mode_during"]
        left = "" if mode == "OFFBOARD" else f", and it left OFFBOARD ({mode})"
        print(f"{Path(sys.argv[0]).name}: the vehicle did not follow: worst error "
              f"{summary['worst_error_deg_s']} deg/s (--max-error {args.max_error:g}){left}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
