from functools import partial

import numpy as np
import onnx
import pytest

from fcemu.firmware.controllers import DEFAULT_POLICY
from fcemu.firmware.neural import META_PREFIX
from fcemu.firmware.observation import (
    AUTHORITY,
    FIELD_DEFS,
    FIELDS,
    INTEGRAL,
    LOOP_DELAY,
    MOTOR_OUTPUT,
    RATE,
    RATE_ERROR,
    RMS,
    ROTOR_SPEED,
    SOURCE_COLUMNS,
    ObservationHistory,
    ObservationSpec,
    observe_step,
)

TOP = 1100.0  # rad/s: the top rotor speed the tests' observations are scaled for
Spec = partial(ObservationSpec, max_rotor_speed=TOP)


def test_the_shipped_policys_spec_round_trips_exactly():
    props = {p.key: p.value for p in onnx.load(str(DEFAULT_POLICY), load_external_data=False).metadata_props}
    meta = props[META_PREFIX + "observation"]
    assert ObservationSpec.from_json(meta).to_json() == meta
    assert "integral_leak" not in Spec().to_json()
    assert "rms_leak" not in Spec().to_json()


def test_integral_spec_round_trips_and_sizes():
    spec = Spec(memory=2, fields=(*FIELDS, INTEGRAL), integral_leak=0.99)
    assert ObservationSpec.from_json(spec.to_json()) == spec
    assert spec.step_size == 10 and spec.size == 20
    assert spec.integrators == ((slice(7, 10), 0.99, False),)
    assert "rms_leak" not in spec.to_json()
    with pytest.raises(ValueError, match="integral_leak"):
        Spec(fields=(*FIELDS, INTEGRAL), integral_leak=1.0)
    with pytest.raises(ValueError, match="repeated"):
        Spec(fields=(*FIELDS, INTEGRAL, INTEGRAL))


def test_batched_history_integrates_per_row_and_masked_reset_keeps_other_rows():
    spec = Spec(fields=(INTEGRAL, "rate_error"), integral_leak=0.5)
    hist = ObservationHistory(spec, (2,))
    rotor = np.zeros((2, 4))

    def step(err: float) -> np.ndarray:
        return observe_step(spec, np.full((2, 3), err / spec.rate_scale), np.zeros((2, 3)), rotor)

    obs = hist.reset(step(1.0))
    np.testing.assert_allclose(obs[:, :3], 0.5)  # I_0 = (1 − λ)·e_0
    obs = hist.push(step(1.0))
    np.testing.assert_allclose(obs[:, :3], 0.75)
    np.testing.assert_allclose(obs[:, 3:], 1.0)  # the plain error is untouched
    obs = hist.reset(step(-1.0), np.array([False, True]))
    np.testing.assert_allclose(obs[0, :3], 0.75)
    np.testing.assert_allclose(obs[1, :3], -0.5)
    obs = hist.push(step(0.0))
    np.testing.assert_allclose(obs[:, 0], [0.375, -0.25])


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_step_is_the_scaled_sources_rounded_to_float32_in_the_inputs_precision(dtype):
    spec = Spec(fields=(INTEGRAL, "rotor_speed", "rate_error"))
    rng = np.random.default_rng(2)
    setpoint, gyro = rng.uniform(-9, 9, (2, 500, 3)).astype(dtype)
    rotor = rng.uniform(0, 1200, (500, 4)).astype(dtype)
    error = (setpoint - gyro) * spec.rate_scale
    expected = np.concatenate([error, rotor * spec.rotor_speed_scale, error], axis=-1).astype(np.float32)
    assert np.array_equal(observe_step(spec, setpoint, gyro, rotor), expected)
    out = np.zeros((1, spec.step_size), dtype=np.float32)
    for i in range(500):  # one vehicle into a preallocated batch of one, as flight does
        observe_step(spec, setpoint[i], gyro[i], rotor[i], out=out)
        assert np.array_equal(out[0], expected[i])


def test_history_keeps_the_newest_first_and_reset_fills_it():
    spec = Spec(memory=3)
    hist = ObservationHistory(spec, (1,))
    steps = [np.full((1, spec.step_size), k, dtype=np.float32) for k in range(4)]
    assert np.array_equal(hist.reset(steps[0]), np.zeros((1, spec.size)))
    hist.record(steps[1])
    obs = hist.push(steps[2])
    np.testing.assert_array_equal(obs.reshape(3, -1)[:, 0], [2, 1, 0])
    obs[:] = 9  # a copy: the history is untouched
    np.testing.assert_array_equal(hist.view.reshape(3, -1)[:, 0], [2, 1, 0])
    hist.start(steps[3])
    np.testing.assert_array_equal(hist.view, 3)


