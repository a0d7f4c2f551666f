"""`fcemu eval --fault SPEC`: the same commands with a fault injected at a seeded time of each episode.

A SPEC is `TARGET:KIND[:VALUE]` with an optional motor number anywhere after the target, e.g.
`gyro:stuck`, `gyro:spikes`, `esc-telemetry:delayed:5ms`, `esc-telemetry:3:stuck`,
`motor:2:thrust=0.7`, `battery:wrong=0.75` (sim_bridge/faults.py lists the kinds and their
defaults). VALUE takes `ms`, `s`, `Hz` (a period) or `%`. A burst's VALUE is `LENGTH@FRACTION`:
`esc-telemetry:burst:20ms@1%` loses frames in bursts of 20 ms on average, 1 % of all frames in
the long run (`burst:20ms` and `burst:1%`, one of the two, keep the other's default).

After the fault, per controller: the Error (Σ|Ω* − Ω| per axis, summed over the axes and
averaged over episodes) from the fault tick to the episode's end, beside the same window of the
fault-free run; how many episodes stayed upright (the attitude never more than 90° from the one
the commanded rates lead to from the fault tick on); and what the firmware's health monitor
(firmware/health.py) answered, in how many ticks after the injection.
"""

from __future__ import annotations

import math
import re
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fcemu.firmware.health import HealthMonitor
from fcemu.sim_bridge.fault_spec import parse_fault
from fcemu.sim_bridge.faults import Fault, FaultInjector, FaultSpecError
from fcemu.sitl.traces import Traces

FAULT_STREAM = 0x6661756C  # "faul": the fault times' and draws' seeds, a stream of their own
FAULT_WINDOW = (0.2, 0.5)  # the fault comes at a uniform fraction of the episode in this range
UPRIGHT_DEG = 90.0


def fault_ticks(seed: int, episodes: int, ticks: int, warmup: int) -> np.ndarray:
    """Per episode, the tick the fault comes at: a seeded fraction of the evaluated ticks."""
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(FAULT_STREAM,)))
    fraction = rng.uniform(*FAULT_WINDOW, episodes)
    return warmup + np.floor(fraction * ticks).astype(np.int64)


class FaultPlan:
    """One fault over an evaluation set: when it comes in each episode and what the firmware answered."""

    def __init__(self, fault: Fault, seed: int, episodes: int, ticks: int, warmup: int = 0) -> None:
        self.fault = fault
        self.seed = seed
        self.ticks = fault_ticks(seed, episodes, ticks, warmup)
        self.answers: list[dict[str, int]] = [{} for _ in range(episodes)]
        self.handover: list[str] = [""] * episodes

    def injector(self, episode: int, twin) -> FaultInjector:
        seed = np.random.SeedSequence(self.seed, spawn_key=(FAULT_STREAM, episode)).generate_state(1)[0]
        injector = FaultInjector(twin.dt, twin.airframe.motor.max_rotor_speed, int(seed))
        injector.inject(self.fault)
        return injector

    def record(self, episode: int, at: int, health: HealthMonitor | None) -> None:
        """What the health monitor declared, in ticks after the injection at tick `at`."""
        if health is None:
            return
        # The monitor counts ticks from 1 at tick 0; the first faulty frame is read at tick at + 1.
        self.answers[episode] = {what: tick - 1 - at for what, tick in health.detected.items()
                                 if tick - 1 > at}
        self.handover[episode] = health.handover


@dataclass(frozen=True)
class FaultResult:
    fault: Fault
    episodes: int
    upright: int
    error_after: float  # Σ over axes of the mean Error from the fault tick on
    error_after_nominal: float  # the same window of the fault-free run
    answer_ticks: dict[str, list[int]]  # verdict → each episode's ticks after injection
    handover_reasons: dict[str, int]

    @property
    def answers(self) -> dict[str, tuple[int, float]]:
        """Verdict → (episodes, median ticks after injection)."""
        return {what: (len(t), float(np.median(t))) for what, t in self.answer_ticks.items()}

    def answer_text(self) -> str:
        if not self.answers:
            return "none"
        parts = []
        for what, (n, ticks) in sorted(self.answers.items(), key=lambda kv: kv[1][1]):
            label = {"handover": "PID takes over", "gyro_failed": "gyro failed → LAND",
                     "esc_late": "rotor speed read ahead"}.get(what, what)
            parts.append(f"{label}: {n}/{self.episodes} ep., median {ticks:.0f} ticks")
        return "; ".join(parts)

    def to_json(self) -> dict:
        return {"fault": self.fault.describe(), "episodes": self.episodes, "upright": self.upright,
                "error_after": self.error_after, "error_after_fault_free": self.error_after_nominal,
                "answers": {k: {"episodes": len(t), "median_ticks": float(np.median(t)),
                                "p95_ticks": float(np.percentile(t, 95)), "worst_ticks": float(max(t))}
                            for k, t in self.answer_ticks.items()},
                "handover_reasons": self.handover_reasons}


