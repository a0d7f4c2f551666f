"""Fly controllers through the firmware loop on the ball-joint rig and record traces.

Every controller is flown exactly as firmware would fly it: `firmware.loop.FlightLoop`
ticking in lockstep against the twin, with the PID as fallback. The commands come from
the seed (`sim_bridge.tasks`), so controllers evaluated with the same seed see the same
ones. Trace sample k is tick k: the setpoint, the body rate (the gyro's reading without
vibration, noise or delay: what the vehicle did, which the metrics judge) and the PWM
written; sample 0 is the vehicle at rest. In the inflight task the episode starts at
steady hover (rotors at the speed the throttle commands, rates zero, level) and flies
`INFLIGHT_WARMUP_S` of zero rate before the command, so the controller's own state
(integrator, filters, observation history) is warm; those samples have t < 0 and the
metrics start at the step, t = 0.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from fcemu.firmware.controller import RateController, RateSetpoint
from fcemu.firmware.controllers import FALLBACK_CONTROLLER as FALLBACK
from fcemu.firmware.controllers import load_controller, resolve
from fcemu.firmware.health import HealthMonitor, HealthRules
from fcemu.firmware.loop import Command, FlightLoop, TickSample
from fcemu.firmware.sensors import SensorFrame
from fcemu.firmware.timing import LockstepClock
from fcemu.sim_bridge.airframe import Airframe, load_airframe
from fcemu.sim_bridge.env_config import DEFAULT_AIRFRAME
from fcemu.sim_bridge.link import InProcessLink
from fcemu.sim_bridge.tasks import EVAL_TASKS, INFLIGHT_WARMUP_S, continuous_schedule, episodic_commands
from fcemu.sim_bridge.twin import Twin, hover_state
from fcemu.sitl.traces import Traces

if TYPE_CHECKING:
    from fcemu.evaluation.faults import FaultPlan

TASKS = EVAL_TASKS
NOISE_STREAM = 0x6e6f6973  # "nois": the twin's sensor-noise seeds, a stream apart from the commands'


@dataclass(frozen=True)
class EvalConfig:
    task: str = "episodic"
    episodes: int = 1000
    seed: int = 0
    episode_s: float | None = None  # None: 1 s episodic, 10 s continuous
    throttle: float | None = None  # None: the airframe's hover throttle
    rate_hz: float = 1000.0
    airframe: str = DEFAULT_AIRFRAME  # sim_bridge/airframes/<name>.json or a path, e.g. iris_realistic
    # The airframe the twin flies where it is not the one the firmware is set up for (`airframe`): the
    # true quad behind an identified file, which a policy fitted on that file is flown on.
    twin: str | None = None
    fallback: str = FALLBACK  # the PID a policy hands over to: by default the airframe's own tune

    def __post_init__(self) -> None:
        if self.task not in TASKS:
            raise ValueError(f"task must be one of {TASKS}, got {self.task!r}")
        if self.episodes < 1:
            raise ValueError("episodes must be >= 1")

    @property
    def duration_s(self) -> float:
        """Seconds evaluated per episode (after the warm-up in the inflight task)."""
        return self.episode_s or (10.0 if self.task == "continuous" else 1.0)

    @property
    def n_ticks(self) -> int:
        return round(self.duration_s * self.rate_hz)

    @property
    def warmup_ticks(self) -> int:
        return round(INFLIGHT_WARMUP_S * self.rate_hz) if self.task == "inflight" else 0

    @property
    def hover_throttle(self) -> float:
        return self.throttle_for(load_airframe(self.airframe))

    def throttle_for(self, airframe: Airframe) -> float:
        """The collective flown: `throttle`, or the airframe's hover throttle."""
        return self.throttle if self.throttle is not None else airframe.hover_throttle()


def sensor_noise_seeds(cfg: EvalConfig) -> np.ndarray:
    """Per episode, the seed of the twin's sensor noise (an airframe with gyro noise draws it)."""
    return np.random.SeedSequence(cfg.seed, spawn_key=(NOISE_STREAM,)).generate_state(cfg.episodes, np.uint64)


def setpoint_schedules(cfg: EvalConfig) -> np.ndarray:
    """(episodes, warm-up + ticks, 3) setpoints drawn from the seed alone."""
    if cfg.task == "episodic":
        commands = episodic_commands(cfg.seed, cfg.episodes)
        return np.broadcast_to(commands[:, None, :], (cfg.episodes, cfg.n_ticks, 3))
    if cfg.task == "inflight":
        commands = episodic_commands(cfg.seed, cfg.episodes)
        out = np.zeros((cfg.episodes, cfg.warmup_ticks + cfg.n_ticks, 3))
        out[:, cfg.warmup_ticks:] = commands[:, None, :]
        return out
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


