import numpy as np
import onnx
import pytest

from firmware.controllers import DEFAULT_POLICY
from firmware.neural import META_PREFIX
from firmware.observation import FIELDS, INTEGRAL, ObservationHistory, ObservationSpec, observe_step


def test_default_spec_serialises_exactly_as_the_shipped_policy_metadata():
    props = {p.key: p.value for p in onnx.load(str(DEFAULT_POLICY), load_external_data=False).metadata_props}
    assert ObservationSpec().to_json() == props[META_PREFIX + "observation"]
    assert "integral_leak" not in ObservationSpec().to_json()


def test_integral_spec_round_trips_and_sizes():
    spec = ObservationSpec(memory=2, fields=(*FIELDS, INTEGRAL), integral_leak=0.99)
    assert ObservationSpec.from_json(spec.to_json()) == spec
    assert spec.step_size == 10 and spec.size == 20
    assert spec.integral_slice() == slice(7, 10)
    with pytest.raises(ValueError, match="integral_leak"):
        ObservationSpec(fields=(*FIELDS, INTEGRAL), integral_leak=1.0)
    with pytest.raises(ValueError, match="repeated"):
        ObservationSpec(fields=(*FIELDS, INTEGRAL, INTEGRAL))


def test_batched_history_integrates_per_row_and_masked_reset_keeps_other_rows():
    spec = ObservationSpec(fields=(INTEGRAL, "rate_error"), integral_leak=0.5)
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
    spec = ObservationSpec(fields=(INTEGRAL, "rotor_speed", "rate_error"))
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
    spec = ObservationSpec(memory=3)
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
    spec = ObservationSpec(fields=("rotor_speed", "rate_error", INTEGRAL))
    assert spec.column_sources == (3, 4, 5, 6, 0, 1, 2, 0, 1, 2)
    assert spec.column_scales == (spec.rotor_speed_scale,) * 4 + (spec.rate_scale,) * 6
    assert spec.step_size == 10 and spec.integral_slice() == slice(7, 10)
