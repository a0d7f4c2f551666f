"""Domain-randomisation ranges: the shipped file, validation, draws, and the environments using them."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from sim_bridge.airframe import AIRFRAME_DIR, load_airframe
from sim_bridge.env import RateControlEnv
from sim_bridge.randomization import PARAMETERS, RandomizationError, load_randomization
from sim_bridge.vec_env import BatchedRateEnv

SHIPPED = AIRFRAME_DIR / "iris.randomization.json"


def test_the_shipped_ranges_load_and_match_the_airframe():
    ranges = load_randomization("iris")
    assert ranges.path == SHIPPED and ranges.airframe == "iris"
    assert {p.key for p in ranges.parameters} == set(PARAMETERS)  # every parameter the twin honours
    iris = load_airframe("iris")
    for p in ranges.parameters:
        assert p.lo < p.nominal < p.hi, p.key
        assert p.nominal == pytest.approx(PARAMETERS[p.key][0](iris), rel=1e-12)
        assert p.source.strip() and p.unit
    assert list(ranges) == ["mass", "inertia", "kf", "km", "tau_up", "tau_down"]  # Airframe.scaled keywords


def _write(tmp_path, edit) -> str:
    raw = json.loads(SHIPPED.read_text())
    edit(raw)
    shutil.copy(AIRFRAME_DIR / "iris.json", tmp_path / "iris.json")
    path = tmp_path / "iris.randomization.json"
    path.write_text(json.dumps(raw))
    return str(path)


def _set(key: str, field: str, value):
    def edit(raw):
        raw["parameters"][key][field] = value
    return edit


@pytest.mark.parametrize(("edit", "message"), [
    (lambda raw: raw["parameters"].update(drag={"nominal": 1, "range": [1, 2], "unit": "", "source": "x"}),
     r"unknown parameter\(s\) \['drag'\]"),
    (_set("mass", "range", [1.7, 1.9]), r"mass: need lo <= nominal <= hi, got 1.7 <= 1.6 <= 1.9"),
    (_set("kf", "range", [5e-6]), r"kf: range must be \[lo, hi\]"),
    (_set("km", "nominal", float("nan")), r"km: nominal and range must be finite positive numbers"),
    (_set("tau_up", "range", [0.0, 0.02]), r"tau_up: nominal and range must be finite positive numbers"),
    (_set("tau_down", "source", " "), r"tau_down: source must say where the range comes from"),
    (_set("mass", "nominal", 1.5), r"mass nominal 1.5 is not the airframe's 1.6"),
    (lambda raw: raw["parameters"]["inertia_xx"].pop("unit"), r"inertia_xx: missing \['unit'\]"),
    (lambda raw: raw.update(airframe="x500"), r"cannot load airframe 'x500'"),
    (lambda raw: raw.update(parameters=[]), r"\"parameters\" must be a non-empty object"),
])
def test_a_bad_file_is_refused_with_a_clear_error(tmp_path, edit, message):
    path = _write(tmp_path, edit)
    with pytest.raises(RandomizationError, match=message) as err:
        load_randomization(path)
    assert str(err.value).startswith(path)


def test_a_missing_or_unreadable_file_is_refused(tmp_path):
    with pytest.raises(RandomizationError, match=r"no randomisation file .*shipped: iris"):
        load_randomization("nosuch")
    bad = tmp_path / "x.randomization.json"
    bad.write_text("{not json")
    with pytest.raises(RandomizationError, match="cannot read as JSON"):
        load_randomization(bad)


def test_draws_are_reproducible_by_seed_and_within_range():
    ranges = load_randomization("iris")
    draws = [ranges.draw(np.random.default_rng(s)) for s in (5, 5, 6)]
    assert draws[0] == draws[1] and draws[0] != draws[2]
    rng = np.random.default_rng(0)
    for _ in range(200):
        f = ranges.draw(rng)
        values = {"mass": f["mass"], "kf": f["kf"], "km": f["km"], "tau_up": f["tau_up"],
                  "tau_down": f["tau_down"], "inertia_xx": f["inertia"][0], "inertia_yy": f["inertia"][1],
                  "inertia_zz": f["inertia"][2]}
        for key, factor in values.items():
            p = ranges.parameter(key)
            assert p.lo <= factor * p.nominal <= p.hi, key


def test_the_env_draws_airframes_from_the_file_per_episode():
    env = RateControlEnv(randomize="iris", episode_s=0.05)
    _, info = env.reset(seed=11)
    f = info["factors"]
    af, iris = env.twin.airframe, load_airframe("iris")
    assert af.mass == pytest.approx(iris.mass * f["mass"])
    assert af.base_inertia == pytest.approx(tuple(i * k for i, k in zip(iris.base_inertia, f["inertia"],
                                                                         strict=True)))
    assert af.motor.tau_up == pytest.approx(iris.motor.tau_up * f["tau_up"])
    assert af.motor.tau_down == pytest.approx(iris.motor.tau_down * f["tau_down"])
    assert len(set(f["inertia"])) == 3  # each axis drawn on its own
    again = RateControlEnv(randomize=load_randomization("iris"), episode_s=0.05)
    assert again.reset(seed=11)[1]["factors"] == f
    assert env.reset()[1]["factors"] != f


def test_the_pm_fraction_mapping_draws_as_before():
    rand = {"mass": 0.3, "inertia": 0.3, "kf": 0.2, "km": 0.3}
    env = RateControlEnv(randomize=rand)
    env.reset(seed=4)
    rng = np.random.default_rng(4)
    rng.uniform(-5.24, 5.24, 3)  # the episode's command comes first
    expected = {k: float(rng.uniform(1.0 - f, 1.0 + f)) for k, f in rand.items()}
    assert env.episode.factors == expected


def _batch_matches_single(ranges, steps: int = 60) -> bool:
    batch = BatchedRateEnv(1, randomize=ranges, episode_s=0.2)
    single = RateControlEnv(randomize=ranges, episode_s=0.2)
    ob, _ = batch.reset(seed=3)
    os_, _ = single.reset(seed=3)
    same = np.array_equal(ob[0], os_)
    rng = np.random.default_rng(0)
    for _ in range(steps):
        a = rng.uniform(-1, 1, (1, 4)).astype(np.float32)
        ob = batch.step(a)[0]
        os_ = single.step(a[0])[0]
        same &= np.array_equal(ob[0], os_)
    return bool(same)


def test_the_batched_training_env_honours_the_file_for_mass_inertia_and_motor_constants(tmp_path):
    def pin_motor_lag(raw):
        for key in ("tau_up", "tau_down"):
            p = raw["parameters"][key]
            p["range"] = [p["nominal"], p["nominal"]]
    assert _batch_matches_single(load_randomization(_write(tmp_path, pin_motor_lag)))


@pytest.mark.xfail(strict=True, reason="BatchedRateEnv steps every copy with one motor lag (vec_env.py); "
                                       "per-copy tau_up/tau_down is its owner's change")
def test_the_batched_training_env_honours_the_motor_lag_ranges():
    assert _batch_matches_single(load_randomization("iris"))
