"""The identification flight: what a system-identification log needs, flown on the twin.

As PX4's system-identification flights and Betaflight's CHIRP mode do, the rate setpoint
carries the excitation while the PID flies: per axis a doublet, then a chirp sweeping
`CHIRP_HZ`, and first a few collective steps, which spin the four motors up and down together
(the motors' time constants and their speed against the command over a wide range). Last, roll
and pitch doublets while the vehicle yaws each way: the products of two rates they make are what
the body's gyroscopic coupling, and so the yaw inertia against roll's and pitch's, is read from. The twin is
on the ball-joint rig at its hover throttle, so the rotors run where they would in a hover.
The loop ticks in lockstep with the twin, faster than real time; the log is the one
`fcemu sitl --ulog` writes (`sitl.ulog_writer`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fcemu.firmware.controller import RateSetpoint
from fcemu.firmware.controllers import load_controller
from fcemu.firmware.health import HealthMonitor, HealthRules
from fcemu.firmware.loop import Command, FlightLoop
from fcemu.firmware.sensors import SensorFrame
from fcemu.firmware.timing import LockstepClock
from fcemu.sim_bridge.airframe import Airframe
from fcemu.sim_bridge.airframe_spec import airframe_spec
from fcemu.sim_bridge.link import InProcessLink
from fcemu.sim_bridge.twin import Twin, hover_state
from fcemu.sitl.ulog_writer import ULogRecorder

CHIRP_HZ = (0.5, 12.0)  # the sweep of each axis's chirp
DOUBLET_RATE = (2.5, 2.5, 1.5)  # rad/s, roll, pitch, yaw
# The chirp's is smaller: the rate loop peaks near 2 Hz, and a saturated motor says nothing.
CHIRP_RATE = (0.8, 0.8, 1.0)
COLLECTIVE_STEP = 0.12  # throttle above and below hover in the collective steps
YAWING_DOUBLET_S = 0.3  # each half of a roll or pitch doublet flown while yawing at the yaw doublet's rate


def excitation(rate_hz: float, hover: float, axis_s: float = 6.0) -> tuple[np.ndarray, np.ndarray]:
    """(rates (T, 3) rad/s, throttle (T,)) per tick: collective steps, then each axis's doublet and
    chirp (a third of `axis_s` for the doublet, the rest for the chirp), with a pause between."""
    dt = 1.0 / rate_hz
    pieces_rates, pieces_throttle = [], []

    def add(rates: np.ndarray, throttle: np.ndarray | float) -> None:
        pieces_rates.append(rates)
        pieces_throttle.append(np.broadcast_to(throttle, len(rates)).astype(float))

    def hold(seconds: float, throttle: float = hover) -> None:
        add(np.zeros((round(seconds * rate_hz), 3)), throttle)

    hold(0.3)
    for sign in (1, -1, 1, -1):
        hold(0.25, hover + sign * COLLECTIVE_STEP)
        hold(0.25)
    for axis in range(3):
        amplitude = DOUBLET_RATE[axis]
        doublet_s = axis_s / 3
        for value in (amplitude, -amplitude, 0.0):
            rates = np.zeros((round(doublet_s / 3 * rate_hz), 3))
            rates[:, axis] = value
            add(rates, hover)
        chirp_s = axis_s - doublet_s
        t = np.arange(round(chirp_s * rate_hz)) * dt
        f0, f1 = CHIRP_HZ
        phase = 2 * np.pi * (f0 * t + (f1 - f0) * t**2 / (2 * chirp_s))  # linear sweep, as Betaflight's
        rates = np.zeros((len(t), 3))
        rates[:, axis] = CHIRP_RATE[axis] * np.sin(phase)
        add(rates, hover)
        hold(0.3)
    for yaw in (DOUBLET_RATE[2], -DOUBLET_RATE[2]):
        steps = [(0.0, 0.0, yaw, 0.4)]
        steps += [(v, 0.0, yaw, YAWING_DOUBLET_S) for v in (DOUBLET_RATE[0], -DOUBLET_RATE[0])]
        steps += [(0.0, v, yaw, YAWING_DOUBLET_S) for v in (DOUBLET_RATE[1], -DOUBLET_RATE[1])]
        for roll, pitch, yaw_rate, seconds in steps:
            add(np.tile([roll, pitch, yaw_rate], (round(seconds * rate_hz), 1)), hover)
        hold(0.3)
    return np.concatenate(pieces_rates), np.concatenate(pieces_throttle)


class _Excitation:
    """Commander: tick k flies row k of the excitation, armed throughout."""

    def __init__(self, rates: np.ndarray, throttle: np.ndarray, period_us: int) -> None:
        self.commands = [Command(True, RateSetpoint(r, float(th)), "main") for r, th in zip(rates, throttle,
                                                                                            strict=True)]
        self.period_us = period_us

    def command(self, t_us: int, frame: SensorFrame) -> Command:
        return self.commands[min(t_us // self.period_us, len(self.commands) - 1)]


def identification_controller(airframe: Airframe, controller: str, out_dir: Path) -> tuple[str, str | None]:
    """(the controller spec that flies `airframe`'s identification flight, a sentence for the report
    where it is not the one asked for). `pid` is the airframe's shipped tune; where none is shipped it
    is the Iris tune carried over by the loop's physics, as `fcemu tune` starts from
    (`evaluation.pid_carry_over`), written to DIR/pid_carried_over.json and flown as pid:that file."""
    from fcemu.firmware.controllers import ControllerSpecError, airframe_preset

    if controller != "pid":
        return controller, None
    try:
        airframe_preset(airframe_spec(airframe))
        return controller, None
    except ControllerSpecError:
        pass
    import json

    from fcemu.evaluation.pid_carry_over import REFERENCE, iris_tune_carried_over

    start = iris_tune_carried_over(airframe)
    path = Path(out_dir) / "pid_carried_over.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(start, indent=1) + "\n")
    note = (f"flown by the {REFERENCE[0].capitalize()} tune carried over to {airframe.name} by the loop's "
            f"physics (fcemu tune's start, {path.name}): no tune is shipped for it")
    return f"pid:{path}", note


def fly_identification(airframe: Airframe, controller: str = "pid", rate_hz: float = 1000.0,
                       axis_s: float = 6.0, seed: int = 0) -> ULogRecorder:
    """Fly the identification flight on `airframe`'s twin with `controller`; the recorded log.
    `seed` seeds the twin's sensor noise."""
    spec = airframe_spec(airframe)
    twin = Twin(airframe, rig="rig", dt=1.0 / rate_hz)
    hover = spec.hover_throttle
    rates, throttle = excitation(rate_hz, hover, axis_s)
    period_us = round(1e6 / rate_hz)
    recorder = ULogRecorder()
    first = twin.reset(seed, hover_state(airframe, hover))
    loop = FlightLoop(InProcessLink(twin), first, {"main": load_controller(controller, rate_hz, spec)},
                      _Excitation(rates, throttle, period_us), LockstepClock(), rate_hz, [recorder],
                      health=HealthMonitor(HealthRules.for_airframe(spec), dt=1.0 / rate_hz))
    for k in range(len(rates)):
        loop.tick(k * period_us)
    return recorder
