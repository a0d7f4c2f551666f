"""Software in the loop: the twin, the firmware loop and its controllers wired together.

With MAVLink (the default of `fcemu sitl`) the loop flies whatever the `Vehicle` commands,
and the MAVLink process (firmware/mavlink) carries ground stations' requests to it; with
`--no-mavlink` it flies the scripted doublets of `scripted_flight`.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fcemu.firmware.airframe_spec import AirframeSpec
from fcemu.firmware.controllers import FALLBACK_CONTROLLER as FALLBACK
from fcemu.firmware.controllers import load_controller
from fcemu.firmware.health import HealthMonitor, HealthRules
from fcemu.firmware.loop import Commander, FlightLoop, ScriptedCommander, TelemetrySink, TickSample
from fcemu.firmware.timing import LockstepClock, RealTimeClock, give_loop_a_core, prioritize_loop
from fcemu.sim_bridge.airframe import DEFAULT_AIRFRAME

# A loop that shares its CPU sleeps between ticks and spins only this last stretch (time.sleep
# overshoots): spinning through the period would starve the MAVLink processes beside it.
SHARED_SPIN_US = 300


@dataclass
class Sitl:
    loop: FlightLoop
    twin: object  # sim_bridge.twin.Twin when in-process, None over UDP
    link: object
    selected: str = "pid"  # the controller key the --controller option chose
    airframe: AirframeSpec | None = None  # what the firmware was configured for


class ScaledClock:
    """Simulated time paced at `factor`× wall time, as a ceiling: when the host cannot keep up,
    the simulation slows down instead of skipping ticks.

    A real-time loop that overruns must skip (the world does not wait); a simulated one need
    not, and skipping would only make the vehicle fly worse because the host is busy. So this
    clock is not `realtime` to the loop: every tick runs, on the exact loop-time grid. Lags
    shorter than `max_lag_us` of loop time are caught up; longer ones move the wall-time origin
    (counted in `rebases`, with the lost time in `lost_us`).
    """

    realtime = False

    def __init__(self, factor: float, max_lag_us: int = 20_000) -> None:
        if not factor > 0:
            raise ValueError(f"speed factor must be positive, got {factor}")
        self.factor = factor
        self.max_lag_us = max_lag_us
        self.rebases = 0
        self.lost_us = 0
        self._t0 = time.perf_counter_ns()
        self._now = 0

    def _scaled_us(self) -> int:
        return int((time.perf_counter_ns() - self._t0) * self.factor) // 1000

    def now_us(self) -> int:
        return self._now

    def wait_until(self, deadline_us: int) -> int:
        remaining_wall_us = (deadline_us - self._scaled_us()) / self.factor
        if remaining_wall_us > 0:
            time.sleep(remaining_wall_us * 1e-6)
        elif -remaining_wall_us * self.factor > self.max_lag_us:
            lag_us = self._scaled_us() - deadline_us
            self._t0 += int(lag_us * 1000 / self.factor)
            self.rebases += 1
            self.lost_us += lag_us
        self._now = max(self._now, deadline_us)
        return self._now


def parse_speed(text: str) -> float | None:
    """'realtime' → 1, 'max' → None (lockstep), 'N' → N times real time."""
    if text == "realtime":
        return 1.0
    if text == "max":
        return None
    value = float(text.rstrip("xX"))
    if not 0 < value <= 1000:
        raise ValueError(f"--speed must be realtime, max or a factor in (0, 1000], got {text}")
    return value


def scripted_flight(rig: str, controller: str = "pid", hover: float | None = None,
                    airframe: str = DEFAULT_AIRFRAME) -> ScriptedCommander:
    """What `fcemu sitl --no-mavlink` flies: rate doublets on each axis in turn, about `hover`
    (the throttle that holds the weight; None: `airframe`'s)."""
    if hover is None:
        from fcemu.sim_bridge.airframe import load_airframe

        hover = load_airframe(airframe).hover_throttle()
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
    return ScriptedCommander(schedule, controller=controller)


def flying_line(controller: str, airframe: AirframeSpec | None = None) -> str:
    """One line for the console saying which controller flies and from where (`default`, as
    resolved for `airframe`)."""
    from fcemu.firmware.controllers import (
        DEFAULT,
        DEFAULT_POLICY,
        DEFAULT_POLICY_LONGEST_LOOP_TICKS,
        default_refusal,
        is_policy,
        resolve,
    )

    flown = resolve(controller, airframe)
    if controller == DEFAULT and airframe is not None and not is_policy(flown) and DEFAULT_POLICY.exists():
        refusal = default_refusal(airframe)
        why = f"the shipped policy refuses it: {refusal}" if refusal else (
            f"on a loop of {airframe.loop_delay_ticks} ticks; the shipped policy holds loops of up to "
            f"{DEFAULT_POLICY_LONGEST_LOOP_TICKS}")
        return f"fcemu: flying {flown} (the default for {airframe.name}, {why})"
    controller = flown
    if is_policy(controller):
        kind = "neural" if controller.endswith(".onnx") else "c_policy"
        return f"fcemu: flying {kind}:{Path(controller).stem} ({controller})"
    if controller == "pid" and not DEFAULT_POLICY.exists():
        return f"fcemu: flying pid (no policy found at {DEFAULT_POLICY})"
    return f"fcemu: flying {controller}"


def load_controllers(controller: str, rate_hz: float, airframe: AirframeSpec,
                     fallback: str | None = None) -> tuple[dict, str]:
    """The loop's controllers by CTRL_SEL name ('pid', 'neural') and which one `controller` picks,
    each for `airframe` (a policy outside its envelope, or `pid` where none is tuned, is refused).
    `fallback`: the PID a policy hands over to, and CTRL_SEL's pid (None: the one the policy names,
    as `fcemu fit`'s does its DIR/pid.json, else the airframe's own tune)."""
    from fcemu.firmware.controllers import is_policy, resolve, resolve_fallback

    controller = resolve(controller, airframe)
    if is_policy(controller):
        pid = resolve_fallback(fallback, [controller], lambda: airframe)
        return {"neural": load_controller(controller, rate_hz, airframe),
                FALLBACK: load_controller(pid, airframe=airframe)}, "neural"
    return {FALLBACK: load_controller(controller, rate_hz, airframe)}, FALLBACK


def firmware_airframe(airframe: str | object) -> tuple[object, AirframeSpec]:
    """The twin's airframe (a name, a file or an Airframe) and what the firmware is configured with for it."""
    from fcemu.sim_bridge.airframe import Airframe, load_airframe
    from fcemu.sim_bridge.airframe_spec import airframe_spec

    af = airframe if isinstance(airframe, Airframe) else load_airframe(airframe)  # type: ignore[arg-type]
    return af, airframe_spec(af)


def build_sitl(controller: str, rig: str = "free", rate_hz: float = 1000.0, realtime: bool = True,
               commander: Commander | None = None, sinks: Sequence[TelemetrySink] = (),
               twin_address: tuple[str, int] | None = None, speed: float = 1.0,
               spin_us: int | None = None, airframe: str | object = DEFAULT_AIRFRAME,
               fallback: str | None = None) -> Sitl:
    """`airframe` (a name, a file or an Airframe): the twin's, and what the firmware's controllers,
    health rules and scripted hover are for (over UDP, the remote twin must fly the same one).
    `fallback`: the PID under a policy (`load_controllers`)."""
    from fcemu.sim_bridge.link import InProcessLink, UdpTwinClient
    from fcemu.sim_bridge.twin import Twin

    af, spec = firmware_airframe(airframe)
    controllers, selected = load_controllers(controller, rate_hz, spec, fallback)
    if twin_address is None:
        twin = Twin(af, rig=rig, dt=1.0 / rate_hz)  # type: ignore[arg-type]
        link = InProcessLink(twin)
    else:
        twin, link = None, UdpTwinClient(*twin_address)
    frame = link.reset(seed=0)
    real = RealTimeClock() if spin_us is None else RealTimeClock(spin_us)
    clock = (real if speed == 1.0 else ScaledClock(speed)) if realtime else LockstepClock()
    commander = commander or scripted_flight(rig, selected, spec.hover_throttle)
    loop = FlightLoop(link, frame, controllers, commander, clock, rate_hz, sinks, fallback=FALLBACK,
                      health=HealthMonitor(HealthRules.for_airframe(spec), dt=1.0 / rate_hz))
    return Sitl(loop, twin, link, selected, spec)


@dataclass
class StatusLine:
    """A live one-line status on stderr, refreshed a few times a second from the loop's slack."""

    loop: FlightLoop
    every_s: float = 0.5
    extra: Callable[[], str] | None = None
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
            f"\rt {sample.frame.t_us / 1e6:7.2f}s  loop {rate:7.0f} Hz  misses {stats.deadline_misses}  "
            f"rate/setpoint rad/s: {axes}  pwm {np.array2string(sample.pwm, precision=0)}"
            f"{'  ' + self.extra() if self.extra else ''}  "
        )
        sys.stderr.flush()


