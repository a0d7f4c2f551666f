"""`fcemu bench loop`: the firmware loop's timing budget in real time, flying the twin; with
`--fault SPEC` each measurement is repeated, in the same run, with that fault active in the twin."""

from __future__ import annotations

import json
import socket
import subprocess
import sys

from fcemu.firmware.timing import give_loop_a_core
from fcemu.sim_bridge.airframe import DEFAULT_AIRFRAME
from fcemu.sim_bridge.faults import Fault, FaultInjector
from fcemu.sitl.sitl import build_sitl, firmware_airframe, flying_line, load_controllers


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _inject(sitl, fault: Fault | None) -> None:
    if fault is not None:
        twin = sitl.twin
        twin.faults = FaultInjector(twin.dt, twin.airframe.motor.max_rotor_speed, seed=0)
        twin.faults.inject(fault)


def _answers(sitl, fault: Fault | None, start: int) -> dict:
    """What the health monitor made of `fault`: its verdicts, in ticks after the injection at `start`."""
    health = sitl.loop.health
    if fault is None or health is None:
        return {}
    return {"fault": {"spec": fault.describe(), "handover": health.handover, "failsafe": health.failsafe,
                      "answers_ticks": {k: t - start for k, t in health.detected.items()}}}


def measure_loop(controller: str, seconds: float, rate_hz: float, rig: str = "rig",
                 mavlink: bool = False, fault: Fault | None = None, airframe: str = DEFAULT_AIRFRAME) -> dict:
    """DESIGN.md's `bench loop` figures in real time: the scripted doublets, or with `mavlink`
    the Vehicle flown in OFFBOARD by a peer process sending 100 Hz setpoints while every
    telemetry stream goes out to two peers. `fault` is injected into the twin when the measured
    seconds begin (with `mavlink`, once the vehicle flies OFFBOARD)."""
    if not mavlink:
        sitl = build_sitl(controller, rig=rig, rate_hz=rate_hz, realtime=True, airframe=airframe)
        _inject(sitl, fault)
        start = 0
        release_core = give_loop_a_core(())
        try:
            stats = sitl.loop.run(seconds)
        finally:
            release_core()
        extra = {}
    else:
        from fcemu.firmware.mavlink.bridge import MavlinkConfig, PeerConfig
        from fcemu.sitl.sitl import start_vehicle_sitl

        gcs, offboard = _free_port(), _free_port()
        config = MavlinkConfig(peers=[PeerConfig("gcs", "127.0.0.1", gcs),
                                      PeerConfig("offboard", "127.0.0.1", offboard)], params_file=None)
        vs = start_vehicle_sitl(controller, rig, rate_hz, 1.0, config, airframe=airframe)
        peer = subprocess.Popen([sys.executable, "-m", "fcemu.benchmarks.loadpeer",
                                 str(gcs), str(offboard)])
        sitl = vs.sitl
        release_core = give_loop_a_core((vs.proc.pid, peer.pid))
        try:
            sitl.loop.run(1.0)  # the peer connects, switches to OFFBOARD and arms
            for _ in range(90):  # a loaded host may take longer: measure (and inject) armed
                if vs.vehicle.armed:
                    break
                sitl.loop.run(0.1)
            sitl.loop.stats.__post_init__()
            _inject(sitl, fault)
            start = sitl.loop.health.ticks if sitl.loop.health is not None else 0
            stats = sitl.loop.run(seconds)
        finally:
            release_core()
            peer.terminate()
            peer.wait(5)
            mav = vs.stop()
        extra = {"mavlink": {"armed": vs.vehicle.armed, "mode": vs.vehicle.mode_name(),
                             "ipc_dropped": vs.linked.dropped, "rx_frames": mav.get("rx_frames", 0),
                             "tx_frames": mav.get("tx_frames", 0)}}
    return {"rate_hz": rate_hz, "seconds": seconds, "controller": controller, **stats.summary(),
            "controller_faults": sum(sitl.loop.faults.values()), **extra, **_answers(sitl, fault, start)}


