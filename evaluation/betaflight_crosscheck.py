"""`fcemu betaflight`: real Betaflight on the rig, and fcemu's `pid:betaflight` on the same commands.

Both fly the evaluator's seeded episodic commands (`sim_bridge.tasks.episodic_commands`),
quantised to the µs of the stick channels Betaflight receives, from rest, at the same collective,
on the same twin; both are scored by `evaluation.metrics.compute_metrics`.

The closed-loop metrics can agree by accident (one difference hiding another through the
mixer's saturation), so the report also replays the controller open loop: fcemu's preset is fed
Betaflight's own recorded gyro and commands tick by tick, and its per-axis motor mix is compared
with Betaflight's answers (`replay_residual`). Equal controllers give a residual at the level of
Betaflight's 1 µs output truncation and its 8 kHz filters on the held 1 kHz gyro.

`--firmware DIR` flies a Betaflight built with a policy in it (`fcemu export --target
betaflight`) with NEURAL on, against fcemu flying the same exported C policy (DIR/policy).

Pace. The SITL's clock follows the FDM timestamps only as far as the packets' arrival allows
(see `sitl.betaflight`); each episode's drift of that clock from the twin's is measured and a
PID run in which it exceeds `CLOCK_TOLERANCE` (median) or `CLOCK_LIMIT` is refused, since
Betaflight's 8 kHz loop, filters and RX then run on another time base than the twin's. The
default pace (`--speed 0.25`) keeps it within tolerance on a lightly loaded host; a heavily
loaded one is told to fly slower.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from fcemu.evaluation.metrics import AXES, EvalMetrics, compute_metrics
from fcemu.evaluation.runner import TraceRecorder
from fcemu.firmware.controller import RateSetpoint
from fcemu.firmware.controllers import load_controller
from fcemu.firmware.loop import Command, FlightLoop
from fcemu.firmware.mixer import BETAFLIGHT_QUAD_X
from fcemu.firmware.sensors import SensorFrame
from fcemu.firmware.timing import LockstepClock
from fcemu.sim_bridge.airframe import DEFAULT_AIRFRAME, Airframe, load_airframe
from fcemu.sim_bridge.airframe_spec import airframe_spec
from fcemu.sim_bridge.link import InProcessLink
from fcemu.sim_bridge.tasks import episodic_commands
from fcemu.sim_bridge.twin import Twin
from fcemu.sitl.betaflight import BetaflightFlight
from fcemu.sitl.betaflight_process import BetaflightError, NeuralFirmware, neural_firmware
from fcemu.sitl.betaflight_rc import RcMap
from fcemu.sitl.traces import Traces, save_traces

FCEMU_PRESET = "pid:betaflight"
_AT_REST, _NO_ROTORS = np.array([0.0, 0.0, -9.80665]), np.zeros(4)
TOLERANCE = 0.15
NEURAL_TOLERANCE = 0.05
CLOCK_TOLERANCE = 0.05  # median over episodes of |SITL elapsed / twin elapsed − 1|
CLOCK_LIMIT = 0.15  # the same, any one episode
# --rig free with a neural firmware: NEURAL on from after the 1 s climb to after the doublets
# (1.0–5.5 s of `scripted_flight`), then the PID descends.
NEURAL_WINDOW_S = (0.9, 5.6)
COMPARED = ("rise_ms", "peak_pct", "error")


class _Hold:
    def __init__(self, setpoint: np.ndarray, throttle: float) -> None:
        self.command_ = Command(True, RateSetpoint(setpoint, throttle), "main")

    def command(self, t_us: int, frame: SensorFrame) -> Command:
        return self.command_


def fly_fcemu(spec: str, commands: np.ndarray, throttle: float, ticks: int, progress: bool = False,
              airframe: Airframe | str = DEFAULT_AIRFRAME) -> Traces:
    """fcemu's firmware loop, lockstep on the rig, each command from rest (as `fcemu eval`)."""
    twin = Twin(airframe, rig="rig")
    controller = load_controller(spec, airframe=airframe_spec(twin.airframe))
    n = len(commands)
    rate, pwm = np.zeros((n, ticks, 3)), np.zeros((n, ticks, 4))
    for i in tqdm(range(n), desc=spec, unit="ep", disable=not progress, leave=False):
        loop = FlightLoop(InProcessLink(twin), twin.reset(), {"main": controller},
                          _Hold(commands[i], throttle), LockstepClock(), 1000.0,
                          [TraceRecorder(rate[i], pwm[i])])
        for k in range(ticks):
            loop.tick(k * loop.period_us)
    setpoint = np.broadcast_to(commands[:, None, :], (n, ticks, 3)).copy()
    return Traces(np.arange(ticks) * twin.dt, setpoint, rate, pwm, controller=spec, task="episodic",
                  extra={"throttle": throttle})


