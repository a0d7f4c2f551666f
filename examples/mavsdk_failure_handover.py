#!/usr/bin/env python3
"""A motor's ESC telemetry fails in flight and the policy hands over to the PID, with MAVSDK-Python
(4.x) and its failure plugin as it ships: SYS_FAILURE_EN=1 (param plugin), arm, climb to 3 m in
OFFBOARD, hover, `failure.inject(FailureUnit.SYSTEM_MOTOR, FailureType.STUCK, 1)`, wait for the
firmware's "Policy hands over to PID" STATUSTEXT, hover on the PID, then HOLD and LAND.

    fcemu sitl                                   # the default policy, on the free rig
    python examples/mavsdk_failure_handover.py

fcemu maps SYSTEM_MOTOR as PX4 has no ESC-telemetry unit: OFF and WRONG act on what the motor
produces (WRONG: 70 % thrust), STUCK, GARBAGE, SLOW, DELAYED and INTERMITTENT on what it reports,
its ESC telemetry (the rotor speed the policy reads; docs/DESIGN.md, "Faults and the firmware's
answers"). A stuck reading is stale once the motor's PWM has moved on for 20 ticks: the policy
hands over, the PID (which does not read rotor speed) flies on, in OFFBOARD.

Exit status 0 only when all of it happened: the injection acknowledged, the hand-over said
within --timeout s, the vehicle still in OFFBOARD and airborne after it, landed and disarmed;
1 otherwise, with the reason on stderr. The vehicle must fly a policy (`fcemu sitl --controller
pid` has nothing to hand over).

Options: --connect (default udpin://0.0.0.0:14540), --motor N (1..4), --type stuck|garbage|slow|
delayed|intermittent, --timeout s, --summary FILE.json.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import time
from pathlib import Path

from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.failure import FailureAsync, FailureType, FailureUnit
from mavsdk.asyncio.plugins.offboard import AttitudeRate, OffboardAsync
from mavsdk.asyncio.plugins.param import ParamAsync
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
from mavsdk.plugins.failure import FailureError
from mavsdk.plugins.param import ParamError
from mavsdk_offboard_rates import HOVER, TAKEOFF_ALTITUDE_M, Pilot, wait_until

HANDOVER = "Policy hands over to PID"
TELEMETRY_TYPES = ("stuck", "garbage", "slow", "delayed", "intermittent")  # SYSTEM_MOTOR → ESC telemetry
HOVER_BEFORE_S = 1.0
HOVER_AFTER_S = 2.0
YAW_DEG_S = 30.0


async def manoeuvre(pilot: Pilot, seconds: float) -> None:
    """Fly on as a pilot would, yawing ±YAW_DEG_S every half second: a stuck ESC reading is told
    from a steady one only once the motor's command moves (docs/DESIGN.md, the stale rule), and a
    hover with a smooth policy hardly moves it."""
    end = time.monotonic() + seconds
    sign = 1.0
    while (left := end - time.monotonic()) > 0:
        roll, pitch, _ = pilot.level_rates()
        await pilot.fly(min(0.5, left), (roll, pitch, sign * YAW_DEG_S))
        sign = -sign


class Texts:
    """Every STATUSTEXT the vehicle sends, with when it arrived (time.monotonic())."""

    def __init__(self, telemetry: TelemetryAsync) -> None:
        self.seen: list[tuple[float, str, str]] = []
        self._task = asyncio.create_task(self._follow(telemetry))

    async def _follow(self, telemetry: TelemetryAsync) -> None:
        async for st in telemetry.subscribe_status_text():
            self.seen.append((time.monotonic(), st.type.name, st.text))

    def first(self, prefix: str, after: float = 0.0) -> tuple[float, str, str] | None:
        return next((s for s in self.seen if s[2].startswith(prefix) and s[0] >= after), None)

    def stop(self) -> None:
        self._task.cancel()


async def fly(url: str, motor: int, failure_type: FailureType, timeout: float) -> dict:
    config = Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)
    async with Mavsdk(config) as mavsdk:
        await mavsdk.add_any_connection(url)
        system = await mavsdk.first_autopilot(timeout_s=30.0)
        if system is None:
            raise RuntimeError(f"no autopilot on {url}")
        action, offboard, telemetry = ActionAsync(system), OffboardAsync(system), TelemetryAsync(system)
        texts = Texts(telemetry)
        try:
            await ParamAsync(system).set_param_int("SYS_FAILURE_EN", 1)
        except ParamError as exc:
            raise RuntimeError(f"SYS_FAILURE_EN not set: {exc}") from None
        failure = FailureAsync(system)  # it reads SYS_FAILURE_EN when created, and refuses while it is 0
        await wait_until(telemetry.subscribe_health(), lambda h: h.is_armable, timeout=15.0)
        pilot = Pilot(offboard, telemetry, HOVER)
        if not await pilot.start():
            raise RuntimeError("the vehicle reports no position: fly it on the free rig (--rig free)")
        summary: dict = {"motor": motor, "failure_type": failure_type.name}
        try:
            await offboard.set_attitude_rate(AttitudeRate(0.0, 0.0, 0.0, 0.0))  # streaming before start
            await action.arm()
            await wait_until(telemetry.subscribe_armed(), bool, timeout=10.0)
            await offboard.start()
            await pilot.take_off(TAKEOFF_ALTITUDE_M)
            await pilot.fly(HOVER_BEFORE_S)
            if texts.first(HANDOVER) is not None:
                raise RuntimeError(f"the policy handed over before any fault: {texts.first(HANDOVER)[2]}")

            # The pilot keeps streaming setpoints while the injection and its answer are awaited.
            hovering = asyncio.create_task(manoeuvre(pilot, timeout + HOVER_AFTER_S))
            injected_at = time.monotonic()
            try:
                await failure.inject(FailureUnit.SYSTEM_MOTOR, failure_type, motor)
            except FailureError as exc:
                hovering.cancel()
                raise RuntimeError(f"injection refused: {exc}") from None
            summary["inject_ack_ms"] = round(1e3 * (time.monotonic() - injected_at))
            while texts.first(HANDOVER, injected_at) is None and time.monotonic() - injected_at < timeout:
                await asyncio.sleep(0.01)
            said = texts.first(HANDOVER, injected_at)
            injected = texts.first("Failure injected", injected_at)
            summary["failure_text"] = injected[2] if injected else None
            summary["failure_text_ms"] = round(1e3 * (injected[0] - injected_at)) if injected else None
            summary["handover_text"] = said[2] if said else None
            summary["handover_ms"] = round(1e3 * (said[0] - injected_at)) if said else None
            if said is None:
                hovering.cancel()
                raise RuntimeError(f"no '{HANDOVER}' within {timeout:g} s of the injection; heard: "
                                   f"{[t for _, _, t in texts.seen]}")
            hovering.cancel()
            await pilot.fly(HOVER_AFTER_S)  # on the PID now
            summary["mode_after_handover"] = (await telemetry.flight_mode()).name
            summary["altitude_after_handover_m"] = round(pilot.altitude(), 2)
            await offboard.stop()  # HOLD
            await wait_until(telemetry.subscribe_flight_mode(), lambda m: m.name == "HOLD", timeout=5.0)
            await action.land()
            await wait_until(telemetry.subscribe_armed(), lambda armed: not armed, timeout=40.0)
            summary["landed"] = True
            await failure.inject(FailureUnit.SYSTEM_MOTOR, FailureType.OK, motor)  # the telemetry back
        finally:
            pilot.stop()
            summary["status_texts"] = [f"{kind}: {text}" for _, kind, text in texts.seen]
            texts.stop()
    return summary


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--connect", default="udpin://0.0.0.0:14540")
    ap.add_argument("--motor", type=int, default=1, choices=(1, 2, 3, 4),
                    help="which motor's telemetry fails")
    ap.add_argument("--type", default="stuck", choices=TELEMETRY_TYPES,
                    help="the ESC telemetry's failure (FailureType; default stuck)")
    ap.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for the hand-over")
    ap.add_argument("--summary", default=None, help="write the result to this .json")
    args = ap.parse_args(argv)
    name = Path(sys.argv[0]).name
    try:
        summary = asyncio.run(fly(args.connect, args.motor, FailureType[args.type.upper()], args.timeout))
    except (RuntimeError, TimeoutError) as exc:
        print(f"{name}: {exc or type(exc).__name__}", file=sys.stderr)
        return 1
    summary["survived"] = (summary.get("landed", False) and summary["mode_after_handover"] == "OFFBOARD"
                           and summary["altitude_after_handover_m"] > 0.5 * TAKEOFF_ALTITUDE_M)
    if args.summary:
        with open(args.summary, "w") as f:
            json.dump(summary, f, indent=1)
    print(json.dumps(summary))
    if not summary["survived"]:
        print(f"{name}: after the hand-over the vehicle was in {summary['mode_after_handover']} at "
              f"{summary['altitude_after_handover_m']} m (expected OFFBOARD, above "
              f"{0.5 * TAKEOFF_ALTITUDE_M:g} m)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
