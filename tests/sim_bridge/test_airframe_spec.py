"""What the firmware is told of an airframe file, and the envelope of a randomisation."""

from __future__ import annotations

import numpy as np
import pytest

from fcemu.sim_bridge.airframe import load_airframe
from fcemu.sim_bridge.airframe_spec import airframe_spec, envelope
from fcemu.sim_bridge.randomization import load_randomization


@pytest.mark.parametrize("name", ["iris", "crazyflie", "x500", "racer5"])
def test_the_spec_is_the_airframe_file_s(name: str) -> None:
    af, spec = load_airframe(name), airframe_spec(name)
    assert spec.name == af.name and spec.max_rotor_speed == af.motor.max_rotor_speed
    m = af.motor
    assert (spec.pwm_min, spec.pwm_max, spec.motor_poles) == (m.pwm_min, m.pwm_max, m.poles)
    assert spec.hover_throttle == af.hover_throttle() and spec.thrust_to_weight == af.thrust_to_weight()
    assert spec.max_angular_acceleration == tuple(af.max_angular_acceleration())
    assert (spec.motor_tau_up, spec.motor_tau_down) == (af.motor.tau_up, af.motor.tau_down)


@pytest.mark.parametrize("ranges", ["iris", "iris_esc2"])
def test_every_draw_of_a_randomisation_lies_inside_its_envelope_without_slack(ranges: str) -> None:
    randomization = load_randomization(ranges)
    base = randomization.base_airframe()
    env = envelope(base, randomization)
    rng = np.random.default_rng(0)
    for _ in range(300):
        spec = airframe_spec(base.scaled(**randomization.draw(rng)))
        for key, r in env.ranges.items():
            value = spec.scale(key)
            for v, (lo, hi) in zip(np.atleast_1d(value), r if isinstance(r[0], tuple) else [r], strict=True):
                assert lo <= v <= hi, (key, v, lo, hi)


def test_without_a_randomisation_the_envelope_is_the_airframe_within_a_margin() -> None:
    env, spec = envelope("x500"), airframe_spec("x500")
    assert env.ranges["max_rotor_speed"] == (spec.max_rotor_speed * 0.75, spec.max_rotor_speed * 1.25)
    assert env.outside(spec) == []
    assert env.outside(airframe_spec("crazyflie"))
