"""`--init`'s check of the named run, and how an observation with added fields maps onto it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from fcemu.firmware.observation import INTEGRAL, MOTOR_OUTPUT, RMS, ObservationSpec
from fcemu.sim_bridge.airframe import DEFAULT_AIRFRAME, load_airframe
from fcemu.training.init import InitError, _widen, init_checkpoint


def _spec(**kwargs) -> ObservationSpec:
    """An observation spec scaled for the default airframe's top rotor speed."""
    return ObservationSpec(max_rotor_speed=load_airframe(DEFAULT_AIRFRAME).motor.max_rotor_speed, **kwargs)


def _run(tmp_path: Path, spec: ObservationSpec, algo: str = "ppo") -> Path:
    run = tmp_path / "run"
    run.mkdir()
    (run / "model.zip").write_bytes(b"")  # only its existence is checked before the load
    (run / "config.json").write_text(json.dumps({"algo": algo, "observation": json.loads(spec.to_json())}))
    return run


def _config(spec: ObservationSpec, algo: str = "ppo") -> dict:
    return {"algo": algo, "observation": json.loads(spec.to_json())}


def test_an_added_field_maps_to_no_column_and_the_others_to_theirs_step_by_step(tmp_path):
    theirs = _spec(memory=2, fields=("rate_error", "rotor_speed", INTEGRAL))
    ours = _spec(memory=2, fields=("rate_error", "rotor_speed", INTEGRAL, MOTOR_OUTPUT))
    source = init_checkpoint(str(_run(tmp_path, theirs)), _config(ours))
    assert source.added == (MOTOR_OUTPUT,)
    step0, step1 = list(range(10)), list(range(10, 20))  # their 10 columns per step, newest first
    assert source.column_map().tolist() == step0 + [-1] * 4 + step1 + [-1] * 4


def test_a_field_in_the_middle_is_added_where_this_run_has_it(tmp_path):
    theirs = _spec(fields=("rate_error", "rotor_speed", RMS))
    ours = _spec(fields=("rate_error", "rotor_speed", INTEGRAL, RMS), integral_leak=0.99)
    source = init_checkpoint(str(_run(tmp_path, theirs)), _config(ours))
    assert source.added == (INTEGRAL,)
    assert source.column_map().tolist() == [0, 1, 2, 3, 4, 5, 6, -1, -1, -1, 7, 8, 9]


@pytest.mark.parametrize("ours", [
    _spec(fields=("rate_error",)),  # a field taken away
    _spec(memory=2, fields=("rate_error", "rotor_speed", MOTOR_OUTPUT)),  # another memory
    _spec(fields=("rate_error", "rotor_speed", RMS, MOTOR_OUTPUT), rms_leak=0.9),  # another leak
    _spec(fields=("rate_error", "rotor_speed", RMS, MOTOR_OUTPUT), rate_scale=0.5),  # another scale
])
def test_only_added_fields_are_accepted(tmp_path, ours):
    run = _run(tmp_path, _spec(fields=("rate_error", "rotor_speed", RMS)))
    with pytest.raises(InitError, match="a fine-tune may only add fields"):
        init_checkpoint(str(run), _config(ours))


def test_another_algorithm_is_refused(tmp_path):
    run = _run(tmp_path, _spec(), algo="sac")
    with pytest.raises(InitError, match="trained by 'sac', this run is 'ppo'"):
        init_checkpoint(str(run), _config(_spec()))


def test_widen_puts_the_saved_columns_where_they_map_and_zeros_elsewhere():
    saved = torch.arange(6, dtype=torch.float32).reshape(2, 3)
    columns = np.array([0, -1, 1, 2, -1])
    out = _widen(saved, torch.empty(2, 5), columns, 3)
    assert out.tolist() == [[0, 0, 1, 2, 0], [3, 0, 4, 5, 0]]
    hidden = torch.ones(2, 2)  # not an input layer: returned as it is, for set_parameters to judge
    assert _widen(hidden, torch.empty(2, 2), columns, 3) is hidden
    assert _widen(hidden, torch.empty(4, 4), columns, 3) is hidden