def test_the_field_table_flattens_to_one_source_column_and_scale_per_observation_column():
    spec = Spec(fields=("rotor_speed", "rate_error", INTEGRAL))
    assert spec.column_sources == (3, 4, 5, 6, 0, 1, 2, 0, 1, 2)
    assert spec.column_scales == (spec.rotor_speed_scale,) * 4 + (spec.rate_scale,) * 6
    assert spec.step_size == 10 and spec.integrators[0][0] == slice(7, 10)


def test_each_fields_columns_by_name_hold_its_source_scaled():
    spec = Spec(memory=2, fields=(MOTOR_OUTPUT, RATE, ROTOR_SPEED, RATE_ERROR))
    assert spec.columns == {MOTOR_OUTPUT: slice(0, 4), RATE: slice(4, 7), ROTOR_SPEED: slice(7, 11),
                            RATE_ERROR: slice(11, 14)}
    for name, cols in spec.columns.items():
        assert spec.column_sources[cols] == SOURCE_COLUMNS[FIELD_DEFS[name].source], name
    rng = np.random.default_rng(5)
    setpoint, gyro, rotor = rng.normal(size=3), rng.normal(size=3), rng.uniform(0, TOP, 4)
    step = observe_step(spec, setpoint, gyro, rotor)
    np.testing.assert_allclose(step[spec.columns[RATE_ERROR]], (setpoint - gyro) * spec.rate_scale, rtol=1e-6)
    np.testing.assert_allclose(step[spec.columns[RATE]], gyro * spec.rate_scale, rtol=1e-6)
    np.testing.assert_allclose(step[spec.columns[ROTOR_SPEED]], rotor * spec.rotor_speed_scale, rtol=1e-6)


def test_rms_spec_round_trips_and_refuses_a_leak_out_of_range():
    spec = Spec(memory=2, fields=(*FIELDS, INTEGRAL, RMS), integral_leak=0.99, rms_leak=0.9)
    assert ObservationSpec.from_json(spec.to_json()) == spec
    assert spec.step_size == 13 and spec.size == 26
    assert spec.integrators == ((slice(7, 10), 0.99, False), (slice(10, 13), 0.9, True))
    assert "integral_leak" not in Spec(fields=(*FIELDS, RMS)).to_json()
    with pytest.raises(ValueError, match="rms_leak"):
        Spec(fields=(*FIELDS, RMS), rms_leak=-0.1)


def test_rms_is_the_root_of_the_leaky_mean_square_and_sees_an_oscillation_the_integral_does_not():
    mu = 0.9
    spec = Spec(fields=(RMS, INTEGRAL, "rate_error"), rms_leak=mu, integral_leak=mu)
    hist = ObservationHistory(spec, (2,))
    rotor = np.zeros((2, 4))

    def step(err: np.ndarray) -> np.ndarray:
        return observe_step(spec, np.stack([err / spec.rate_scale] * 3, axis=-1), np.zeros((2, 3)), rotor)

    # row 0 oscillates ±0.5 every tick, row 1 holds 0.5: the same RMS, opposite integrals
    errors = [np.array([0.5 * (-1) ** k, 0.5]) for k in range(200)]
    obs = hist.reset(step(errors[0]))
    np.testing.assert_allclose(obs[:, 0], np.sqrt(1 - mu) * 0.5, rtol=1e-6)  # P_0 = (1 − μ)·e_0²
    mean_square = (1 - mu) * 0.25
    for err in errors[1:]:
        obs = hist.push(step(err))
        mean_square = mu * mean_square + (1 - mu) * 0.25
    np.testing.assert_allclose(obs[:, 0], np.sqrt(mean_square), rtol=1e-5)
    assert obs[0, 0] > 0.49 and abs(obs[0, 3]) < 0.03 and obs[1, 3] > 0.49  # RMS ≈ 0.5 both; I ≈ 0 vs 0.5
    np.testing.assert_allclose(obs[:, 6], [0.5 * (-1) ** 199, 0.5])
    obs = hist.reset(step(np.array([0.0, 2.0])), np.array([False, True]))  # row 0 keeps its state
    assert obs[0, 0] > 0.49
    np.testing.assert_allclose(obs[1, 0], np.sqrt(1 - mu) * 2.0, rtol=1e-6)


def test_motor_output_is_the_previous_output_and_at_a_start_the_rotors_steady_state_command():
    spec = Spec(fields=(*FIELDS, MOTOR_OUTPUT))
    assert spec.step_size == 11 and spec.reads_motor_output and not Spec().reads_motor_output
    assert ObservationSpec.from_json(spec.to_json()) == spec
    rng = np.random.default_rng(5)
    setpoint, gyro = rng.uniform(-9, 9, (2, 200, 3))
    rotor = rng.uniform(0, 1300, (200, 4))  # beyond the Iris' 1100 rad/s: the start's u clips at 1
    u = rng.uniform(0, 1, (200, 4))
    given = observe_step(spec, setpoint, gyro, rotor, motor_output=u)
    np.testing.assert_array_equal(given[:, 7:], u.astype(np.float32))
    start = observe_step(spec, setpoint, gyro, rotor)
    np.testing.assert_array_equal(start[:, 7:], np.clip(rotor / 1100.0, 0, 1).astype(np.float32))
    assert start[:, 7:].max() == 1.0 and start[:, 7:].min() >= 0.0
    out = np.zeros((1, spec.step_size), dtype=np.float32)
    for i in range(200):  # one float64 vehicle takes the plain-float path: the same values
        observe_step(spec, setpoint[i], gyro[i], rotor[i], out=out, motor_output=u[i])
        assert np.array_equal(out[0], given[i])
        observe_step(spec, setpoint[i], gyro[i], rotor[i], out=out)
        assert np.array_equal(out[0], start[i])


