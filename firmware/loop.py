"""The fixed-rate inner loop: read the SensorFrame, run the controller, write PWM, record timing.

The loop owns time and I/O and nothing else. What to fly (armed, setpoint, which
controller) comes from a `Commander`; what happened goes to `TelemetrySink`s. Both are
called once per tick and must be cheap and non-blocking: network I/O lives elsewhere.
"""

from __future__ import annotations

import gc
import math
import time
from collections.abc import Callable, Mapping, Sequence
from typing import NamedTuple, Protocol

import numpy as np

from fcemu.firmware.controller import PWM_MAX, PWM_MIN, RateController, RateSetpoint
from fcemu.firmware.health import HealthMonitor
from fcemu.firmware.sensors import SensorFrame
from fcemu.firmware.timing import Clock, TimingStats

DISARMED_PWM = np.full(4, PWM_MIN)
# Garbage collection runs only in a tick's slack, and only when at least this much is left.
GC_SLACK_US = 400
GC_EVERY_TICKS = 200


class Plant(Protocol):
    """The vehicle's hardware as the firmware sees it: the twin in-process or over the UDP link."""

    def pwm_write(self, pwm: np.ndarray) -> SensorFrame: ...


class Command(NamedTuple):
    armed: bool
    setpoint: RateSetpoint
    controller: str  # key into the loop's controllers


class TickSample(NamedTuple):
    t_us: int  # the tick's scheduled time on the loop clock
    frame: SensorFrame  # what the controller read
    command: Command
    pwm: np.ndarray  # what was written
    controller: str  # which controller produced it (may be the fallback)
    sensed: SensorFrame | None = None  # what the sensors said, before the health checks read any ahead


class Commander(Protocol):
    def command(self, t_us: int, frame: SensorFrame) -> Command: ...


class TelemetrySink(Protocol):
    def publish(self, sample: TickSample) -> None: ...


class ScriptedCommander:
    """A fixed schedule of setpoints: [(start_s, rates FRD rad/s, throttle)], armed throughout."""

    def __init__(self, schedule: Sequence[tuple[float, Sequence[float], float]],
                 controller: str = "default") -> None:
        if not schedule:
            raise ValueError("a scripted schedule needs at least one setpoint")
        self._starts = [round(s * 1e6) for s, _, _ in schedule]
        self._commands = [Command(True, RateSetpoint(np.asarray(r, float), float(th)), controller)
                          for _, r, th in schedule]
        self._i = 0

    def command(self, t_us: int, frame: SensorFrame) -> Command:
        while self._i + 1 < len(self._starts) and t_us >= self._starts[self._i + 1]:
            self._i += 1
        return self._commands[self._i]