def fly_betaflight(commands: np.ndarray, throttle_ch: int, ticks: int, run_dir: Path, speed: float,
                   rc: RcMap, progress: bool = False, firmware: NeuralFirmware | None = None,
                   airframe: Airframe | str = DEFAULT_AIRFRAME, blackbox: str | None = None) -> Traces:
    bar = tqdm(total=len(commands), desc="betaflight", unit="ep", disable=not progress, leave=False)
    with BetaflightFlight(run_dir, Twin(airframe, rig="rig"), rc, speed=speed, firmware=firmware,
                          neural=firmware is not None, blackbox=blackbox) as flight:
        traces = flight.fly_steps(commands, throttle_ch, ticks / 1000.0, on_episode=lambda _: bar.update())
    bar.close()
    _say_blackbox(flight)
    return traces


def _say_blackbox(flight: BetaflightFlight) -> None:
    if flight.blackbox is not None:
        print(f"blackbox: {flight.blackbox} ({flight.blackbox_logs} logs, one per arming)"
              if flight.blackbox_logs else "blackbox: Betaflight wrote no log", file=sys.stderr)


def axis_mix(pwm: np.ndarray) -> np.ndarray:
    """Per-axis motor mix (..., 4) µs → (..., 3) µs: each axis' share of the four outputs, FRD."""
    return np.asarray(pwm) @ np.asarray(BETAFLIGHT_QUAD_X) / 4.0


def first_answer_tick(pwm: np.ndarray, idle_us: float) -> int:
    """The first tick at which an episode's motors leave idle: Betaflight answers the first FDM
    packet of a step before its RX task has read the RC packet sent with it."""
    moving = np.flatnonzero(pwm.max(axis=1) > idle_us + 0.5)
    return int(moving[0]) if moving.size else 0


def replay_residual(bf: Traces, spec: str, throttle: float, idle_us: float,
                    airframe: Airframe | str = DEFAULT_AIRFRAME) -> dict[str, Any]:
    """Open loop: `spec` gets Betaflight's gyro and command each tick (the command from the tick
    Betaflight first answered it); the rms difference of the per-axis motor mix (µs) from
    Betaflight's, pooled over all episodes and as the median of the episodes' rms."""
    controller = load_controller(spec, airframe=airframe_spec(airframe))
    per_episode, pooled = [], []
    for i in range(bf.n_episodes):
        start = first_answer_tick(bf.pwm[i], idle_us)
        controller.reset()
        out = np.zeros_like(bf.pwm[i])
        for k in range(len(bf.t)):
            rates = bf.setpoint[i, k] if k >= start else np.zeros(3)
            gyro = np.asarray(bf.rate[i, k], dtype=float)
            frame = SensorFrame(round(bf.t[k] * 1e6), gyro, _AT_REST, _NO_ROTORS)
            out[k] = controller.update(RateSetpoint(rates, throttle), frame, bf.dt)
        diff = (axis_mix(bf.pwm[i]) - axis_mix(out))[start:]
        pooled.append(diff)
        per_episode.append(np.sqrt(np.mean(diff ** 2, axis=0)))
    rms = np.sqrt(np.mean(np.concatenate(pooled) ** 2, axis=0))
    median = np.median(per_episode, axis=0)
    return {"rms_us": dict(zip(AXES, np.round(rms, 2).tolist(), strict=True)),
            "median_episode_rms_us": dict(zip(AXES, np.round(median, 2).tolist(), strict=True))}


def check_clock(bf: Traces, speed: float, enforce: bool = True) -> dict[str, Any]:
    """The SITL clock's drift from the twin's per episode; with `enforce`, refuses (BetaflightError)
    a run whose median episode drifted more than CLOCK_TOLERANCE, or any episode more than
    CLOCK_LIMIT. Not enforced for a NEURAL firmware: its policy ticks once per FDM packet, not
    on the SITL's clock, and with RC smoothing and feedforward off nothing else in its loop
    reads that clock (the drift is reported)."""
    drift = np.abs(np.asarray(bf.extra.get("clock_drift_per_episode", []), dtype=float))
    if drift.size == 0:
        return {}
    median, worst = float(np.median(drift)), int(np.argmax(drift))
    summary = {"median": round(median, 4), "max": round(float(drift[worst]), 4),
               "tolerance": CLOCK_TOLERANCE, "limit": CLOCK_LIMIT, "enforced": enforce}
    if enforce and (median > CLOCK_TOLERANCE or drift[worst] > CLOCK_LIMIT):
        raise BetaflightError(f"the SITL's clock drifted from the twin's by {median:.1%} per episode "
                              f"(median; "
                              f"worst {drift[worst]:.1%}, episode {worst}; tolerance {CLOCK_TOLERANCE:.0%} "
                              f"median, {CLOCK_LIMIT:.0%} any) at --speed {speed:g}: Betaflight ran on "
                              f"another time base than the twin; fly slower (e.g. --speed {speed / 2:g}) "
                              "or on a less loaded host")
    return summary


