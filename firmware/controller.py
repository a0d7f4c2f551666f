"""What every rate controller looks like to the loop."""

from __future__ import annotations

from typing import NamedTuple, Protocol

import numpy as np

from fcemu.firmware.sensors import SensorFrame

PWM_MIN = 1000.0
PWM_MAX = 2000.0


class RateSetpoint(NamedTuple):
    """Body rates FRD in rad/s and collective thrust 0..1, as an outer loop sends them."""

    rates: np.ndarray
    throttle: float


class RateController(Protocol):
    """A controller turns sensors and a setpoint into four PWM values (µs, motor order).

    `update` is called once per tick with the tick's period `dt` in seconds; it must
    return finite PWM in [1000, 2000]. The loop sends 1000 itself while disarmed and
    calls `reset` on arming, so the controller never sees disarmed ticks. A controller that
    can start in flight without a bump also has `take_over(setpoint, frame)`, which the loop
    calls instead of `reset` when it switches to it mid-flight (the PID: firmware/pid.py).
    """

    name: str

    def reset(self) -> None: ...

    def update(self, setpoint: RateSetpoint, frame: SensorFrame, dt: float) -> np.ndarray: ...
