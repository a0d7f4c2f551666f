"""Betaflight's NEURAL mode meets the twin's ESC-telemetry and gyro faults: does it hold lost frames
and drop the policy only when a motor's telemetry is too old, too often lost or late, or the gyro
too old?

`python -m fcemu.sitl.betaflight_health --firmware DIR` flies the rig's roll step `--episodes`
times per scenario in `SCENARIOS` (fault-free, frames lost at random and in bursts, delayed, one
motor's telemetry or the gyro stopped mid-episode), each fault injected into the twin (sim_bridge/faults.py)
and carried to the SITL as DShot would (sim_bridge/betaflight_link.py: a lost frame arrives as an
invalid one), and prints, per episode, what the mode's health rules made of it
(`BetaflightFlight.neural_health`, the largest rpm delay its lag rule judged among them) and how
well the roll step was tracked, and per scenario a summary (`summarise`).
"""

from __future__ import annotations

import argparse
import json
import statistics
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fcemu.sim_bridge.faults import Fault, FaultInjector
from fcemu.sim_bridge.twin import Twin
from fcemu.sitl.betaflight import BetaflightFlight
from fcemu.sitl.betaflight_process import BetaflightError, neural_firmware
from fcemu.sitl.betaflight_rc import RcMap

HOVER = 0.745  # the rig's throttle (tests/sitl/test_betaflight_neural.py)
ROLL_STEP = 2.0  # rad/s
TICKS = 500
SETTLED = 150  # ticks after which the step is tracked


@dataclass(frozen=True)
class Scenario:
    name: str
    fault: Fault | None
    at_tick: int = 0  # the step before which it is injected


SCENARIOS = (
    Scenario("fault-free", None),
    Scenario("esc-telemetry:intermittent:1%", Fault("esc-telemetry", "intermittent", 0, 0.01)),
    Scenario("esc-telemetry:intermittent:5%", Fault("esc-telemetry", "intermittent", 0, 0.05)),
    Scenario("esc-telemetry:burst:20ms@1%", Fault("esc-telemetry", "burst", 0, 0.01, 0.02)),
    Scenario("esc-telemetry:delayed:5ms", Fault("esc-telemetry", "delayed", 0, 0.005)),
    Scenario("esc-telemetry:1:off at 100 ms", Fault("esc-telemetry", "off", 1), at_tick=100),
    Scenario("gyro:off at 100 ms", Fault("gyro", "off"), at_tick=100),
)


def fly_scenario(flight: BetaflightFlight, scenario: Scenario, seed: int = 0,
                 ticks: int = TICKS) -> dict[str, object]:
    """One episode of the roll step with NEURAL on and `scenario`'s fault; the fault is cleared after."""
    twin = flight.twin
    rc = flight.rc
    step = rc.quantise(np.array([ROLL_STEP, 0.0, 0.0]))
    rate, pwm = np.zeros((ticks, 3)), np.zeros((ticks, 4))

    def inject(k: int) -> None:
        if scenario.fault is not None and k == scenario.at_tick:
            twin.faults = FaultInjector(twin.dt, twin.airframe.motor.max_rotor_speed, seed)
            twin.faults.inject(scenario.fault)

    try:
        flight.fly_episode(step, rc.throttle_channel(HOVER), ticks, rate, pwm, on_tick=inject)
        health = flight.neural_health()
    finally:
        twin.faults = None
    tracked = rate[SETTLED:, 0]
    # None where the twin's gyro read NaN (gyro off): the rate flown is not recorded
    error = round(float(np.abs(tracked - step[0]).mean()), 4) if np.isfinite(tracked).all() else None
    return {"scenario": scenario.name, "fault_at_tick": scenario.at_tick if scenario.fault else None,
            **health, "roll_error_rad_s": error}


def fly_scenarios(firmware_dir: str | Path, run_dir: str | Path, scenarios: tuple[Scenario, ...] = SCENARIOS,
                  speed: float = 0.25, seed: int = 0, episodes: int = 1) -> list[dict[str, object]]:
    """Each scenario `episodes` times (the faults' draws seeded `seed`, `seed` + 1, ...), on one SITL
    with the export in `firmware_dir`."""
    firmware = neural_firmware(firmware_dir)
    with BetaflightFlight(run_dir, Twin(rig="rig"), RcMap(), speed=speed, firmware=firmware,
                          neural=True) as flight:
        return [{**fly_scenario(flight, s, seed + e), "episode": e}
                for s in scenarios for e in range(episodes)]


def summarise(rows: list[dict]) -> list[dict[str, object]]:
    """Per scenario: episodes the policy flew to the end, why the others dropped it and how many
    ticks after the fault, the oldest telemetry, largest loss rate and largest judged rpm delay it
    flew on, the median roll error and its ratio to the fault-free scenario's."""
    by_name: dict[str, list[dict]] = {}
    for row in rows:
        by_name.setdefault(str(row["scenario"]), []).append(row)
    clean = by_name.get("fault-free")
    clean_error = _median_error(clean) if clean else None
    summary = []
    for name, group in by_name.items():
        dropped = [r for r in group if r["dropped"]]
        error = _median_error(group)
        after = sorted(r["dropped_after_ticks"] - r["fault_at_tick"] for r in dropped)
        summary.append({"scenario": name, "episodes": len(group),
                        "flew_to_the_end": len(group) - len(dropped),
                        "dropped": dict(Counter(r["dropped"] for r in dropped)),
                        "dropped_ticks_after_fault": after,
                        "max_rpm_age_ticks": max(r["max_rpm_age_ticks"] for r in group),
                        "max_loss_rate": max(r["max_loss_rate"] for r in group),
                        "max_lag_us": max((r.get("max_lag_us", 0) for r in group), default=0),
                        "roll_error_rad_s_median": error,
                        "error_ratio": round(error / clean_error, 2) if clean_error and error else None})
    return summary


def _median_error(rows: list[dict]) -> float | None:
    errors = [r["roll_error_rad_s"] for r in rows if r["roll_error_rad_s"] is not None]
    return statistics.median(errors) if errors else None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fcemu.sitl.betaflight_health",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--firmware", required=True, metavar="DIR",
                        help="an `fcemu export POLICY --target betaflight` output with a SITL build")
    parser.add_argument("--run-dir", default="betaflight_health_run", metavar="DIR")
    parser.add_argument("--speed", type=float, default=0.25, help="× real time (default 0.25)")
    parser.add_argument("--seed", type=int, default=0, help="the faults' random draws")
    parser.add_argument("--episodes", type=int, default=1, help="per scenario (default 1)")
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.exit(2, "fcemu: error: --episodes must be >= 1\n")
    try:
        rows = fly_scenarios(args.firmware, args.run_dir, speed=args.speed, seed=args.seed,
                             episodes=args.episodes)
    except BetaflightError as exc:
        parser.exit(2, f"fcemu: error: {exc}\n")
    print(json.dumps({"summary": summarise(rows), "episodes": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