def trace_difference(bf: Traces, fc: Traces) -> dict[str, float]:
    """Tick by tick, the same policy in Betaflight and in fcemu: the largest rate difference, and
    the first tick's motor outputs (before any difference has fed back through the twin)."""
    rate = np.abs(bf.rate - fc.rate).max(axis=(1, 2))
    return {"rate_max_rad_s": round(float(rate.max()), 4),
            "rate_median_episode_max_rad_s": round(float(np.median(rate)), 4),
            "first_tick_pwm_max_us": round(float(np.abs(bf.pwm[:, 0] - fc.pwm[:, 0]).max()), 3)}


def comparison(bf: EvalMetrics, fc: EvalMetrics, tolerance: float = TOLERANCE) -> dict[str, dict[str, Any]]:
    """Per metric and axis: Betaflight, fcemu, relative difference, within TOLERANCE."""
    out: dict[str, dict[str, Any]] = {}
    for metric in COMPARED:
        out[metric] = {}
        for axis in AXES:
            b, f = bf.stat(metric, axis).mean, fc.stat(metric, axis).mean
            rel = abs(f - b) / abs(b) if b else float("nan")
            out[metric][axis] = {"betaflight": round(b, 2), "fcemu": round(f, 2), "rel_diff": round(rel, 3),
                                 "within": bool(rel <= tolerance)}
    return out


def plot_overlay(bf: Traces, fc: Traces, path: Path, episodes: int = 3,
                 labels: tuple[str, str] = ("Betaflight 4.6 SITL", "fcemu pid:betaflight")) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = min(episodes, bf.n_episodes)
    fig, axes = plt.subplots(n, 3, figsize=(13, 2.6 * n), sharex=True, squeeze=False)
    t_ms = bf.t * 1e3
    for i in range(n):
        for a, name in enumerate(AXES):
            ax = axes[i][a]
            ax.plot(t_ms, bf.setpoint[i, :, a], "k--", lw=1, label="setpoint")
            ax.plot(t_ms, bf.rate[i, :, a], lw=1.3, label=labels[0])
            ax.plot(t_ms, fc.rate[i, :, a], lw=1.3, label=labels[1])
            ax.set_title(f"episode {i}, {name}", fontsize=9)
            ax.grid(alpha=0.3)
            if a == 0:
                ax.set_ylabel("rad/s")
    for ax in axes[-1]:
        ax.set_xlabel("ms")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def markdown(result: dict[str, Any], command: str) -> str:
    title = result.get("title", "Betaflight 4.6.0 SITL vs fcemu `pid:betaflight`")
    within = f"within {result.get('tolerance', TOLERANCE):.0%}".replace("%", " %")
    lines = [f"# {title}", "", f"Made by `{command}`.", "",
             f"{result['episodes']} seeded episodic commands (seed {result['seed']}), each from rest on the "
             "ball-joint rig, hover collective; metrics as `fcemu eval` (mean over episodes).", "",
             f"| metric | axis | Betaflight | fcemu | rel. diff | {within} |", "|---|---|---|---|---|---|"]
    for metric, axes in result["comparison"].items():
        for axis, c in axes.items():
            lines.append(f"| {metric} | {axis} | {c['betaflight']} | {c['fcemu']} | {c['rel_diff']:.1%} | "
                         f"{'yes' if c['within'] else 'no'} |")
    r = result.get("replay")
    lines += [] if r is None else [
              "", "Open loop: fcemu's preset fed Betaflight's own gyro and commands, tick by tick; rms "
              "difference of the per-axis motor mix from Betaflight's answers (µs; 1.0 of demand is 945 µs):",
              "", "| | roll | pitch | yaw |", "|---|---|---|---|",
              "| pooled | " + " | ".join(str(r["rms_us"][a]) for a in AXES) + " |",
              "| median episode | " + " | ".join(str(r["median_episode_rms_us"][a]) for a in AXES) + " |"]
    d = result.get("traces")
    if d:
        lines += ["", "Tick by tick: the first tick's motor outputs differ by at most "
                  f"{d['first_tick_pwm_max_us']} µs (Betaflight's SITL truncates its outputs to whole µs); "
                  "the roll/pitch/yaw rates by at most "
                  f"{d['rate_max_rad_s']} rad/s (median episode {d['rate_median_episode_max_rad_s']}). "
                  "What remains: the SITL's gyro is int16 at 16.4 LSB per deg/s (0.001 rad/s steps), its "
                  "outputs whole µs, the rotor speeds pass as rpm in float, and an answer lost on the link "
                  "flies a step on the previous motors (see Packets)."]
    clock = result.get("clock")
    if clock:
        lines += ["", "SITL clock vs the twin's, |elapsed ratio − 1| per episode: median "
                  f"{clock['median']:.2%}, "
                  f"max {clock['max']:.2%}; --speed {result['setup']['speed']:g}. "
                  + (f"Refused above {clock['tolerance']:.0%} median or {clock['limit']:.0%} in any episode."
                     if clock["enforced"] else
                     "Not enforced: the NEURAL firmware's policy ticks once per FDM packet (the twin's "
                     "step), not on the SITL's clock.")]
    p = result["packets"]
    lines += ["", f"Packets: {p['sent']} FDM sent, {p['received']} motor answers, {p['late']} late "
              f"(sim time slowed for them), {p['lost']} lost.", "",
              "![step responses](step_responses.png)", ""]
    return "\n".join(lines)


