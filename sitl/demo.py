"""`fcemu demo`: the SITL (free rig) flown over MAVLink by the pymavlink script `sitl.demo_flight`
(run as its own process, as a GCS would be), faster than real time; prints a summary and writes a
flight plot, the script's log and a .tlog."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from pathlib import Path

FLIGHT_SCRIPT = "fcemu.sitl.demo_flight"


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def plot_flight(log_path: Path, out_png: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    d = np.load(log_path)
    t = d["t"] - d["t"][0]
    fig, ax = plt.subplots(4, 1, figsize=(10, 10), sharex=True)
    ax[0].plot(t, -d["z"], label="altitude (LOCAL_POSITION_NED)")
    ax[0].set_ylabel("m")
    ax[1].plot(t, np.degrees(np.unwrap(d["roll"])), label="roll")
    ax[1].plot(t, np.degrees(d["pitch"]), label="pitch")
    ax[1].set_ylabel("deg (estimator)")
    ax[2].plot(t, d["p"], label="roll rate")
    ax[2].plot(t, d["p_sp"], "--", label="roll rate setpoint")
    ax[2].plot(t, d["q"], label="pitch rate", alpha=0.6)
    ax[2].set_ylabel("rad/s")
    ax[3].plot(t, d["thrust"], label="thrust setpoint")
    ax[3].set_ylabel("0..1")
    ax[3].set_xlabel("vehicle time, s")
    for a in ax:
        a.legend(loc="upper right", fontsize=8)
        a.grid(alpha=0.3)
    ax[0].set_title(title)
    fig.tight_layout()
    fig.savefig(out_png, dpi=90)
    plt.close(fig)


def run_demo(controller: str, speed: float, out: Path, timeout_s: float = 150.0) -> dict:
    from fcemu.firmware.mavlink.bridge import MavlinkConfig, PeerConfig
    from fcemu.firmware.timing import give_loop_a_core
    from fcemu.sitl.sitl import flying_line, start_vehicle_sitl

    out.mkdir(parents=True, exist_ok=True)
    gcs, offboard = _free_port(), _free_port()
    peers = [PeerConfig("gcs", "127.0.0.1", gcs), PeerConfig("offboard", "127.0.0.1", offboard)]
    config = MavlinkConfig(peers=peers, tlog=str(out / "flight.tlog"), params_file=None)
    vs = start_vehicle_sitl(controller, "free", 1000.0, speed, config)
    print(flying_line(controller), file=sys.stderr)
    log, summary_path = out / "flight.npz", out / "summary.json"
    summary_path.unlink(missing_ok=True)
    script = subprocess.Popen([sys.executable, "-m", FLIGHT_SCRIPT, "--connect", f"udpin:127.0.0.1:{gcs}",
                               "--log", str(log), "--summary", str(summary_path),
                               "--timeout", str(timeout_s)], stdout=subprocess.DEVNULL)
    calls = [0]

    def finished() -> bool:
        calls[0] += 1
        return calls[0] % 100 == 0 and script.poll() is not None

    wall0 = time.monotonic()
    release_core = give_loop_a_core((vs.proc.pid, script.pid))
    try:
        vs.sitl.loop.run(timeout_s * speed, should_stop=finished)
    finally:
        release_core()
        wall_s = time.monotonic() - wall0
        mav = vs.stop()
        if script.poll() is None:
            script.terminate()
        script.wait(10)
    flight = json.loads(summary_path.read_text()) if summary_path.exists() else {"completed": False}
    stats = vs.sitl.loop.stats.summary()
    result = {"controller": controller, "speed": speed, "flight": flight,
              "loop": {"ticks": stats["ticks"], "deadline_misses": stats["deadline_misses"],
                       "compute_us_p99": stats["compute_us"]["p99"],
                       "achieved_speed": round(stats["ticks"] * vs.sitl.loop.period_us / 1e6 / wall_s, 2),
                       "clock_rebases": getattr(vs.sitl.loop.clock, "rebases", 0)},
              "vehicle": vs.vehicle.counters, "mavlink": mav, "tlog": str(out / "flight.tlog")}
    if log.exists():
        title = f"fcemu demo: take-off, flip, land ({Path(controller).name}, {speed:g}× real time)"
        plot_flight(log, out / "flight.png", title)
        result["plot"] = str(out / "flight.png")
    (out / "demo.json").write_text(json.dumps(result, indent=1))
    return result


def demo_command(args) -> int:
    from fcemu.firmware.controllers import default_controller
    from fcemu.sitl.sitl import parse_speed

    controller = args.controller or default_controller()
    speed = parse_speed(args.speed) or 3.0
    if not args.json:
        print(f"fcemu demo: {Path(controller).name} flying the Iris twin at {speed:g}× real time, "
              f"driven by {FLIGHT_SCRIPT} over MAVLink ...", file=sys.stderr)
    result = run_demo(controller, speed, Path(args.out))
    if args.json:
        print(json.dumps(result))
    else:
        f = result["flight"]
        print(f"flight: {'completed' if f.get('completed') else 'NOT completed'}  "
              f"max altitude {f.get('max_altitude_m')} m  flip {f.get('flip_deg')}° in {f.get('flip_s')} s"
              f"  "
              f"landed at {f.get('final_altitude_m')} m  ({f.get('flight_s')} s of flight)")
        lp = result["loop"]
        print(f"loop: {lp['ticks']} ticks at {lp['achieved_speed']:g}× real time, "
              f"{lp['deadline_misses']} deadline misses, "
              f"p99 compute {lp['compute_us_p99']:.0f} µs   vehicle events: {result['vehicle']}")
        print(f"MAVLink: {result['mavlink'].get('rx_frames', 0)} frames in, "
              f"{result['mavlink'].get('tx_frames', 0)} out, rejected "
              f"{sum(result['mavlink'].get(k, 0) for k in ('rx_bad', 'rx_rejected', 'rx_foreign'))}")
        print(f"plot: {result.get('plot', '(none)')}   tlog: {result['tlog']}   "
              f"summary: {args.out}/demo.json")
    return 0 if result["flight"].get("completed") else 1
