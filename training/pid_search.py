"""Flying PID presets on the ball-joint twin, scoring them, and a parallel pattern search over knobs.

The loop is the firmware's, stripped to its core: read the frame, `controller.update`,
`twin.step`, at 1 kHz on `Twin(rig="rig")`, over the paper's episodic commands at the
airframe's hover throttle; scores are the paper's metrics from `evaluation.metrics`.
`CandidatePool` flies many presets at once, one per worker process (`jobs`), each worker
holding its own twins; the search is deterministic for a given number of jobs.
"""

from __future__ import annotations

import json
import math
import multiprocessing as mp
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fcemu.evaluation.metrics import episode_metrics
from fcemu.firmware.controller import RateSetpoint
from fcemu.firmware.pid_controller import PIDRateController
from fcemu.sim_bridge.airframe import Airframe
from fcemu.sim_bridge.twin import SensorNoise, Twin

AXES = ("roll", "pitch", "yaw")
DT = 0.001
TICKS = 1000


def fly(controller: PIDRateController, twin: Twin, setpoints: np.ndarray, throttle: float,
        ticks: int = TICKS) -> tuple[np.ndarray, np.ndarray]:
    """(rate, pwm) traces, (N, T, 3) and (N, T, 4); sample k is what tick k read and wrote.

    The rate is the body's (`Twin.clean_gyro`), what the metrics judge; the controller reads
    the gyro, noisy where the twin's is."""
    n = len(setpoints)
    rate, pwm = np.zeros((n, ticks, 3)), np.zeros((n, ticks, 4))
    for i, sp in enumerate(setpoints):
        frame = twin.reset(seed=i)
        controller.reset()
        setpoint = RateSetpoint(np.asarray(sp, dtype=float), throttle)
        r, u = rate[i], pwm[i]
        for k in range(ticks):
            out = controller.update(setpoint, frame, DT)
            r[k] = twin.clean_gyro()
            u[k] = out
            frame = twin.step(out)
    return rate, pwm


@dataclass(frozen=True)
class Score:
    error: np.ndarray  # (3,) mean per-episode Σ|Ω* − Ω|, rad/s
    rise_ms: np.ndarray  # (3,) mean over episodes that reached 90%
    peak_pct: np.ndarray  # (3,)
    success_pct: np.ndarray  # (3,)
    not_risen: np.ndarray  # (3,) episodes that never reached 90%
    smoothness: float  # mean |Δpwm| per step, µs
    worst_settle_pct: np.ndarray  # (3,) the largest settling error over episodes, % of |e0| (Success: ≤ 10)

    def line(self) -> str:
        axes = "  ".join(f"{a}: E {self.error[i]:.1f} rise {self.rise_ms[i]:.1f} ms"
                         f" peak {self.peak_pct[i]:.1f}%"
                         f" ok {self.success_pct[i]:.1f}%" for i, a in enumerate(AXES))
        return f"{axes}  |du| {self.smoothness:.2f} µs"

    def to_json(self) -> dict[str, Any]:
        def per_axis(v: np.ndarray) -> dict[str, float | None]:
            return {a: round(float(x), 2) if np.isfinite(x) else None for a, x in zip(AXES, v, strict=True)}

        return {"error": per_axis(self.error), "error_sum": round(float(self.error.sum()), 2),
                "rise_ms": per_axis(self.rise_ms), "peak_pct": per_axis(self.peak_pct),
                "success_pct": per_axis(self.success_pct), "smoothness_us": round(self.smoothness, 3),
                "worst_settle_pct": per_axis(self.worst_settle_pct)}


def score(setpoints: np.ndarray, rate: np.ndarray, pwm: np.ndarray) -> Score:
    t = np.arange(rate.shape[1]) * DT
    sp = np.broadcast_to(setpoints[:, None, :], rate.shape)
    ep = episode_metrics(t, sp, rate, pwm)
    with np.errstate(invalid="ignore"):
        rise = np.nanmean(np.where(ep.included, ep.rise_ms, np.nan), axis=0)
        peak = np.nanmean(ep.peak_pct, axis=0)
        worst = np.nanmax(np.where(ep.assessed, ep.settle_err_pct, np.nan), axis=0)
    inc = ep.included
    return Score(error=ep.error.mean(axis=0), rise_ms=rise, peak_pct=peak,
                 success_pct=100.0 * ep.success.sum(axis=0) / np.maximum(inc.sum(axis=0), 1),
                 not_risen=(inc & ~np.isfinite(ep.rise_ms)).sum(axis=0),
                 smoothness=float(ep.smoothness_per_motor.mean()), worst_settle_pct=np.nan_to_num(worst))


