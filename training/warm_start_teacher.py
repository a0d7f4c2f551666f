"""The warm start's teacher: a PID preset flying every copy of the batched twin.

Kept apart from `training.warm_start` (torch) so the configuration can check a teacher
without importing torch.
"""

from __future__ import annotations

import numpy as np

from firmware.controllers import load_controller
from firmware.pid_controller import PIDRateController

PWM_MIN, PWM_SPAN = 1000.0, 1000.0


def check_teacher(spec: str) -> None:
    """A PID controller spec (pid, pid:paper, pid:FILE.json), else ValueError."""
    if not (spec == "pid" or spec.startswith("pid:")):
        raise ValueError(f"--warm-start {spec!r}: the teacher is a PID, pid or pid:<preset>")
    load_controller(spec)  # ControllerSpecError (a ValueError) for an unknown preset


def pid_action(pwm: np.ndarray) -> np.ndarray:
    """The ``throttle`` mapping's action that reproduces a mixer's PWM: u = t + ½(a − ā), so
    a = 2(u − ū), zero-mean (the mapping ignores a's mean), clipped to [-1, 1]."""
    u = (np.asarray(pwm, dtype=np.float64) - PWM_MIN) / PWM_SPAN
    return np.clip(2.0 * (u - u.mean(axis=-1, keepdims=True)), -1.0, 1.0)


class PidTeacher:
    """One PID per environment copy, fed each copy's setpoint and measured gyro."""

    def __init__(self, spec: str, n: int, dt: float) -> None:
        check_teacher(spec)
        self.ctrls: list[PIDRateController] = [load_controller(spec) for _ in range(n)]  # type: ignore[misc]
        for c in self.ctrls:
            c.pid.set_dt(dt)

    def reset(self, rows: np.ndarray) -> None:
        for i in np.flatnonzero(rows):
            self.ctrls[i].reset()

    def act(self, setpoint: np.ndarray, gyro: np.ndarray, throttle: np.ndarray) -> np.ndarray:
        # The controller's RatePID and QuadXMixer on plain floats: what `update` does at a
        # fixed period (the twin's), without a numpy round trip per copy.
        sp, gy, th = setpoint.tolist(), gyro.tolist(), throttle.tolist()
        pwm = [c.mixer.mix(c.pid.update(sp[i], gy[i], c.mixer.mix_range), th[i])
               for i, c in enumerate(self.ctrls)]
        return pid_action(np.array(pwm))


def teacher_inputs(batch, raw_obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Setpoint, measured gyro and collective of every copy of `batch` (a `BatchedRateEnv`),
    for the observation `raw_obs` it just returned: the gyro is decoded from the newest
    step's rate error, so the teacher reads the same noisy, delayed gyro the policy does."""
    setpoint = batch.current_setpoint
    cols = batch.obs_spec.layout[0][0]
    gyro = setpoint - raw_obs[:, cols].astype(np.float64) / batch.obs_spec.rate_scale
    return setpoint, gyro, batch.current_throttle