GCS_PORT = 14550  # where every instance sends to a ground station, as PX4 SITL does
OFFBOARD_PORT = 14540  # + the instance: each vehicle's own offboard API peer


def default_params_file(instance: int = 0) -> Path:
    base = Path(os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share")
    return base / "fcemu" / ("params.json" if instance == 0 else f"params-{instance}.json")


@dataclass
class VehicleSitl:
    """SITL flown over MAVLink: the loop, the Vehicle and the MAVLink process beside it."""

    sitl: Sitl
    vehicle: object
    linked: object
    proc: object
    param_problems: list[str]
    ports: dict[str, int]  # the vehicle's local UDP port per peer
    params_file: str | None = None

    def stop(self) -> dict:
        from fcemu.firmware.mavlink.bridge import stop_mavlink

        stop_mavlink(self.proc, self.linked.sock, self.linked)
        return self.linked.mavlink_stats


def start_vehicle_sitl(controller: str, rig: str, rate_hz: float, speed: float | None, config,
                       explicit_controller: bool = True, spin_us: int | None = None,
                       airframe: str | object = DEFAULT_AIRFRAME,
                       fallback: str | None = None) -> VehicleSitl:
    """Build the loop with a `Vehicle` commander and start its MAVLink process (`config`)."""
    from fcemu.firmware.mavlink.bridge import LinkedVehicle, start_mavlink
    from fcemu.firmware.params import ParamTable
    from fcemu.firmware.vehicle import Vehicle, param_adapter

    sitl = build_sitl(controller, rig, rate_hz, realtime=speed is not None, speed=speed or 1.0,
                      spin_us=spin_us, airframe=airframe, fallback=fallback)
    assert sitl.airframe is not None
    params = ParamTable()
    for pid in param_adapter.tunable_pids(sitl.loop.controllers):
        param_adapter.set_gain_defaults(params, pid.gains)  # the loaded preset's gains: a GCS's defaults
    params.set_default("MPC_THR_HOVER", sitl.airframe.hover_throttle)
    problems = params.load(config.params_file) if config.params_file else []
    if explicit_controller or params["CTRL_SEL"] >= len(sitl.loop.controllers):
        params.set("CTRL_SEL", ("pid", "neural").index(sitl.selected))
    vehicle = Vehicle(params, sitl.loop.controllers, fallback=FALLBACK)
    if sitl.twin is not None:  # MAV_CMD_INJECT_FAILURE acts in the twin (sim_bridge/faults.py)
        from fcemu.sim_bridge.faults import mavlink_injector

        vehicle.failure_injector = mavlink_injector(sitl.twin)
    config.controllers = list(sitl.loop.controllers)
    config.has_position = rig == "free" and sitl.twin is not None
    proc, sock, slot, ports = start_mavlink(config, dict(params.values))
    truth = sitl.twin.truth if config.has_position else None
    linked = LinkedVehicle(vehicle, sock, slot, truth=truth, every=max(1, round(rate_hz / 250)),
                           loop=sitl.loop)
    sitl.loop.commander = linked
    sitl.loop.sinks.append(linked)
    return VehicleSitl(sitl, vehicle, linked, proc, problems, ports, config.params_file)


def mavlink_config_from_args(args):
    """The MAVLink process's config; its peers, key and files checked (sitl_args) before anything starts."""
    from fcemu.firmware.mavlink.bridge import MavlinkConfig
    from fcemu.sitl.sitl_args import check_mavlink_files, check_signed_peers, checked_peer

    instance = getattr(args, "instance", 0)
    options = [("--gcs", args.gcs or f"127.0.0.1:{GCS_PORT}"),
               ("--offboard", args.offboard or f"127.0.0.1:{OFFBOARD_PORT + instance}")]
    options += [("--peer", spec) for spec in args.peer or []]
    names = ["gcs", "offboard"] + [f"peer{i}" for i in range(len(options) - 2)]
    peers = [checked_peer(spec, name) for (_, spec), name in zip(options, names, strict=True)]
    check_signed_peers(options, peers, args.signing_key)
    params_file = args.params if args.params is not None else str(default_params_file(instance))
    check_mavlink_files(args, params_file or None)
    return MavlinkConfig(peers=peers, sysid=args.sysid or 1 + instance, tlog=args.tlog,
                         signing_key=args.signing_key, params_file=params_file or None)


def owns_a_core(instance: int) -> bool:
    """Instance 0 spins on a CPU of its own, with the others left to its helpers, as long as the
    machine has two; further instances get one only where CPUs remain for all of them."""
    return instance == 0 or len(os.sched_getaffinity(0)) >= 2 * (instance + 1)


def claim_cpu(helper_pids: Sequence[int], own_core: bool) -> Callable[[], None]:
    if own_core:
        return give_loop_a_core(helper_pids)
    return prioritize_loop()


def stop_on_sigint() -> None:
    """Ctrl-C or SIGINT ends the flight with its summary and the MAVLink shutdown, also when
    started as a background job of a non-interactive shell: such a job inherits SIGINT
    ignored, and Python then installs no KeyboardInterrupt handler of its own."""
    signal.signal(signal.SIGINT, signal.default_int_handler)


def sitl_command(args) -> int:
    from fcemu.firmware.controllers import DEFAULT, resolve

    stop_on_sigint()

    controller = args.controller or DEFAULT
    speed = parse_speed(args.speed)
    own_core = owns_a_core(args.instance)
    spin_us = None if own_core else SHARED_SPIN_US
    vs = None
    ulog = None
    if getattr(args, "ulog", None):
        from fcemu.sitl.sitl_args import check_ulog
        from fcemu.sitl.ulog_writer import ULogRecorder

        check_ulog(args.ulog)
        ulog = ULogRecorder()
    if args.no_mavlink:
        from fcemu.sitl.sitl_args import refuse_mavlink_options

        refuse_mavlink_options(args)
        sitl = build_sitl(controller, args.rig, args.rate, realtime=speed is not None, speed=speed or 1.0,
                          spin_us=spin_us, airframe=args.airframe, fallback=args.fallback)
    else:
        vs = start_vehicle_sitl(controller, args.rig, args.rate, speed, mavlink_config_from_args(args),
                                explicit_controller=args.controller is not None, spin_us=spin_us,
                                airframe=args.airframe, fallback=args.fallback)
        sitl = vs.sitl
        if vs.param_problems:
            from fcemu.firmware.params import load_warning

            print(load_warning(vs.params_file, vs.param_problems), file=sys.stderr)
    if ulog is not None:
        sitl.loop.sinks.append(ulog)
    print(flying_line(controller, sitl.airframe), file=sys.stderr)
    extra = None
    if vs is not None:
        veh = vs.vehicle
        extra = lambda: f"{'ARMED' if veh.armed else 'disarmed'} {veh.mode_name()}"  # noqa: E731
    status = None if args.quiet else StatusLine(sitl.loop, every_s=0.5 if speed else 2.0, extra=extra)
    release_core = claim_cpu([vs.proc.pid] if vs is not None else [], own_core)
    try:
        sitl.loop.run(args.duration, on_slack=status)
    except KeyboardInterrupt:
        pass
    finally:
        release_core()
        mav_stats = vs.stop() if vs is not None else {}
    if status is not None:
        sys.stderr.write("\n")
    summary = sitl.loop.stats.summary()
    controller = resolve(controller, sitl.airframe)  # what flew, `default` resolved
    written = None
    if ulog is not None and len(ulog):
        written = ulog.write(args.ulog, {"ver_hw": f"fcemu SITL {args.airframe}"})
    if getattr(args, "json", False):
        samples = len(ulog) if ulog is not None else 0
        print(json.dumps(flight_summary(controller, args, summary, sitl.loop.faults, written, samples, vs,
                                        mav_stats)))
        return 0
    print(f"controller {controller}  rig {args.rig}  {summary['ticks']} ticks at {args.rate:.0f} Hz"
          f"  misses {summary['deadline_misses']}  p99 period error "
          f"{summary['period_error_us']['p99']:.0f} µs  p99 compute {summary['compute_us']['p99']:.0f} µs"
          + (f"  faults {sitl.loop.faults}" if sitl.loop.faults else ""))
    if written is not None:
        print(f"ulog: {written}, {len(ulog)} samples per topic")
    if vs is not None:
        print(f"vehicle: {vs.vehicle.counters or 'no events'}  ipc dropped {vs.linked.dropped}  "
              f"mavlink: {mav_stats or 'no stats'}")
    return 0


def flight_summary(controller: str, args, timing: dict, faults: dict[str, int], ulog_path: Path | None,
                   ulog_samples: int, vs: VehicleSitl | None, mav_stats: dict) -> dict:
    """`fcemu sitl --json`: what the flight's last lines say, as one JSON object."""
    out = {"controller": controller, "rig": args.rig, "airframe": args.airframe, "rate_hz": args.rate,
           "timing": timing, "faults": faults, "ulog": None}
    if ulog_path is not None:
        out["ulog"] = {"path": str(ulog_path), "samples_per_topic": ulog_samples}
    if vs is not None:
        out["vehicle"] = {"events": vs.vehicle.counters, "ipc_dropped": vs.linked.dropped,
                          "mavlink": mav_stats}
    return out