class Flights:
    """One airframe's twins (a clean gyro and a noisy one) and commands: `evaluate` scores a preset."""

    def __init__(self, airframe: Airframe, setpoints: np.ndarray, gyro_noise: float) -> None:
        self.twins = {False: Twin(airframe, rig="rig"),
                      True: Twin(airframe, rig="rig", noise=SensorNoise(gyro_std=gyro_noise))}
        self.setpoints = np.asarray(setpoints, dtype=float)
        self.throttle = airframe.hover_throttle()

    def evaluate(self, preset: dict[str, Any], noisy: bool) -> Score:
        controller = PIDRateController.from_dict(preset)
        return score(self.setpoints, *fly(controller, self.twins[noisy], self.setpoints, self.throttle))


class _Worker:
    """A worker process's airframe, its flights per command set, and the bound's programmes."""

    def __init__(self, airframe: Airframe, gyro_noise: float) -> None:
        self.airframe, self.gyro_noise = airframe, gyro_noise
        self.flights: dict[bytes, Flights] = {}
        self.floor: Any = None

    def fly(self, preset: dict[str, Any], noisy: bool, setpoints: np.ndarray) -> Score:
        key = setpoints.tobytes()
        if key not in self.flights:
            self.flights = {key: Flights(self.airframe, setpoints, self.gyro_noise)}
        return self.flights[key].evaluate(preset, noisy)

    def bound(self, command: np.ndarray, tight: bool) -> Any:
        from fcemu.evaluation.bound import Floor, rig_constants

        if self.floor is None:
            self.floor = Floor(rig_constants(self.airframe))
        return self.floor.solve(command, tight=tight)


_WORKER: _Worker | None = None


def _init_worker(airframe: Airframe, gyro_noise: float) -> None:
    global _WORKER
    _WORKER = _Worker(airframe, gyro_noise)


def _fly(job: tuple[dict[str, Any], bool, np.ndarray]) -> Score:
    assert _WORKER is not None
    return _WORKER.fly(*job)


def _bound(job: tuple[np.ndarray, bool]) -> Any:
    assert _WORKER is not None
    return _WORKER.bound(*job)


class CandidatePool:
    """Flies presets, `jobs` at a time in worker processes (1: in this one); also solves the
    bound's programmes (`evaluation.bound.Floor`) for commands, one per worker."""

    def __init__(self, airframe: Airframe, gyro_noise: float, jobs: int = 1) -> None:
        self.jobs = max(1, jobs)
        self._pool = None
        if self.jobs == 1:
            _init_worker(airframe, gyro_noise)
        else:
            self._pool = mp.get_context("spawn").Pool(self.jobs, _init_worker, (airframe, gyro_noise))

    def scores(self, presets: Sequence[dict[str, Any]], noisy: bool, setpoints: np.ndarray) -> list[Score]:
        jobs = [(p, noisy, np.asarray(setpoints, dtype=float)) for p in presets]
        if self._pool is None:
            return [_fly(j) for j in jobs]
        return self._pool.map(_fly, jobs, chunksize=1)

    def bounds(self, commands: np.ndarray, progress: Callable[[int], None] | None = None,
               tight: bool = True) -> list[Any]:
        """`evaluation.bound.CommandBound` per command (`Floor.solve`); `progress(done)` after each."""
        work = [(np.asarray(c, dtype=float), tight) for c in commands]
        found = []
        for b in map(_bound, work) if self._pool is None else self._pool.imap(_bound, work):
            found.append(b)
            if progress:
                progress(len(found))
        return found

    def close(self) -> None:
        if self._pool is not None:
            self._pool.terminate()
            self._pool.join()
            self._pool = None

    def __enter__(self) -> CandidatePool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class Knob:
    """One searched setting: `pid[setting]` (or its `axis` entry), moved by a factor `step` within bounds."""

    name: str
    setting: str
    axis: int | None
    step: float
    lowest: float
    highest: float
    first: float = 0.0  # where a move up from zero goes (a term the start does not use); 0: stays off

    def get(self, preset: dict[str, Any]) -> float:
        value = preset["pid"][self.setting]
        return float(value if self.axis is None else value[self.axis])

    def moved(self, preset: dict[str, Any], factor: float) -> dict[str, Any] | None:
        """A copy with this knob times `factor` (clamped to the bounds); None if that changes nothing."""
        value = self.get(preset)
        target = value * factor
        if value == 0.0 and self.first > 0.0:
            if factor <= 1.0:
                return None
            target = self.first
        new = float(f"{min(max(target, self.lowest), self.highest):.6g}")
        if math.isclose(new, value, rel_tol=1e-9):
            return None
        out = json.loads(json.dumps(preset))
        if self.axis is None:
            out["pid"][self.setting] = new
        else:
            out["pid"][self.setting][self.axis] = new
        return out