def betaflight_command(args) -> int:
    try:
        return _run(args)
    except BetaflightError as exc:
        print(f"fcemu: error: {exc}", file=sys.stderr)
        return 2


def _run(args) -> int:
    if args.episodes < 1:
        raise BetaflightError("--episodes must be >= 1")
    if not args.speed > 0:
        raise BetaflightError("--speed must be positive")
    progress = sys.stderr.isatty() and not args.json
    rc = RcMap(rate_dps=args.rate_dps)
    firmware = neural_firmware(args.firmware) if args.firmware else None
    if args.rig == "free":
        return _run_free(args, rc, firmware)
    commands = rc.quantise(episodic_commands(args.seed, args.episodes))
    airframe = load_airframe(getattr(args, "airframe", DEFAULT_AIRFRAME))
    hover = airframe.hover_throttle()
    throttle_ch = rc.throttle_channel(hover)
    ticks = round(args.episode_s * 1000)
    run_dir = Path(args.run_dir) if args.run_dir else Path(tempfile.mkdtemp(prefix="fcemu_betaflight_"))
    bf = fly_betaflight(commands, throttle_ch, ticks, run_dir, args.speed, rc, progress, firmware, airframe,
                        args.blackbox)
    clock = check_clock(bf, args.speed, enforce=firmware is None)
    bf_metrics = compute_metrics(bf)
    result: dict[str, Any] = {"betaflight": bf_metrics.to_json(), "packets": bf.extra["packets"]}
    spec = str(firmware.policy_dir) if firmware else FCEMU_PRESET
    if args.save_traces:
        print(f"traces: {save_traces(args.save_traces, bf)}", file=sys.stderr)
    if args.crosscheck:
        fc = fly_fcemu(spec, commands, rc.fcemu_throttle(throttle_ch), ticks, progress, airframe)
        fc_metrics = compute_metrics(fc)
        if args.save_traces:
            path = Path(args.save_traces)
            print(f"traces: {save_traces(path.with_name(path.stem + '_fcemu.npz'), fc)}", file=sys.stderr)
        result = {"betaflight": bf_metrics.to_json(), "fcemu": fc_metrics.to_json(),
                  "packets": bf.extra["packets"], "clock": clock}
        tolerance = NEURAL_TOLERANCE if firmware else TOLERANCE
        summary = {"episodes": args.episodes, "seed": args.seed, **result,
                   "comparison": comparison(bf_metrics, fc_metrics, tolerance), "tolerance": tolerance,
                   "setup": {"speed": args.speed, "rate_dps": args.rate_dps, "throttle_channel": throttle_ch,
                             "fcemu_throttle": rc.fcemu_throttle(throttle_ch), "preset": spec,
                             "betaflight_cli": bf.extra["settings"],
                             "reply_us_p50": bf.extra["reply_us_p50"],
                             "reply_us_p99": bf.extra["reply_us_p99"]}}
        if firmware:
            summary["traces"] = trace_difference(bf, fc)
            summary["title"] = ("Betaflight 4.6.0 SITL with the policy compiled in (NEURAL) vs fcemu flying "
                                f"the same exported C policy (`{firmware.policy_dir}`)")
        else:
            summary["replay"] = replay_residual(bf, FCEMU_PRESET, rc.fcemu_throttle(throttle_ch),
                                                1000.0 + 1000.0 * rc.motor_idle, airframe)
        if args.out:
            out = Path(args.out)
            out.mkdir(parents=True, exist_ok=True)
            command = "fcemu " + " ".join(sys.argv[1:])
            (out / "crosscheck.json").write_text(json.dumps(summary, indent=1) + "\n")
            (out / "README.md").write_text(markdown(summary, command))
            labels = ("Betaflight 4.6 SITL, NEURAL", "fcemu, same C policy") if firmware else \
                ("Betaflight 4.6 SITL", "fcemu pid:betaflight")
            plot_overlay(bf, fc, out / "step_responses.png", labels=labels)
            print(f"report: {out / 'README.md'}", file=sys.stderr)
        if not args.json:
            for metric, axes in summary["comparison"].items():
                cells = "  ".join(f"{a} {c['betaflight']}/{c['fcemu']} ({c['rel_diff']:.0%})"
                                  for a, c in axes.items())
                print(f"{metric:>9} betaflight/fcemu: {cells}")
    if args.json:
        print(json.dumps(result))
    elif not args.crosscheck:
        m = result["betaflight"]
        print("betaflight  " + "  ".join(f"{k} {v}" for k, v in m.items() if k in COMPARED))
    if not args.json:
        p = result["packets"]
        print(f"packets: sent {p['sent']}, received {p['received']}, late {p['late']}, lost {p['lost']}")
    return 0


