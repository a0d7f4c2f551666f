"""The envelope a policy records: its JSON, what lies outside it and how that is said."""

from __future__ import annotations

from dataclasses import replace

import pytest

from fcemu.firmware.airframe_spec import ENVELOPE_SLACK, AirframeSpec, Envelope

SPEC = AirframeSpec(name="quad", max_rotor_speed=1000.0, pwm_min=1000.0, pwm_max=2000.0, motor_poles=14,
                    hover_throttle=0.6, thrust_to_weight=2.0, max_angular_acceleration=(200.0, 100.0, 40.0),
                    motor_tau_up=0.01, motor_tau_down=0.02)


def test_an_envelope_round_trips_through_its_json() -> None:
    other = replace(SPEC, thrust_to_weight=2.5, max_angular_acceleration=(250.0, 90.0, 40.0))
    env = Envelope.around([SPEC, other])
    assert env.ranges["thrust_to_weight"] == (2.0, 2.5)
    assert env.ranges["max_angular_acceleration"] == ((200.0, 250.0), (90.0, 100.0), (40.0, 40.0))
    assert Envelope.from_json(env.to_json()) == env


def test_a_margin_widens_every_range() -> None:
    env = Envelope.around([SPEC]).widened(0.25)
    assert env.ranges["max_rotor_speed"] == (750.0, 1250.0)
    assert env.ranges["max_angular_acceleration"][2] == (30.0, 50.0)


def test_what_lies_outside_is_named_with_its_value() -> None:
    env = Envelope.around([SPEC]).widened(0.25)
    assert env.outside(SPEC) == []
    assert env.outside(replace(SPEC, max_rotor_speed=1250.0 * (1 + ENVELOPE_SLACK / 2))) == []
    assert env.outside(replace(SPEC, max_rotor_speed=2600.0)) == ["top rotor speed 2,600 rad/s"]
    far = replace(SPEC, max_angular_acceleration=(900.0, 100.0, 900.0), motor_tau_up=0.05)
    assert env.outside(far) == ["roll/yaw top angular acceleration 900/900 rad/s²",
                                "motor spin-up time constant 0.05 s"]
    assert env.describe() == "thrust-to-weight 1.5–2.5, top rotor speed 750–1,250 rad/s"
    assert Envelope.around([SPEC]).describe() == "thrust-to-weight 2, top rotor speed 1,000 rad/s"


@pytest.mark.parametrize("text", ["wide", "[1, 2]", "{}", '{"mass": [1, 2]}', '{"max_rotor_speed": [2, 1]}',
                                  '{"max_rotor_speed": [NaN, 1]}', '{"max_rotor_speed": [true, 1]}',
                                  '{"max_angular_acceleration": [[1, 2]]}', '{"hover_throttle": [-1, 1]}'])
def test_an_envelope_that_is_not_one_is_refused(text: str) -> None:
    with pytest.raises(ValueError):
        Envelope.from_json(text)
