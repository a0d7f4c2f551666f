"""`EnvConfig`: each option declared once, with its command line or the reason it has none."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fcemu.sim_bridge.airframe import AIRFRAME_DIR
from fcemu.sim_bridge.env import RateControlEnv
from fcemu.sim_bridge.env_config import (
    DEFAULT_AIRFRAME,
    ENV_FIELDS,
    EXCLUDED,
    EnvConfig,
    own_ranges,
)
from fcemu.sim_bridge.vec_env import BatchedRateEnv


def test_every_option_has_help_and_is_either_on_the_command_line_or_excluded_with_a_reason():
    for name, f in ENV_FIELDS.items():
        assert f.metadata["help"], name
        assert ("cli" in f.metadata) != (name in EXCLUDED), name
        assert name not in EXCLUDED or len(EXCLUDED[name]) > 20, name  # a reason, not a placeholder


def test_the_observation_scales_rotor_speed_by_the_airframes_top_speed(tmp_path):
    assert EnvConfig().observation_spec.rotor_speed_scale == 1.0 / 1100.0  # the Iris: as before, to the bit
    path = _scaled_iris(tmp_path, max_rotor_speed=1300.0)
    assert EnvConfig(airframe=str(path)).observation_spec.rotor_speed_scale == 1.0 / 1300.0


def test_an_env_takes_a_config_or_its_fields_as_keywords_not_both():
    cfg = EnvConfig(memory=2, episode_s=0.01)
    a, b = RateControlEnv(cfg), RateControlEnv(memory=2, episode_s=0.01)
    np.testing.assert_array_equal(a.reset(seed=3)[0], b.reset(seed=3)[0])
    assert BatchedRateEnv(2, cfg).config is cfg
    with pytest.raises(TypeError, match="not both"):
        RateControlEnv(cfg, memory=3)
    with pytest.raises(TypeError, match="must be an EnvConfig"):
        RateControlEnv("episodic")


def test_the_default_airframe_and_its_own_ranges():
    assert EnvConfig().base_airframe.name == DEFAULT_AIRFRAME
    assert own_ranges(DEFAULT_AIRFRAME) == "iris"
    assert own_ranges("crazyflie") == own_ranges("iris_realistic") == "relative"
    crazyflie = EnvConfig(airframe="crazyflie", randomize="relative")  # relative ranges, built for it
    assert crazyflie.randomize.base_airframe() is crazyflie.base_airframe
    assert EnvConfig(airframe="crazyflie", randomize=own_ranges("crazyflie")).randomize == crazyflie.randomize


def _scaled_iris(tmp_path: Path, max_rotor_speed: float) -> Path:
    raw = json.loads((AIRFRAME_DIR / "iris.json").read_text())
    raw["name"] = "iris_fast"
    raw["motor"]["max_rotor_speed_rad_s"] = max_rotor_speed
    path = tmp_path / "iris_fast.json"
    path.write_text(json.dumps(raw))
    return path
