"""Clocks for the fixed-rate loop, and the per-tick timing statistics it records."""

from __future__ import annotations

import contextlib
import os
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
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
    """Wall time: sleep until `spin_us` before the deadline, then busy-wait the rest.

    `time.sleep` on Linux overshoots by tens of microseconds (more on a loaded machine), so
    the final stretch is busy-waited. By default the loop spins through its whole period at
    1 kHz and above, as a flight controller owns its core: measured on this project's 2-core
    VM, a loop that sleeps between ticks wakes on a cold core and its tick takes 2-3× longer
    (compute p50 53 vs 20 µs, misses 0.23% vs 0.05% at 1 kHz; `fcemu bench loop`).
    """

    realtime = True

    def __init__(self, spin_us: int = 2000) -> None:
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
    """Per-tick timing (µs) over the last `capacity` ticks, plus totals.

    `compute_us` is the firmware's own work in a tick (commander, controller, sinks);
    `plant_us` is the simulated world answering the PWM write (the twin's physics step,
    or the UDP round trip), which hardware would not charge to the flight controller.
    Deadline misses count the whole tick, both together.
    """

    capacity: int = 600_000

    def __post_init__(self) -> None:
        self.compute_us = np.zeros(self.capacity, dtype=np.int64)
        self.period_error_us = np.zeros(self.capacity, dtype=np.int64)
        self.plant_us = np.zeros(self.capacity, dtype=np.int64)
        self.ticks = 0
        self.deadline_misses = 0

    def record(self, compute_us: int, period_error_us: int, plant_us: int = 0) -> None:
        i = self.ticks % self.capacity
        self.compute_us[i] = compute_us
        self.period_error_us[i] = period_error_us
        self.plant_us[i] = plant_us
        self.ticks += 1

    def _window(self, arr: np.ndarray) -> np.ndarray:
        return arr[: min(self.ticks, self.capacity)]

    def summary(self) -> dict:
        return {
            "ticks": self.ticks,
            "deadline_misses": self.deadline_misses,
            "period_error_us": percentiles(self._window(self.period_error_us)),
            "compute_us": percentiles(self._window(self.compute_us)),
            "plant_us": percentiles(self._window(self.plant_us)),
        }


LOOP_NICE = -20


def raise_loop_priority() -> tuple[Callable[[], None], str]:
    """Ask for nice LOOP_NICE for this thread (the flight loop); returns the undo and, when the
    system refuses, why.

    Other local processes (a peer flooding MAVLink, a training run) otherwise take the loop's
    CPU in equal shares and it misses deadlines. Not SCHED_FIFO: the loop spins through its
    period, so a real-time policy runs into the kernel's RT throttling (sched_rt_runtime_us)
    and loses the CPU for tens of milliseconds every second. Where the kernel groups each
    session's processes (sched_autogroup), a nice value only counts inside the session, so the
    session's group is raised too (restored by the undo).
    """
    undo: list[Callable[[], None]] = []
    before = os.getpriority(os.PRIO_PROCESS, 0)
    if before > LOOP_NICE:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, LOOP_NICE)
        except OSError as exc:
            return lambda: None, f"nice {LOOP_NICE}: {exc.strerror or exc}"
        undo.append(lambda: os.setpriority(os.PRIO_PROCESS, 0, before))
    group = _autogroup_nice()
    if group is not None and group > LOOP_NICE:
        try:
            _set_autogroup_nice(LOOP_NICE)
            undo.append(lambda: _set_autogroup_nice(group))
        except OSError as exc:
            undo_all(undo)
            return lambda: None, f"session group nice {LOOP_NICE}: {exc.strerror or exc}"
    return lambda: undo_all(undo), ""


def undo_all(steps: list[Callable[[], None]]) -> None:
    for step in reversed(steps):
        with contextlib.suppress(OSError):
            step()


def _autogroup_nice() -> int | None:
    try:
        if Path("/proc/sys/kernel/sched_autogroup_enabled").read_text().strip() != "1":
            return None
        return int(Path("/proc/self/autogroup").read_text().split()[-1])
    except (OSError, ValueError, IndexError):
        return None


def _set_autogroup_nice(value: int) -> None:
    Path("/proc/self/autogroup").write_text(f"{value}\n")


def prioritize_loop() -> Callable[[], None]:
    """`raise_loop_priority`, saying on stderr when the system refuses; returns the undo."""
    lower, problem = raise_loop_priority()
    if problem:
        print(f"fcemu: note: the flight loop runs at normal priority ({problem}); other load on this "
              "machine can make it miss deadlines (run as root or grant CAP_SYS_NICE)", file=sys.stderr)
    return lower


def available_cpus() -> int:
    """The CPUs this process may run on (its affinity: `taskset`, a container's limit), not the machine's."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def give_loop_a_core(helper_pids: Iterable[int]) -> Callable[[], None]:
    """Pin this process (the flight loop) to one CPU and `helper_pids` to the others, and raise
    its priority (`prioritize_loop`).

    The loop spins through its period, so on a 2-core machine the MAVLink process and its
    peers otherwise keep preempting it mid-tick: measured with `fcemu bench loop --mavlink`,
    compute p50/p99 43/148 µs shared vs 28/99 µs pinned. Returns a function that undoes it.
    Does not pin with fewer than two CPUs.
    """
    lower = prioritize_loop()
    original = os.sched_getaffinity(0)
    cpus = sorted(original)
    if len(cpus) < 2:
        return lower
    loop_cpu, others = {cpus[-1]}, set(cpus[:-1])
    for pid in helper_pids:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.sched_setaffinity(pid, others)
    os.sched_setaffinity(0, loop_cpu)

    def release() -> None:
        os.sched_setaffinity(0, original)
        lower()

    return release
