"""The warm start's teacher: a PID preset flying every copy of the batched twin.

Kept apart from `training.warm_start` (torch) so the configuration can check a teacher
without importing torch.
"""

from __future__ import annotations

import numpy as np

from firmware.action import pwm_to_action
from firmware.controllers import load_controller
from firmware.pid_controller import PIDRateController


def check_teacher(spec: str) -> None:
    """A PID controller spec (pid, pid:paper, pid:FILE.json), else ValueError."""
    if not (spec == "pid" or spec.startswith("pid:")):
        raise ValueError(f"--warm-start {spec!r}: the teacher is a PID, pid or pid:<preset>")
    load_controller(spec)  # ControllerSpecError (a ValueError) for an unknown preset


def _pid(spec: str, dt: float) -> PIDRateController:
    ctrl = load_controller(spec)
    assert isinstance(ctrl, PIDRateController)  # check_teacher admits PID specs only
    ctrl.pid.set_dt(dt)
    return ctrl


class PidTeacher:
    """One PID per environment copy, fed each copy's setpoint and measured gyro; its PWM
    is labelled as the policy's action under `action_mapping`."""

    def __init__(self, spec: str, n: int, dt: float, action_mapping: str = "throttle") -> None:
        check_teacher(spec)
        self.ctrls = [_pid(spec, dt) for _ in range(n)]
        self.action_mapping = action_mapping

    def reset(self, rows: np.ndarray) -> None:
        for i in np.flatnonzero(rows):
            self.ctrls[i].reset()

    def act(self, setpoint: np.ndarray, gyro: np.ndarray, throttle: np.ndarray) -> np.ndarray:
        # The controller's RatePID and QuadXMixer on plain floats: what `update` does at a
        # fixed period (the twin's), without a numpy round trip per copy.
        sp, gy, th = setpoint.tolist(), gyro.tolist(), throttle.tolist()
        pwm = [c.mixer.mix(c.pid.update(sp[i], gy[i], c.mixer.mix_range), th[i])
               for i, c in enumerate(self.ctrls)]
        return pwm_to_action(self.action_mapping, np.array(pwm))


def teacher_inputs(batch, raw_obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Setpoint, measured gyro and collective of every copy of `batch` (a `BatchedRateEnv`),
    for the observation `raw_obs` it just returned: the gyro is decoded from the newest
    step's rate error, so the teacher reads the same noisy, delayed gyro the policy does."""
    setpoint = batch.current_setpoint
    cols = next(c for c, d, _ in batch.obs_spec.layout if d.source == "rate_error" and not d.integrated)
    gyro = setpoint - raw_obs[:, cols].astype(np.float64) / batch.obs_spec.rate_scale
    return setpoint, gyro, batch.current_throttle
