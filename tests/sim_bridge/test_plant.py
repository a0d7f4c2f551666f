"""The plant's motor and sensor models: one vehicle and a batch agree to the bit; lag, noise as given."""

from __future__ import annotations

import numpy as np
import pytest

from fcemu.sim_bridge.airframe import load_airframe
from fcemu.sim_bridge.plant import MotorModel
from fcemu.sim_bridge.sensor_model import NoiseStreams, SensorModel, SensorNoise

MOTORS = MotorModel.from_spec(load_airframe("iris").motor, 0.001)
NOISE = SensorNoise(gyro_std=0.1, gyro_bias=(0.01, -0.02, 0.03), accel_std=0.5, accel_bias=(0.1, 0.0, -0.1),
                    rotor_speed_std=5.0)


def pwm_sequence(seed: int, steps: int, batch: int) -> np.ndarray:
    """Held random PWM, some of it outside [1000, 2000] µs, (steps, batch, 4)."""
    rng = np.random.default_rng(seed)
    pwm = rng.uniform(900.0, 2100.0, (steps // 20 + 1, batch, 4))
    pwm[rng.random(pwm.shape) < 0.3] = 2000.0
    return np.repeat(pwm, 20, axis=0)[:steps]


@pytest.mark.parametrize("seed", [0, 1])
def test_one_vehicle_in_floats_is_the_batch_to_the_bit(seed):
    pwm = pwm_sequence(seed, 300, 3)
    omega = np.random.default_rng(seed).uniform(0.0, MOTORS.max_rotor_speed, (3, 4))
    singles = [omega[i].tolist() for i in range(3)]
    for k in range(len(pwm)):
        omega, thrust = MOTORS.step(omega, pwm[k])
        for i in range(3):
            singles[i], single_thrust = MOTORS.step_one(singles[i], pwm[k, i].tolist())
            np.testing.assert_array_equal(singles[i], omega[i])
            np.testing.assert_array_equal(single_thrust, thrust[i])
            np.testing.assert_array_equal(MOTORS.thrust_one(singles[i]), thrust[i])


def test_float32_pwm_is_the_same_command():
    pwm = np.array([1234.5, 1999.75, 1000.25, 1500.0], dtype=np.float32)
    a = MOTORS.step(np.zeros(4), pwm)
    b = MOTORS.step(np.zeros(4), pwm.astype(np.float64))
    np.testing.assert_array_equal(a, b)
    assert a[0].dtype == np.float64


def test_lag_closes_the_gap_with_tau_up_and_tau_down():
    spec = load_airframe("iris").motor
    omega = np.zeros(4)
    for _ in range(20):
        omega, _ = MOTORS.step(omega, np.full(4, spec.pwm_max))
    np.testing.assert_allclose(omega / spec.max_rotor_speed, 1.0 - np.exp(-0.02 / spec.tau_up), rtol=1e-9)
    top = omega.copy()
    for _ in range(30):
        omega, thrust = MOTORS.step(omega, np.full(4, 500.0))  # below pwm_min: command 0
    np.testing.assert_allclose(omega / top, np.exp(-0.03 / spec.tau_down), rtol=1e-9)
    np.testing.assert_allclose(thrust, spec.kf * omega**2, rtol=1e-15)


def test_per_vehicle_thrust_coefficient():
    kf = np.array([[1.0], [2.0]]) * MOTORS.kf
    _, thrust = MOTORS.step(np.full((2, 4), 500.0), np.full((2, 4), 1700.0), kf)
    np.testing.assert_array_equal(thrust[1], 2.0 * thrust[0])
    assert MOTORS.max_thrust == MOTORS.kf * MOTORS.max_rotor_speed**2


def test_sensors_add_bias_and_scaled_draws_and_nothing_when_off():
    rng = np.random.default_rng(3)
    gyro, accel, rotor = rng.normal(size=3), rng.normal(size=3), rng.uniform(0, 800, 4)
    z = rng.normal(size=10)
    g, a, r = SensorModel(NOISE).read(gyro, accel, rotor, z)
    np.testing.assert_allclose(g, gyro + np.array(NOISE.gyro_bias) + 0.1 * z[0:3], rtol=1e-15)
    np.testing.assert_allclose(a, accel + np.array(NOISE.accel_bias) + 0.5 * z[3:6], rtol=1e-15)
    np.testing.assert_allclose(r, rotor + 5.0 * z[6:10], rtol=1e-15)
    off = SensorModel()
    assert not off.enabled and SensorModel(NOISE).enabled
    g, a, r = off.read(gyro, None, rotor, z)
    np.testing.assert_array_equal(g, gyro)
    np.testing.assert_array_equal(r, rotor)
    assert a is None
    batch = SensorModel(NOISE).read(np.tile(gyro, (2, 1)), None, np.tile(rotor, (2, 1)), np.tile(z, (2, 1)))
    np.testing.assert_array_equal(batch[0][1], SensorModel(NOISE).read(gyro, accel, rotor, z)[0])


def test_noise_streams_draw_what_one_generator_per_vehicle_draws_frame_by_frame():
    streams = NoiseStreams(3, SensorModel.DRAWS, block=8)
    seeds = [11, 12, 13]
    for i, s in enumerate(seeds):
        streams.reseed(i, s)
    reference = [np.random.default_rng(s) for s in seeds]
    idx_patterns = [np.arange(3), np.array([0, 2]), np.array([1])]
    for k in range(40):  # several refills of the 8-frame blocks, vehicles drawing at different paces
        idx = idx_patterns[k % 3]
        z = streams.next(idx)
        for row, i in enumerate(idx):
            expected = np.concatenate([reference[i].standard_normal(3), reference[i].standard_normal(3),
                                       reference[i].standard_normal(4)])  # as the twin once drew them
            np.testing.assert_array_equal(z[row], expected)