class FlightLoop:
    """Runs `controllers[command.controller]` against `plant` at `rate_hz` on `clock`.

    Deadlines sit on an absolute grid (t0 + k·period), so the loop never drifts; a tick
    that overruns is counted as a miss and the loop resumes at the next grid point ahead
    rather than catching up in a burst; the plant steps through the skipped slots with the
    last PWM held, so simulated time stays on the loop's clock. A controller that raises or
    returns non-finite or out-of-range PWM is replaced for that tick by `fallback` (or the
    motors stop if there is none), and the fault is counted; the loop never stops for bad data.
    With `health` (firmware/health.py) each tick's frame is checked first: the controller reads
    the frame it returns, and once it no longer trusts a policy's inputs the fallback flies.
    """

    def __init__(
        self,
        plant: Plant,
        initial_frame: SensorFrame,
        controllers: Mapping[str, RateController],
        commander: Commander,
        clock: Clock,
        rate_hz: float = 1000.0,
        sinks: Sequence[TelemetrySink] = (),
        fallback: str | None = None,
        stats: TimingStats | None = None,
        health: HealthMonitor | None = None,
    ) -> None:
        if rate_hz <= 0 or 1e6 % rate_hz:
            raise ValueError(f"rate_hz must divide one second into whole microseconds, got {rate_hz}")
        self.plant = plant
        self.frame = initial_frame
        self.controllers = dict(controllers)
        self.commander = commander
        self.clock = clock
        self.period_us = int(1e6 // rate_hz)
        self.dt = self.period_us * 1e-6
        self.sinks = list(sinks)
        self.fallback = fallback
        self.stats = stats or TimingStats()
        self.faults: dict[str, int] = {}
        self._armed = False
        self._active = ""
        self.last_sample: TickSample | None = None
        self.plant_ns = 0
        self.health = health

    def tick(self, t_us: int) -> TickSample:
        command = self.commander.command(t_us, self.frame)
        name = command.controller
        frame = sensed = self.frame
        health = self.health
        if health is not None:
            if command.armed and not self._armed:
                health.reset()
            written = self.last_sample.pwm if self.last_sample is not None else DISARMED_PWM
            health.policy_flying = name != self.fallback
            frame = health.check(frame, written)
            if not health.policy_trusted and self.fallback in self.controllers:
                name = self.fallback
        if not command.armed:
            pwm = DISARMED_PWM
        else:
            if not self._armed or name != self._active:
                self._switch(name, command.setpoint, frame)
            pwm, name = self._run_controller(name, command.setpoint, frame)
        self._armed = command.armed
        plant_start = time.perf_counter_ns()
        self.frame = self.plant.pwm_write(pwm)
        self.plant_ns = time.perf_counter_ns() - plant_start
        sample = TickSample(t_us, frame, command, pwm, name, sensed)
        for sink in self.sinks:
            sink.publish(sample)
        self.last_sample = sample
        return sample

    def _hold_outputs(self, slots: int) -> None:
        """The world does not wait for a late tick: ESCs hold the last PWM through skipped slots."""
        pwm = self.last_sample.pwm if self.last_sample is not None else DISARMED_PWM
        for _ in range(slots):
            self.frame = self.plant.pwm_write(pwm)

    def _switch(self, name: str, setpoint: RateSetpoint, frame: SensorFrame) -> None:
        """On arming a controller starts from reset; in flight one that can takes over bumplessly."""
        controller = self.controllers.get(name)
        if controller is not None:
            take_over = getattr(controller, "take_over", None)
            if self._armed and take_over is not None:
                take_over(setpoint, frame)
            else:
                controller.reset()
        self._active = name

    def _run_controller(self, name: str, setpoint: RateSetpoint,
                        frame: SensorFrame) -> tuple[np.ndarray, str]:
        controller = self.controllers.get(name)
        problem = "unknown controller" if controller is None else ""
        if controller is not None:
            try:
                pwm = controller.update(setpoint, frame, self.dt)
                # NaN fails both comparisons, so two reductions check finiteness and range.
                if pwm.shape == (4,) and PWM_MIN <= pwm.min() and pwm.max() <= PWM_MAX:
                    return pwm, name
                problem = ("output out of range" if pwm.shape == (4,) and np.isfinite(pwm).all()
                           else "non-finite output")
            except Exception as exc:  # a controller bug must not stop the motors mid-air
                problem = f"raised {type(exc).__name__}"
        self.faults[f"{name}: {problem}"] = self.faults.get(f"{name}: {problem}", 0) + 1
        if self.fallback and self.fallback != name and self.fallback in self.controllers:
            return self._run_controller(self.fallback, setpoint, frame)
        return DISARMED_PWM, "none"

    def run(self, duration_s: float | None = None, should_stop: Callable[[], bool] | None = None,
            on_slack: Callable[[int], None] | None = None) -> TimingStats:
        """Tick until `duration_s` of loop time has passed or `should_stop()` is true.

        `on_slack(remaining_us)` is called after a tick when time remains before the next
        deadline, for work that may wait (status lines); it must return quickly.
        """
        end_ticks = math.inf if duration_s is None else round(duration_s * 1e6 / self.period_us)
        clock, stats, period = self.clock, self.stats, self.period_us
        perf_us = _perf_us
        gc_was_enabled = gc.isenabled()
        gc.collect()
        gc.freeze()  # everything built so far is permanent: keep it out of later collections
        gc.disable()
        try:
            deadline = clock.now_us() + period
            n = 0
            while n < end_ticks and not (should_stop and should_stop()):
                woke = clock.wait_until(deadline)
                start = perf_us()
                self.tick(deadline)
                done = perf_us()
                plant = self.plant_ns // 1000
                stats.record(done - start - plant, woke - deadline if clock.realtime else 0, plant)
                n += 1
                deadline += period
                if clock.realtime:
                    now = clock.now_us()
                    if now > deadline:  # overran into the next slot: skip, never burst
                        missed = (now - deadline) // period + 1
                        stats.deadline_misses += missed
                        deadline += missed * period
                        self._hold_outputs(missed)
                    slack = deadline - now
                    if n % GC_EVERY_TICKS == 0 and slack > GC_SLACK_US:
                        gc.collect(0)
                        slack = deadline - clock.now_us()
                    if on_slack is not None and slack > GC_SLACK_US:
                        on_slack(slack)
                elif n % GC_EVERY_TICKS == 0:
                    gc.collect(0)
                    if on_slack is not None:
                        on_slack(0)
        finally:
            gc.unfreeze()
            if gc_was_enabled:
                gc.enable()
        return stats


def _perf_us() -> int:
    return time.perf_counter_ns() // 1000
