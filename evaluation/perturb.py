"""`fcemu eval --perturb N`: the same commands on N airframes drawn from the randomisation ranges.

The airframes come from their own random stream, `SeedSequence(perturb_seed,
spawn_key=(PERTURB_STREAM,))`. Training seeds its environments with plain integers
(`default_rng(s)`, spawn key empty), and a SeedSequence's pool mixes in the spawn key, so
no integer training seed below 2**128 draws the evaluation's airframes. Each controller
flies the nominal protocol's commands (same seed, same task) on every airframe; the
per-episode metrics of all N airframes are pooled into one `EvalMetrics`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fcemu.evaluation.metrics import (
    AXES,
    EpisodeMetrics,
    EvalMetrics,
    aggregate,
    pool_episode_metrics,
    traces_episode_metrics,
)
from fcemu.evaluation.runner import EvalConfig, run_controller
from fcemu.sim_bridge.airframe import Airframe
from fcemu.sim_bridge.randomization import Randomization

PERTURB_STREAM = 0x70657274  # "pert": the spawn key that sets the evaluation's airframe stream apart
DELAY_FACTORS = (("esc_delay_ticks", "ESC"), ("gyro_delay_ticks", "gyro"))  # Airframe.scaled keys


@dataclass(frozen=True)
class PerturbedAirframe:
    index: int
    factors: dict[str, Any]  # Airframe.scaled keywords
    airframe: Airframe

    def factors_json(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in self.factors.items()}


def perturbed_airframes(ranges: Randomization, n: int, seed: int) -> list[PerturbedAirframe]:
    """`n` airframes drawn from `ranges` with the evaluation's stream for `seed`."""
    if n < 1:
        raise ValueError(f"--perturb needs at least one airframe, got {n}")
    if seed < 0:
        raise ValueError(f"--perturb-seed must be >= 0, got {seed}")
    base = ranges.base_airframe()
    ranges.check_airframe(base)
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(PERTURB_STREAM,)))
    out = []
    for i in range(n):
        factors = ranges.draw(rng)
        out.append(PerturbedAirframe(i, factors, base.scaled(**factors)))
    return out


@dataclass(frozen=True)
class PerturbedResult:
    """One controller over every perturbed airframe: pooled metrics and each airframe's own Error."""

    metrics: EvalMetrics
    error_sum: np.ndarray  # (N,) per airframe: mean Error summed over the axes
    success_min: np.ndarray  # (N,) per airframe: the lowest axis Success %
    airframes: tuple[PerturbedAirframe, ...]
    seed: int
    ranges: str | None = None  # the randomisation file the airframes were drawn from
    parts: tuple[EpisodeMetrics, ...] = ()  # per airframe: its episodes' metrics, as pooled
    unit: str = "episode"

    def by_delay(self) -> list[DelayGroup]:
        """The airframes grouped by each drawn loop delay (ESC, then gyro), each group pooled.

        A network that reads the rotor speeds can ring on an ESC delay that a PID, which sees
        only the total delay, holds; pooled over all the airframes, such a group hides among the rest.
        """
        groups = []
        for key, label in DELAY_FACTORS:
            values = sorted({a.factors[key] for a in self.airframes if key in a.factors})
            for v in values if self.parts else ():
                members = [i for i, a in enumerate(self.airframes) if a.factors.get(key) == v]
                pooled = aggregate(pool_episode_metrics([self.parts[i] for i in members]), unit=self.unit)
                groups.append(DelayGroup(f"{label} {v}", len(members), pooled,
                                         float(np.mean(self.error_sum[members]))))
        return groups

    def details_json(self) -> dict[str, Any]:
        return {"airframes": len(self.airframes), "perturb_seed": self.seed, "ranges": self.ranges,
                "index_per_airframe": [a.index for a in self.airframes],
                "error_sum_per_airframe": [float(v) for v in self.error_sum],
                "success_min_pct_per_airframe": [float(v) for v in self.success_min],
                "factors": [a.factors_json() for a in self.airframes],
                "by_delay": {g.label: g.to_json() for g in self.by_delay()},
                "n": self.metrics.n_episodes}


@dataclass(frozen=True)
class DelayGroup:
    """The perturbed airframes that share one loop delay, e.g. an ESC delay of 2 ticks."""

    label: str  # "ESC 2" or "gyro 1" (ticks)
    airframes: int
    metrics: EvalMetrics  # their episodes pooled
    error_sum: float  # mean over them of each airframe's Error summed over the axes

    def to_json(self) -> dict[str, Any]:
        success = self.metrics.to_json()["success_pct"]
        return {"airframes": self.airframes, "error_sum": self.error_sum, "success_pct": success}


def fly_perturbed(spec: str, cfg: EvalConfig, airframes: Sequence[PerturbedAirframe], seed: int,
                  on_airframe: Callable[[int], None] | None = None,
                  ranges: str | None = None) -> PerturbedResult:
    """Fly `spec` over the commands of `cfg` on each airframe; pool the per-episode metrics.

    `ranges`: the randomisation file the airframes were drawn from, recorded with the result.
    """
    parts, error_sum, success_min = [], [], []
    unit = "episode"
    for a in airframes:
        traces = run_controller(spec, cfg, progress=False, airframe=a.airframe)
        ep, unit = traces_episode_metrics(traces)
        parts.append(ep)
        m = aggregate(ep, unit=unit)
        error_sum.append(sum(m.stat("error", axis).mean for axis in AXES))
        success_min.append(min(m.stat("success_pct", axis).mean for axis in AXES))
        if on_airframe is not None:
            on_airframe(a.index)
    return PerturbedResult(aggregate(pool_episode_metrics(parts), unit=unit), np.array(error_sum),
                           np.array(success_min), tuple(airframes), seed, ranges, tuple(parts), unit)