def _error_after(traces: Traces, ticks: np.ndarray) -> float:
    err = np.abs(traces.setpoint - traces.rate).sum(axis=2)  # (N, T), Σ over axes
    after = np.arange(err.shape[1])[None, :] >= ticks[:, None]
    return float(np.where(after, err, 0.0).sum(axis=1).mean())


def attitude_departure_deg(rate: np.ndarray, setpoint: np.ndarray, start: int, dt: float) -> float:
    """The largest angle between the attitude the body rates `rate` (T, 3) lead to and the one the
    setpoints lead to, both from the same attitude at tick `start`."""
    q_body, q_cmd = np.array([1.0, 0, 0, 0]), np.array([1.0, 0, 0, 0])
    worst = 0.0
    for k in range(start, rate.shape[0]):
        q_body, q_cmd = _rotate(q_body, rate[k], dt), _rotate(q_cmd, setpoint[k], dt)
        dot = min(1.0, abs(float(q_body @ q_cmd)))
        worst = max(worst, 2.0 * math.degrees(math.acos(dot)))
    return worst


def _rotate(q: np.ndarray, omega: np.ndarray, dt: float) -> np.ndarray:
    """q advanced by body rates `omega` for `dt` (exact for constant rates over the step)."""
    angle = float(np.linalg.norm(omega)) * dt
    if angle < 1e-12:
        return q
    axis = omega / np.linalg.norm(omega)
    s = math.sin(angle / 2)
    w2, x2, y2, z2 = math.cos(angle / 2), axis[0] * s, axis[1] * s, axis[2] * s
    w1, x1, y1, z1 = q
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def fault_result(plan: FaultPlan, faulted: Traces, nominal: Traces, dt: float,
                 policy: bool = True) -> FaultResult:
    """`policy`: the controller is a policy (a PID has nothing to hand over, so no hand-over is listed)."""
    n = len(plan.ticks)
    upright = sum(attitude_departure_deg(faulted.rate[i], faulted.setpoint[i], int(plan.ticks[i]), dt)
                  < UPRIGHT_DEG for i in range(n))
    verdicts: dict[str, list[int]] = {}
    for answer in plan.answers:
        for what, ticks in answer.items():
            if what == "handover" and not policy:
                continue
            verdicts.setdefault(what, []).append(ticks)
    reasons = Counter(re.sub(r"\d", "N", h) for h in plan.handover if h and policy)
    return FaultResult(plan.fault, n, int(upright), _error_after(faulted, plan.ticks),
                       _error_after(nominal, plan.ticks), verdicts, dict(reasons))


def fault_table(rows: Sequence[tuple[str, FaultResult]]) -> str:
    """Markdown: per controller and fault, upright, Error after the fault against fault-free, the answer."""
    lines = ["| Controller | Fault | Upright | Error Σ after the fault | fault-free, same window "
             "| Firmware's answer (ticks after injection) |", "|---|---|---:|---:|---:|---|"]
    for name, r in rows:
        cell = name.replace("|", "\\|")
        lines.append(f"| {cell} | {r.fault.describe()} | {r.upright}/{r.episodes} | {r.error_after:.1f} | "
                     f"{r.error_after_nominal:.1f} | {r.answer_text()} |")
    return "\n".join(lines)


def summary_line(name: str, r: FaultResult) -> str:
    return (f"{name:>28}  fault {r.fault.describe()}: upright {r.upright}/{r.episodes}  error after "
            f"{r.error_after:.1f} (fault-free {r.error_after_nominal:.1f})  answer: {r.answer_text()}")


def check_specs(specs: Sequence[str]) -> list[Fault]:
    return [parse_fault(s) for s in specs]


__all__ = ["FaultPlan", "FaultResult", "FaultSpecError", "check_specs", "fault_result", "fault_table",
           "parse_fault", "summary_line"]