class TraceRecorder:
    """Telemetry sink writing tick k's rate and PWM into row k of the given arrays.

    The rate is the gyro reading the controller used, unless `clean` is given: a callable
    returning the body rate of the frame the plant has just produced (e.g. `Twin.clean_gyro`),
    which on an airframe with gyro noise, vibration or delay is what the metrics should
    judge. A sample publishes tick k after the plant has stepped to tick k + 1, so the clean
    rate goes into row k + 1; `start` fills row 0 from the reset frame.
    """

    def __init__(self, rate: np.ndarray, pwm: np.ndarray,
                 clean: Callable[[], np.ndarray] | None = None) -> None:
        self.rate, self.pwm, self.k, self.clean = rate, pwm, 0, clean

    def start(self) -> None:
        if self.clean is not None:
            self.rate[0] = self.clean()

    def publish(self, sample: TickSample) -> None:
        k = self.k
        if self.clean is None:
            self.rate[k] = sample.frame.gyro
        elif k + 1 < len(self.rate):
            self.rate[k + 1] = self.clean()
        self.pwm[k] = sample.pwm
        self.k = k + 1


def run_controller(spec: str, cfg: EvalConfig, progress: bool = True,
                   on_episode: Callable[[int], None] | None = None,
                   airframe: Airframe | None = None, faults: FaultPlan | None = None,
                   controller: RateController | None = None) -> Traces:
    """Fly `spec` (default, pid, pid:<preset>, FILE.onnx) over the evaluation set; return its traces.

    `airframe` replaces the nominal Iris (e.g. a perturbed one) for the firmware and the twin alike;
    `cfg.twin`, for the twin alone. The twin's hover throttle is flown unless `cfg.throttle` is set.
    `faults` injects its faults into the twin at its tick of each episode and records what the
    firmware's health monitor made of them. `controller` flies instead of the one `spec` names
    (which then only names it), with no fallback: a model-based teacher.
    """
    from fcemu.sim_bridge.airframe_spec import airframe_spec

    configured = airframe_spec(airframe or cfg.airframe)  # what the firmware is set up for
    spec = resolve(spec, configured)  # `default`: what the firmware flies on this airframe
    controllers = {"main": controller or load_controller(spec, cfg.rate_hz, configured)}
    neural = controller is None and not spec.startswith("pid")
    if neural:
        controllers[FALLBACK] = load_controller(cfg.fallback, airframe=configured)
    setpoints = setpoint_schedules(cfg)
    n, ticks = cfg.episodes, cfg.warmup_ticks + cfg.n_ticks
    rate, pwm = np.zeros((n, ticks, 3)), np.zeros((n, ticks, 4))
    twin = Twin(airframe or cfg.twin or cfg.airframe, rig="rig", dt=1.0 / cfg.rate_hz)
    throttle = cfg.throttle_for(twin.airframe)
    start = hover_state(twin.airframe, throttle) if cfg.task == "inflight" else None
    noise_seeds = sensor_noise_seeds(cfg)
    n_faults = 0
    bar = tqdm(range(n), desc=f"eval {spec}", unit="ep", disable=not progress, leave=False)
    for i in bar:
        commander = _Schedule(setpoints[i], throttle, round(1e6 / cfg.rate_hz))
        recorder = TraceRecorder(rate[i], pwm[i], twin.clean_gyro)
        first = twin.reset(int(noise_seeds[i]), start)
        recorder.start()
        loop = FlightLoop(InProcessLink(twin), first, controllers, commander, LockstepClock(), cfg.rate_hz,
                          [recorder], fallback=FALLBACK if neural else None,
                          health=HealthMonitor(HealthRules.for_airframe(configured), dt=1.0 / cfg.rate_hz))
        at = -1 if faults is None else faults.ticks[i]
        for k in range(ticks):
            if k == at:
                twin.faults = faults.injector(i, twin)
            loop.tick(k * loop.period_us)
        if faults is not None:
            faults.record(i, at, loop.health)
            twin.faults = None
        n_faults += sum(loop.faults.values())
        if on_episode is not None:
            on_episode(i)
    t = (np.arange(ticks) - cfg.warmup_ticks) / cfg.rate_hz
    extra = {"throttle": throttle, "controller_faults": n_faults, "rate_hz": cfg.rate_hz}
    if start is not None:
        extra["initial_rotor_speed"] = list(start.rotor_speed)
    return Traces(t, np.array(setpoints), rate, pwm, controller=spec, seed=cfg.seed, task=cfg.task,
                  extra=extra)