def test_loop_delay_is_the_configured_ticks_scaled_in_every_row_and_both_paths():
    """Without motor_output before it, the plain-float path still finds the delay's source column."""
    spec = Spec(memory=2, fields=(*FIELDS, LOOP_DELAY))
    assert spec.step_size == 8 and spec.reads_loop_delay and not Spec().reads_loop_delay
    assert ObservationSpec.from_json(spec.to_json()) == spec
    assert "loop_delay_scale" in spec.to_json() and "loop_delay_scale" not in Spec().to_json()
    rng = np.random.default_rng(2)
    setpoint, gyro = rng.uniform(-5, 5, (2, 50, 3))
    rotor = rng.uniform(0, 1100, (50, 4))
    delay = rng.integers(0, 6, 50).astype(float)
    batch = observe_step(spec, setpoint, gyro, rotor, loop_delay=delay)
    np.testing.assert_array_equal(batch[:, spec.columns[LOOP_DELAY]][:, 0], (delay * 0.2).astype(np.float32))
    np.testing.assert_array_equal(batch[:, :7], observe_step(Spec(), setpoint, gyro, rotor))
    out = np.zeros((1, spec.step_size), dtype=np.float32)
    for i in range(50):
        observe_step(spec, setpoint[i], gyro[i], rotor[i], out=out, loop_delay=delay[i])
        assert np.array_equal(out[0], batch[i])
    one = observe_step(spec, setpoint, gyro, rotor, loop_delay=3.0)  # one delay for the whole batch
    assert np.all(one[:, 7] == np.float32(0.6))
    with pytest.raises(ValueError, match="loop's delay"):
        observe_step(spec, setpoint, gyro, rotor)


def test_the_authority_field_is_the_slope_of_the_gyros_change_on_the_mixers_thrust_differential():
    """A quad whose rates change by k_a per tick per unit of the mixer's thrust-share differential
    on each axis: the estimate converges to k_a × authority_scale once the motors have moved, per
    row of a batch as for one vehicle, and a masked reset starts only that row's over."""
    from fcemu.firmware.mixer import BETAFLIGHT_QUAD_X

    spec = Spec(memory=2, fields=(*FIELDS, AUTHORITY))
    mix = np.asarray(BETAFLIGHT_QUAD_X)
    slope = np.array([[0.02, 0.03, 0.004], [0.2, 0.15, 0.01]])  # scaled rad/s per tick per share²
    batch, one = ObservationHistory(spec, (2,)), ObservationHistory(spec, (1,))
    rng = np.random.default_rng(0)
    gyro = np.zeros((2, 3))
    cols = spec.columns[AUTHORITY]
    for k in range(3000):
        share = 0.5 + 0.2 * np.sin(k / 40.0 + np.arange(4)) * rng.uniform(0.5, 1.0, (2, 4))
        gyro = gyro + slope * ((share**2) @ mix - 0.02) / spec.rate_scale  # an offset the centring removes
        step = observe_step(spec, np.zeros((2, 3)), gyro, share * TOP)
        if k == 0:
            obs, first = batch.reset(step), one.reset(step[1:])
            np.testing.assert_array_equal(obs[:, cols], 0.0)  # the motors have not moved yet
        else:
            obs, first = batch.push(step), one.push(step[1:])
        np.testing.assert_array_equal(obs[1:], first)
    np.testing.assert_allclose(obs[:, cols], slope * spec.authority_scale, rtol=0.02)
    obs = batch.reset(step, np.array([True, False]))
    np.testing.assert_array_equal(obs[0, cols], 0.0)
    np.testing.assert_allclose(obs[1, cols], slope[1] * spec.authority_scale, rtol=0.02)


def test_the_authority_spec_round_trips_with_its_scale_and_leak():
    spec = Spec(fields=(*FIELDS, AUTHORITY), authority_scale=5.0, authority_leak=0.99)
    again = ObservationSpec.from_json(spec.to_json())
    assert again == spec and '"authority_scale": 5.0' in spec.to_json()
    assert "authority" not in Spec().to_json()
    with pytest.raises(ValueError, match="authority_leak"):
        Spec(fields=(*FIELDS, AUTHORITY), authority_leak=1.0)
