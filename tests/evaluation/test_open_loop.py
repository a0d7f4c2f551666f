"""The open-loop near-optimum: its PWM makes the twin's motors run at the planned speeds."""

from __future__ import annotations

import numpy as np

from fcemu.evaluation.bound import rig_constants
from fcemu.evaluation.open_loop import fly, pwm_for_speeds
from fcemu.sim_bridge.twin import Twin


def test_pwm_for_speeds_inverts_the_motor_model():
    rng = np.random.default_rng(0)
    pwm = rng.uniform(1000.0, 2000.0, (200, 4))
    pwm[50:80] = 2000.0  # a saturated stretch
    pwm[120:140] = 1000.0
    twin = Twin("iris", "rig", None, 0.001)
    twin.reset()
    speeds = []
    for p in pwm:
        twin.step(p)
        speeds.append(twin.rotor_speed)
    np.testing.assert_allclose(pwm_for_speeds(rig_constants(), np.array(speeds)), pwm, atol=1e-9)


def test_fly_records_the_samples_the_evaluator_does():
    pwm = np.tile([2000.0, 1000.0, 2000.0, 1000.0], (40, 1))
    rates = fly(pwm)
    assert rates.shape == (40, 3)
    np.testing.assert_array_equal(rates[:2], 0.0)  # samples 0 and 1 are at rest (the gyro lags a step)
    assert np.abs(rates[-1]).max() > 0.1
