"""Fly controllers through the firmware loop on the ball-joint rig and record traces.

Every controller is flown exactly as firmware would fly it: `firmware.loop.FlightLoop`
ticking in lockstep against the twin, with the PID as fallback. The commands come from
the seed (`sim_bridge.tasks`), so controllers evaluated with the same seed see the same
ones. Trace sample k is tick k: the setpoint, the gyro rate the controller read, and the
PWM it wrote; sample 0 is the vehicle at rest.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from evaluation.traces import Traces
from firmware.controller import RateSetpoint
from firmware.controllers import load_controller
from firmware.loop import Command, FlightLoop, TickSample
from firmware.sensors import SensorFrame
from firmware.timing import LockstepClock
from sim_bridge.airframe import load_airframe
from sim_bridge.link import InProcessLink
from sim_bridge.tasks import continuous_schedule, episodic_commands
from sim_bridge.twin import Twin

FALLBACK = "pid"
TASKS = ("episodic", "continuous")


@dataclass(frozen=True)
class EvalConfig:
    task: str = "episodic"
    episodes: int = 1000
    seed: int = 0
    episode_s: float | None = None  # None: 1 s episodic, 10 s continuous
    throttle: float | None = None  # None: the airframe's hover throttle
    rate_hz: float = 1000.0
    airframe: str = "iris"  # sim_bridge/airframes/<name>.json or a path, e.g. iris_realistic

    def __post_init__(self) -> None:
        if self.task not in TASKS:
            raise ValueError(f"task must be one of {TASKS}, got {self.task!r}")
        if self.episodes < 1:
            raise ValueError("episodes must be >= 1")

    @property
    def duration_s(self) -> float:
        return self.episode_s or (1.0 if self.task == "episodic" else 10.0)

    @property
    def n_ticks(self) -> int:
        return round(self.duration_s * self.rate_hz)

    @property
    def hover_throttle(self) -> float:
        if self.throttle is not None:
            return self.throttle
        return (load_airframe(self.airframe).hover_pwm() - 1000) / 1000


def setpoint_schedules(cfg: EvalConfig) -> np.ndarray:
    """(episodes, ticks, 3) setpoints drawn from the seed alone."""
    if cfg.task == "episodic":
        commands = episodic_commands(cfg.seed, cfg.episodes)
        return np.broadcast_to(commands[:, None, :], (cfg.episodes, cfg.n_ticks, 3))
    seeds = np.random.SeedSequence(cfg.seed).spawn(cfg.episodes)
    return np.stack([continuous_schedule(np.random.default_rng(s), cfg.duration_s, 1.0 / cfg.rate_hz)
                     for s in seeds])


class _Schedule:
    """Commander for one episode: tick k flies setpoint k, armed throughout."""

    def __init__(self, setpoints: np.ndarray, throttle: float, period_us: int) -> None:
        self.commands = [Command(True, RateSetpoint(sp, throttle), "main") for sp in setpoints]
        self.period_us = period_us

    def command(self, t_us: int, frame: SensorFrame) -> Command:
        return self.commands[min(t_us // self.period_us, len(self.commands) - 1)]


class _Recorder:
    def __init__(self, rate: np.ndarray, pwm: np.ndarray) -> None:
        self.rate, self.pwm, self.k = rate, pwm, 0

    def publish(self, sample: TickSample) -> None:
        self.rate[self.k] = sample.frame.gyro
        self.pwm[self.k] = sample.pwm
        self.k += 1


def run_controller(spec: str, cfg: EvalConfig, progress: bool = True,
                   on_episode: Callable[[int], None] | None = None) -> Traces:
    """Fly `spec` (pid, pid:<preset>, FILE.onnx) over the evaluation set; return its traces."""
    controllers = {"main": load_controller(spec, cfg.rate_hz)}
    neural = not spec.startswith("pid")
    if neural:
        controllers[FALLBACK] = load_controller(FALLBACK)
    setpoints = setpoint_schedules(cfg)
    n, ticks = cfg.episodes, cfg.n_ticks
    rate, pwm = np.zeros((n, ticks, 3)), np.zeros((n, ticks, 4))
    twin = Twin(cfg.airframe, rig="rig", dt=1.0 / cfg.rate_hz)
    throttle = cfg.hover_throttle
    faults = 0
    bar = tqdm(range(n), desc=f"eval {spec}", unit="ep", disable=not progress, leave=False)
    for i in bar:
        commander = _Schedule(setpoints[i], throttle, round(1e6 / cfg.rate_hz))
        recorder = _Recorder(rate[i], pwm[i])
        loop = FlightLoop(InProcessLink(twin), twin.reset(), controllers, commander, LockstepClock(),
                          cfg.rate_hz, [recorder], fallback=FALLBACK if neural else None)
        for k in range(ticks):
            loop.tick(k * loop.period_us)
        faults += sum(loop.faults.values())
        if on_episode is not None:
            on_episode(i)
    t = np.arange(ticks) / cfg.rate_hz
    return Traces(t, np.array(setpoints), rate, pwm, controller=spec, seed=cfg.seed, task=cfg.task,
                  extra={"throttle": throttle, "controller_faults": faults, "rate_hz": cfg.rate_hz})
