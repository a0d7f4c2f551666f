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
