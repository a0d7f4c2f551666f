"""Software in the loop: the twin, the firmware loop and its controllers wired together."""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from firmware.controllers import load_controller
from firmware.loop import Commander, FlightLoop, ScriptedCommander, TelemetrySink, TickSample
from firmware.timing import LockstepClock, RealTimeClock

FALLBACK = "pid"


@dataclass
class Sitl:
    loop: FlightLoop
    twin: object  # sim_bridge.twin.Twin when in-process, None over UDP
    link: object


def hover_throttle(rig: str = "free") -> float:
    from sim_bridge.airframe import load_airframe

    return (load_airframe().hover_pwm() - 1000.0) / 1000.0


def scripted_flight(rig: str) -> ScriptedCommander:
    """What `fcemu sitl` flies without a ground station: rate doublets on each axis in turn."""
    hover = hover_throttle()
    climb = min(1.0, hover + 0.08) if rig == "free" else hover
    schedule: list[tuple[float, Sequence[float], float]] = [(0.0, (0, 0, 0), climb)]
    t = 1.0
    for axis in range(3):
        for sign in (1.0, -1.0):
            rates = [0.0, 0.0, 0.0]
            rates[axis] = sign * 3.0
            schedule.append((t, rates, hover))
            t += 0.25 if rig == "free" else 1.0
            schedule.append((t, (0, 0, 0), hover))
            t += 0.5
    schedule.append((t, (0, 0, 0), hover - 0.05 if rig == "free" else hover))
    return ScriptedCommander(schedule, controller="main")


def build_sitl(controller: str, rig: str = "free", rate_hz: float = 1000.0, realtime: bool = True,
               commander: Commander | None = None, sinks: Sequence[TelemetrySink] = (),
               twin_address: tuple[str, int] | None = None) -> Sitl:
    from sim_bridge.link import InProcessLink, UdpTwinClient
    from sim_bridge.twin import Twin

    controllers = {"main": load_controller(controller)}
    if controller != FALLBACK:
        controllers[FALLBACK] = load_controller(FALLBACK)
    if twin_address is None:
        twin = Twin(rig=rig, dt=1.0 / rate_hz)
        link = InProcessLink(twin)
    else:
        twin, link = None, UdpTwinClient(*twin_address)
    frame = link.reset(seed=0)
    loop = FlightLoop(link, frame, controllers, commander or scripted_flight(rig),
                      RealTimeClock() if realtime else LockstepClock(), rate_hz, sinks,
                      fallback=FALLBACK)
    return Sitl(loop, twin, link)


@dataclass
class StatusLine:
    """A live one-line status on stderr, refreshed a few times a second from the loop's slack."""

    loop: FlightLoop
    every_s: float = 0.5
    _last_wall: float = field(default_factory=time.monotonic)
    _last_ticks: int = 0

    def __call__(self, _slack_us: int) -> None:
        now = time.monotonic()
        if now - self._last_wall < self.every_s:
            return
        sample: TickSample | None = self.loop.last_sample
        stats = self.loop.stats
        rate = (stats.ticks - self._last_ticks) / (now - self._last_wall)
        self._last_wall, self._last_ticks = now, stats.ticks
        if sample is None:
            return
        sp, gyro = sample.command.setpoint.rates, sample.frame.gyro
        axes = " ".join(f"{n} {g:+5.2f}/{s:+5.2f}" for n, g, s in zip("rpy", gyro, sp, strict=True))
        sys.stderr.write(
            f"\rt {sample.t_us / 1e6:7.2f}s  loop {rate:7.0f} Hz  misses {stats.deadline_misses}  "
            f"rate/setpoint rad/s: {axes}  pwm {np.array2string(sample.pwm, precision=0)}  "
        )
        sys.stderr.flush()


def sitl_command(args) -> int:
    from firmware.controllers import default_controller

    controller = args.controller or default_controller()
    sitl = build_sitl(controller, args.rig, args.rate, realtime=args.speed != "max")
    status = None if args.quiet else StatusLine(sitl.loop, every_s=0.5 if args.speed != "max" else 2.0)
    try:
        sitl.loop.run(args.duration, on_slack=status)
    except KeyboardInterrupt:
        pass
    if status is not None:
        sys.stderr.write("\n")
    summary = sitl.loop.stats.summary()
    print(f"controller {controller}  rig {args.rig}  {summary['ticks']} ticks at {args.rate:.0f} Hz"
          f"  misses {summary['deadline_misses']}  p99 period error "
          f"{summary['period_error_us']['p99']:.0f} µs  p99 compute {summary['compute_us']['p99']:.0f} µs"
          + (f"  faults {sitl.loop.faults}" if sitl.loop.faults else ""))
    return 0
