"""Clocks for the fixed-rate loop, and the per-tick timing statistics it records."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Protocol

import numpy as np


class Clock(Protocol):
    """Where the loop's deadlines come from. Times are integer microseconds."""

    realtime: bool

    def now_us(self) -> int: ...

    def wait_until(self, deadline_us: int) -> int:
        """Block until `deadline_us`; return the time actually woken."""
        ...


class RealTimeClock:
    """Wall time: sleep until shortly before the deadline, then spin for the last stretch.

    `time.sleep` on Linux overshoots by tens of microseconds (more on a loaded machine), so
    the final `spin_us` are busy-waited: that is what keeps the period error in single digits.
    """

    realtime = True

    def __init__(self, spin_us: int = 250) -> None:
        self.spin_us = spin_us

    def now_us(self) -> int:
        return time.perf_counter_ns() // 1000

    def wait_until(self, deadline_us: int) -> int:
        remaining = deadline_us - self.now_us()
        if remaining > self.spin_us:
            time.sleep((remaining - self.spin_us) * 1e-6)
        now = self.now_us()
        while now < deadline_us:
            now = self.now_us()
        return now


class LockstepClock:
    """Simulation time: every deadline is met the instant it is asked for; runs as fast as it can."""

    realtime = False

    def __init__(self) -> None:
        self._now = 0

    def now_us(self) -> int:
        return self._now

    def wait_until(self, deadline_us: int) -> int:
        self._now = max(self._now, deadline_us)
        return self._now


def percentiles(values: np.ndarray) -> dict[str, float]:
    if values.size == 0:
        return {"p50": 0.0, "p99": 0.0, "p999": 0.0, "max": 0.0}
    p50, p99, p999 = np.percentile(values, [50, 99, 99.9])
    return {"p50": float(p50), "p99": float(p99), "p999": float(p999), "max": float(values.max())}


@dataclass
class TimingStats:
    """Per-tick compute time and period error (µs) over the last `capacity` ticks, plus totals."""

    capacity: int = 600_000

    def __post_init__(self) -> None:
        self.compute_us = np.zeros(self.capacity, dtype=np.int64)
        self.period_error_us = np.zeros(self.capacity, dtype=np.int64)
        self.ticks = 0
        self.deadline_misses = 0

    def record(self, compute_us: int, period_error_us: int) -> None:
        i = self.ticks % self.capacity
        self.compute_us[i] = compute_us
        self.period_error_us[i] = period_error_us
        self.ticks += 1

    def _window(self, arr: np.ndarray) -> np.ndarray:
        return arr[: min(self.ticks, self.capacity)]

    def summary(self) -> dict:
        return {
            "ticks": self.ticks,
            "deadline_misses": self.deadline_misses,
            "period_error_us": percentiles(self._window(self.period_error_us)),
            "compute_us": percentiles(self._window(self.compute_us)),
        }