def _line(r: dict, tag: str = "         ") -> str:
    pe, cu = r["period_error_us"], r["compute_us"]
    miss_pct = 100.0 * r["deadline_misses"] / max(r["ticks"], 1)
    return (f"{r['rate_hz']:6.0f} Hz{tag}  ticks {r['ticks']:7d}  misses {r['deadline_misses']:5d} "
            f"({miss_pct:.3f}%)  period error µs p50/p99/p99.9/max {pe['p50']:.0f}/{pe['p99']:.0f}/"
            f"{pe['p999']:.0f}/{pe['max']:.0f}  compute µs {cu['p50']:.0f}/{cu['p99']:.0f}/"
            f"{cu['p999']:.0f}/{cu['max']:.0f}")


def _measure(controller: str, seconds: float, rate: float, args, fault: Fault | None, quiet: bool) -> dict:
    tag = "" if fault is None else f" with {fault.describe()}"
    if not quiet:
        print(f"running {controller} at {rate:.0f} Hz for {seconds:g} s{tag} ...", file=sys.stderr)
    airframe = getattr(args, "airframe", DEFAULT_AIRFRAME)
    result = measure_loop(controller, seconds, rate, args.rig, False, fault, airframe)
    if getattr(args, "mavlink", False):
        if not quiet:
            print(f"running {controller} at {rate:.0f} Hz for {seconds:g} s with MAVLink{tag} ...",
                  file=sys.stderr)
        with_mavlink = measure_loop(controller, seconds, rate, args.rig, True, fault, airframe)
        link = with_mavlink.pop("mavlink")
        for key in ("rate_hz", "seconds", "controller"):
            with_mavlink.pop(key)
        result["mavlink"] = {**with_mavlink, **link}
    return result


def bench_loop(args) -> int:
    """One JSON object per run: the loop's figures, and with --mavlink the same figures measured
    with MAVLink under "mavlink" (with the link's counters); several --rate: {"runs": [...]}.
    With --fault the same figures with the fault active follow under "with_fault" (measured right
    after the fault-free ones, so both meet the same load on the host)."""
    from fcemu.firmware.controllers import default_controller

    controller = args.controller or default_controller()
    rates = args.rate or [1000.0]
    fault: Fault | None = getattr(args, "fault", None)
    # A bad --controller, or one not for the airframe, fails here, before the line below.
    load_controllers(controller, rates[0], firmware_airframe(getattr(args, "airframe", DEFAULT_AIRFRAME))[1])
    print(flying_line(controller), file=sys.stderr)
    results = []
    for rate in rates:
        result = _measure(controller, args.seconds, rate, args, None, args.json)
        if fault is not None:
            faulted = _measure(controller, args.seconds, rate, args, fault, args.json)
            for key in ("rate_hz", "seconds", "controller"):
                faulted.pop(key)
            result["with_fault"] = faulted
        results.append(result)
    if args.json:
        print(json.dumps(results[0] if len(results) == 1 else {"runs": results}))
        return 0
    for r in results:
        _print_run(r)
        if "with_fault" in r:
            f = r["with_fault"]
            print(f"          with {f['fault']['spec']}: firmware's answer (ticks after injection) "
                  f"{f['fault']['answers_ticks'] or 'none'}")
            _print_run({**f, "rate_hz": r["rate_hz"]}, " +fault")
    return 0


def _print_run(r: dict, tag: str = "") -> None:
    print(_line(r, f"{tag:9}"))
    if "mavlink" in r:
        m = r["mavlink"]
        print(_line({**m, "rate_hz": r["rate_hz"]}, f"{tag} +mavlink"))
        counters = {k: m[k] for k in ("armed", "mode", "ipc_dropped", "rx_frames", "tx_frames")}
        print(f"          MAVLink: {counters}")
        if "fault" in m:
            print(f"          with MAVLink, firmware's answer (ticks after injection) "
                  f"{m['fault']['answers_ticks'] or 'none'}")