@dataclass(frozen=True)
class AxisGains:
    """One axis's P, I, D and feedforward moved together by one factor: its loop gain, what a start
    carried over by physics is least sure of. A coordinate move cannot change it without first
    unbalancing the loop, so the search stalls short of it (the Crazyflie's: 2.06 × the bound with
    the gains a factor 3 to 7 low). Each gain keeps its own knob's bounds."""

    name: str
    gains: tuple[Knob, ...]
    step: float

    def get(self, preset: dict[str, Any]) -> float:
        return self.gains[0].get(preset)

    def moved(self, preset: dict[str, Any], factor: float) -> dict[str, Any] | None:
        out, changed = preset, False
        for knob in self.gains:
            if knob.get(out) == 0.0:  # a term the axis does not use stays off
                continue
            trial = knob.moved(out, factor)
            if trial is not None:
                out, changed = trial, True
        return out if changed else None


Move = Knob | AxisGains


@dataclass
class SearchState:
    preset: dict[str, Any]
    score: Score
    cost: float
    evaluations: int = 0
    rounds: int = 0


Progress = Callable[[str], None]


def pattern_search(start: SearchState, knobs: Sequence[Move], pool: CandidatePool, noisy: bool,
                   setpoints: np.ndarray, cost: Callable[[Score], float], deadline: float,
                   max_rounds: int = 12,
                   progress: Progress | None = None, label: str = "") -> SearchState:
    """Deterministic pattern search in log space: each knob is tried a step up and down, knobs in
    batches that fill the pool's workers; the best improving move of a batch is taken. When a
    whole round finds nothing the steps shrink. Stops at `deadline` (time.monotonic) or when
    the steps have shrunk three times."""
    best = start
    per_batch = max(1, pool.jobs // 2)
    shrink = 1.0
    for rnd in range(max_rounds):
        improved = False
        for first in range(0, len(knobs), per_batch):
            if time.monotonic() >= deadline:
                return best
            moves = []
            for knob in knobs[first:first + per_batch]:
                step = knob.step**shrink
                for factor in (step, 1.0 / step):
                    trial = knob.moved(best.preset, factor)
                    if trial is not None:
                        moves.append((knob, trial))
            if not moves:
                continue
            scores = pool.scores([t for _, t in moves], noisy, setpoints)
            best.evaluations += len(moves)
            costs = [cost(s) for s in scores]
            i = int(np.argmin(costs))
            if costs[i] < best.cost - 1e-4:
                best = SearchState(moves[i][1], scores[i], costs[i], best.evaluations, best.rounds)
                improved = True
                if progress:
                    progress(f"{label} round {rnd}: {moves[i][0].name} -> {moves[i][0].get(best.preset):.4g}"
                             f"  best cost {best.cost:.4f}")
        best.rounds = rnd + 1
        if not improved:
            shrink *= 0.5
            if shrink < 0.2:
                break
    return best
