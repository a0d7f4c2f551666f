from __future__ import annotations

import pytest

from fcemu.firmware.action import PWM_MIN, PWM_SPAN
from fcemu.sim_bridge.airframe import load_airframe


@pytest.mark.parametrize("mass", [1.0, 1.3])
def test_hover_throttle_holds_the_weight(mass: float) -> None:
    airframe = load_airframe("iris").scaled(mass=mass)
    throttle = airframe.hover_throttle()
    m = airframe.motor
    omega = (PWM_MIN + PWM_SPAN * throttle - m.pwm_min) / (m.pwm_max - m.pwm_min) * m.max_rotor_speed
    assert 4 * m.kf * omega**2 == pytest.approx(airframe.mass * 9.81, rel=1e-12)
    assert 0.0 < throttle < 1.0
