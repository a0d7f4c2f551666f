"""The warm start's teacher: a PID preset flying every copy of the batched twin.

Kept apart from `training.warm_start` (torch) so the configuration can check a teacher
without importing torch.

A teacher is one PID preset (`pid`, `pid:<preset>`), or a schedule of presets by the
episode airframe's latency (`schedule:<name|file>`, a file in `training/teachers/`). A
schedule is a privileged teacher: it knows each drawn airframe's ESC + gyro delay, which
the firmware cannot, and flies the preset tuned for it (e.g. lower roll and pitch gains
when a long loop delay would make the nominal gains ring). The network it teaches sees
only its observation history, so it must learn to tell the airframes apart from how the
rates answer its commands.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fcemu.firmware.action import pwm_to_action
from fcemu.firmware.controllers import load_controller
from fcemu.firmware.pid_controller import PIDRateController

TEACHER_DIR = Path(__file__).with_name("teachers")
SCHEDULE = "schedule:"


@dataclass(frozen=True)
class TeacherSchedule:
    """PID presets by the airframe's loop delay (ESC + gyro, whole ticks): band k's
    controller flies delays from `from_ticks[k]` up to the next band's."""

    from_ticks: tuple[int, ...]
    controllers: tuple[str, ...]
    name: str = ""

    def __post_init__(self) -> None:
        if not self.controllers or len(self.from_ticks) != len(self.controllers):
            raise ValueError(f"teacher schedule {self.name!r}: one controller per band, at least one band")
        if self.from_ticks[0] != 0 or list(self.from_ticks) != sorted(set(self.from_ticks)):
            raise ValueError(f"teacher schedule {self.name!r}: bands must start at 0 ticks and rise, "
                             f"got {list(self.from_ticks)}")
        for c in self.controllers:
            _check_pid(c)

    def band(self, delay_ticks: int) -> int:
        return int(np.searchsorted(self.from_ticks, delay_ticks, side="right")) - 1


def _check_pid(spec: str) -> None:
    if not (spec == "pid" or spec.startswith("pid:")):
        raise ValueError(f"--warm-start {spec!r}: the teacher is a PID, pid or pid:<preset>, "
                         f"or {SCHEDULE}<name|file>")
    load_controller(spec)  # ControllerSpecError (a ValueError) for an unknown preset


def load_schedule(spec: str) -> TeacherSchedule:
    """A teacher spec as a schedule: one preset is a schedule of one band."""
    if not spec.startswith(SCHEDULE):
        _check_pid(spec)
        return TeacherSchedule((0,), (spec,), spec)
    name = spec[len(SCHEDULE):]
    path = Path(name) if Path(name).suffix else TEACHER_DIR / f"{name}.json"
    try:
        raw = json.loads(path.read_text(encoding="utf-8"))
        bands = raw["bands"]
        return TeacherSchedule(tuple(int(b["from_delay_ticks"]) for b in bands),
                               tuple(str(b["controller"]) for b in bands), name)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as exc:
        known = ", ".join(sorted(p.stem for p in TEACHER_DIR.glob("*.json")))
        raise ValueError(f"--warm-start {spec!r}: cannot read a teacher schedule from {path} "
                         f"({type(exc).__name__}: {exc}); shipped: {known}") from None


def check_teacher(spec: str) -> None:
    """A PID controller spec (pid, pid:paper, pid:FILE.json) or a schedule of them, else ValueError."""
    load_schedule(spec)


def _pid(spec: str, dt: float) -> PIDRateController:
    ctrl = load_controller(spec)
    assert isinstance(ctrl, PIDRateController)  # check_teacher admits PID specs only
    ctrl.pid.set_dt(dt)
    return ctrl


class PidTeacher:
    """One PID per environment copy, fed each copy's setpoint and measured gyro; its PWM
    is labelled as the policy's action under `action_mapping`. With a schedule, each
    copy's PID is the band's for the episode's airframe (`reset`'s `delay_ticks`)."""

    def __init__(self, spec: str, n: int, dt: float, action_mapping: str = "throttle") -> None:
        self.schedule = load_schedule(spec)
        self._bands = [[_pid(c, dt) for _ in range(n)] for c in self.schedule.controllers]
        self.ctrls = list(self._bands[0])
        self.action_mapping = action_mapping

    def reset(self, rows: np.ndarray, delay_ticks: np.ndarray | None = None) -> None:
        """Reset the copies in the mask `rows` for a new episode; `delay_ticks` (n,): each
        copy's airframe loop delay, needed by a schedule of more than one band."""
        if delay_ticks is None and len(self._bands) > 1:
            raise ValueError("a scheduled teacher needs each episode's delay_ticks")
        for i in np.flatnonzero(rows):
            band = 0 if delay_ticks is None else self.schedule.band(int(delay_ticks[i]))
            self.ctrls[i] = self._bands[band][i]
            self.ctrls[i].reset()

    def act(self, setpoint: np.ndarray, gyro: np.ndarray, throttle: np.ndarray) -> np.ndarray:
        # The controller's RatePID and QuadXMixer on plain floats: what `update` does at a
        # fixed period (the twin's), without a numpy round trip per copy.
        sp, gy, th = setpoint.tolist(), gyro.tolist(), throttle.tolist()
        pwm = [c.mixer.mix(c.pid.update(sp[i], gy[i], c.mixer.mix_range), th[i])
               for i, c in enumerate(self.ctrls)]
        return pwm_to_action(self.action_mapping, np.array(pwm))


def episode_delay_ticks(batch) -> np.ndarray:
    """Each copy's loop delay (ESC + gyro ticks) for its current episode of `batch` (a
    `BatchedRateEnv`): the drawn airframe's, else the base airframe's."""
    base = batch.config.base_airframe
    return np.array([f.get("esc_delay_ticks", base.esc_delay_ticks)
                     + f.get("gyro_delay_ticks", base.gyro_delay_ticks) for f in batch.episode_factors])


def teacher_inputs(batch, raw_obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Setpoint, measured gyro and collective of every copy of `batch` (a `BatchedRateEnv`),
    for the observation `raw_obs` it just returned: the gyro is decoded from the newest
    step's rate error, so the teacher reads the same noisy, delayed gyro the policy does."""
    setpoint = batch.current_setpoint
    cols = next(c for c, d, _ in batch.obs_spec.layout if d.source == "rate_error" and not d.integrated)
    gyro = setpoint - raw_obs[:, cols].astype(np.float64) / batch.obs_spec.rate_scale
    return setpoint, gyro, batch.current_throttle
