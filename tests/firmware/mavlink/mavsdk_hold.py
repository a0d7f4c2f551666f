"""A MAVSDK-Python peer for test_mavsdk.py: climb in OFFBOARD, `action.hold()`, OFFBOARD again,
`offboard.stop()`, then `action.land()`; prints a JSON summary of the modes and the altitude
track (NED z from MAVSDK's position_velocity_ned) of each HOLD.

    python tests/firmware/mavlink/mavsdk_hold.py udpin://127.0.0.1:PORT THRUST_HOVER SECONDS
"""

from __future__ import annotations

import asyncio
import json
import sys
import time

from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.offboard import AttitudeRate, OffboardAsync
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync


async def wait_until(stream, predicate, timeout: float):
    async def first():
        async for value in stream:
            if predicate(value):
                return value
    return await asyncio.wait_for(first(), timeout)


async def fly(url: str, hover: float, hold_s: float) -> dict:
    config = Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)
    async with Mavsdk(config) as mavsdk:
        await mavsdk.add_any_connection(url)
        system = await mavsdk.first_autopilot(timeout_s=30.0)
        action, offboard, telemetry = ActionAsync(system), OffboardAsync(system), TelemetryAsync(system)
        await wait_until(telemetry.subscribe_health(), lambda h: h.is_armable, timeout=15.0)
        z: list[float | None] = [None]

        async def follow():
            async for pv in telemetry.subscribe_position_velocity_ned():
                z[0] = pv.position.down_m

        follower = asyncio.create_task(follow())

        async def track(seconds: float) -> list[tuple[float, float]]:
            out, start = [], time.monotonic()
            while time.monotonic() - start < seconds:
                await asyncio.sleep(0.05)
                if z[0] is not None:
                    out.append((round(time.monotonic() - start, 3), z[0]))
            return out

        async def climb(seconds: float) -> None:
            await offboard.set_attitude_rate(AttitudeRate(0.0, 0.0, 0.0, min(1.0, hover + 0.08)))
            await offboard.start()
            await asyncio.sleep(seconds)

        async def mode(name: str) -> str:
            """The flight mode once HEARTBEAT (1 Hz) shows `name`, or the last one seen in 5 s."""
            seen: list[str] = []
            try:
                await wait_until(telemetry.subscribe_flight_mode(),
                                 lambda m: seen.append(m.name) or m.name == name, timeout=5.0)
            except TimeoutError:
                pass
            return seen[-1] if seen else "none"

        summary: dict = {}
        try:
            await offboard.set_attitude_rate(AttitudeRate(0.0, 0.0, 0.0, 0.0))
            await action.arm()
            await climb(0.7)  # some 3 m up once HOLD has braked it: a short LAND
            summary["mode_offboard"] = await mode("OFFBOARD")
            await action.hold()
            summary["mode_after_action_hold"] = await mode("HOLD")
            summary["track_action_hold"] = await track(hold_s)
            await climb(0.5)  # OFFBOARD from HOLD, while setpoints stream
            summary["mode_offboard_again"] = await mode("OFFBOARD")
            await offboard.stop()  # asks for HOLD
            summary["mode_after_offboard_stop"] = await mode("HOLD")
            summary["track_offboard_stop"] = await track(hold_s)
            await action.land()
            await wait_until(telemetry.subscribe_armed(), lambda armed: not armed, timeout=60.0)
            summary["disarmed"] = True
        finally:
            follower.cancel()
    return summary


def main(argv: list[str]) -> int:
    summary = asyncio.run(fly(argv[1], float(argv[2]), float(argv[3])))
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