def _run_free(args, rc: RcMap, firmware: NeuralFirmware | None) -> int:
    """The free rig: take-off, doublets on each axis, descent (`fcemu sitl --no-mavlink`'s script);
    with a neural firmware, NEURAL on over NEURAL_WINDOW_S."""
    from fcemu.sitl.sitl import scripted_flight

    if args.crosscheck:
        raise BetaflightError("--crosscheck flies the rig (ball joint); drop --rig free")
    run_dir = Path(args.run_dir) if args.run_dir else Path(tempfile.mkdtemp(prefix="fcemu_betaflight_"))
    if firmware and args.duration <= NEURAL_WINDOW_S[1]:
        raise BetaflightError(f"--rig free with --firmware: NEURAL is on until {NEURAL_WINDOW_S[1]:g} s; "
                              "give --duration longer than that (the PID lands after it)")
    window = NEURAL_WINDOW_S if firmware else None
    airframe = load_airframe(getattr(args, "airframe", DEFAULT_AIRFRAME))
    twin = Twin(airframe, rig="free")
    with BetaflightFlight(run_dir, twin, rc, speed=args.speed, firmware=firmware,
                          blackbox=args.blackbox) as flight:
        traces = flight.fly_script(scripted_flight("free", hover=airframe.hover_throttle()), args.duration,
                                   neural_window_s=window)
    _say_blackbox(flight)
    if args.save_traces:
        print(f"traces: {save_traces(args.save_traces, traces)}", file=sys.stderr)
    result = {"betaflight": compute_metrics(traces).to_json(), "packets": traces.extra["packets"],
              "max_altitude_m": round(traces.extra["max_altitude_m"], 3),
              "final_altitude_m": round(traces.extra["final_altitude_m"], 3)}
    if window:
        on = np.asarray(traces.extra["neural_on"], dtype=bool)
        err = np.abs(traces.setpoint[0] - traces.rate[0])
        result["neural_window_s"] = list(window)
        result["rate_error_mean_rad_s"] = {
            "neural": dict(zip(AXES, np.round(err[on].mean(axis=0), 4).tolist(), strict=True)),
            "pid": dict(zip(AXES, np.round(err[~on].mean(axis=0), 4).tolist(), strict=True))}
    if args.json:
        print(json.dumps(result))
    else:
        p = result["packets"]
        if window:
            e = result["rate_error_mean_rad_s"]
            print(f"NEURAL on {window[0]:g}–{window[1]:g} s; mean |rate error| rad/s, NEURAL: "
                  + " ".join(f"{a} {v}" for a, v in e["neural"].items()) + "; PID: "
                  + " ".join(f"{a} {v}" for a, v in e["pid"].items()))
        print(f"free rig, {args.duration:g} s: climbed to {result['max_altitude_m']} m, ended at "
              f"{result['final_altitude_m']} m; "
              f"packets: sent {p['sent']}, received {p['received']}, late {p['late']}, lost {p['lost']}")
    return 0
