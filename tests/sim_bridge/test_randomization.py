"""Domain-randomisation ranges: the shipped file, validation, draws, and the environments using them."""

from __future__ import annotations

import json
import shutil

import mujoco
import numpy as np
import pytest

from fcemu.sim_bridge.airframe import AIRFRAME_DIR, build_mjcf, load_airframe
from fcemu.sim_bridge.env import RateControlEnv
from fcemu.sim_bridge.randomization import (
    BUS_PARAMETERS,
    PARAMETERS,
    RandomizationError,
    load_randomization,
    parse_randomization,
    ranges_for,
)
from fcemu.sim_bridge.vec_env import BatchedRateEnv

SHIPPED = AIRFRAME_DIR / "iris.randomization.json"


def test_the_shipped_ranges_load_and_match_the_airframe():
    ranges = load_randomization("iris")
    assert ranges.path == SHIPPED and ranges.airframe == "iris"
    # every parameter the twin honours but the ESC telemetry bus (the distillation ranges draw it)
    assert {p.key for p in ranges.parameters} == set(PARAMETERS) - BUS_PARAMETERS
    iris = load_airframe("iris")
    realistic = load_airframe("iris_realistic")
    for p in ranges.parameters:
        kind = PARAMETERS[p.key].kind
        if kind == "scale":
            assert p.lo < p.nominal < p.hi, p.key
        else:  # an effect: off in the nominal twin, its range around iris_realistic's value
            assert p.nominal == 0 and p.lo < p.hi, p.key
            assert p.lo <= PARAMETERS[p.key].nominal(realistic) <= p.hi, p.key
        assert p.nominal == pytest.approx(PARAMETERS[p.key].nominal(iris), rel=1e-12)
        assert p.source.strip() and p.unit
    assert list(ranges) == ["mass", "inertia", "kf", "km", "tau_up", "tau_down", "rate_damping",
                            "rotor_inertia", "esc_delay_ticks", "gyro_delay_ticks", "gyro_noise_std",
                            "gyro_vibration", "battery_sag_per_charge", "battery_resistance",
                            "battery_current_per_thrust",
                            "battery_drawn_at_start"]  # Airframe.scaled keywords
    assert (ranges.parameter("esc_delay_ticks").lo, ranges.parameter("esc_delay_ticks").hi) == (0, 2)
    assert (ranges.parameter("gyro_delay_ticks").lo, ranges.parameter("gyro_delay_ticks").hi) == (0, 3)


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
    (_set("rotor_inertia", "nominal", 1e-6), r"rotor_inertia nominal 1e-06 is not the airframe's 0"),
    (_set("battery_resistance", "range", [-0.01, 0.06]), r"battery_resistance: an effect's nominal and range "
                                                         r"must be finite numbers >= 0"),
    (_set("gyro_noise_std", "range", [0.02, 0.01]), r"gyro_noise_std: need lo <= hi, got \[0.02, 0.01\]"),
    (_set("esc_delay_ticks", "range", [0, 1.5]), r"esc_delay_ticks: ticks must be whole numbers"),
    (_set("inertia_zz", "range", [0.0136, 0.0204]), r"inertia_zz up to 0.0204 exceeds the other two axes' "
                                                     r"lowest sum 0.0184"),
    (lambda raw: raw["parameters"]["inertia_xx"].pop("unit"), r"inertia_xx: missing \['unit'\]"),
    (lambda raw: raw.update(airframe="f450"), r"cannot load airframe 'f450'"),
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


def _drawn_values(ranges, draw) -> dict[str, float]:
    """Each file key's drawn value, from a draw's `Airframe.scaled` keywords."""
    out = {}
    for p in ranges.parameters:
        _, keyword, axis, kind = PARAMETERS[p.key]
        value = draw[keyword] if axis is None else draw[keyword][axis]
        out[p.key] = value * p.nominal if kind == "scale" else value
    return out


def test_draws_are_reproducible_by_seed_and_within_range():
    ranges = load_randomization("iris")
    draws = [ranges.draw(np.random.default_rng(s)) for s in (5, 5, 6)]
    assert draws[0] == draws[1] and draws[0] != draws[2]
    rng = np.random.default_rng(0)
    ticks = {"esc_delay_ticks": set(), "gyro_delay_ticks": set()}
    for _ in range(300):
        for key, value in _drawn_values(ranges, ranges.draw(rng)).items():
            p = ranges.parameter(key)
            assert p.lo <= value <= p.hi, key
            if key in ticks:
                assert isinstance(value, int)
                ticks[key].add(value)
    assert ticks == {"esc_delay_ticks": {0, 1, 2}, "gyro_delay_ticks": {0, 1, 2, 3}}  # every tick is drawn


def test_a_draw_builds_the_airframe_it_names():
    ranges = load_randomization("iris")
    draw = ranges.draw(np.random.default_rng(3))
    af, iris = ranges.base_airframe().scaled(**draw), load_airframe("iris")
    assert af.rate_damping == draw["rate_damping"] and af.gyro_vibration == draw["gyro_vibration"]
    for name in ("rotor_inertia", "esc_delay_ticks", "gyro_delay_ticks", "gyro_noise_std",
                 "battery_resistance", "battery_sag_per_charge", "battery_current_per_thrust",
                 "battery_drawn_at_start"):
        assert getattr(af, name) == draw[name], name
    assert af.battery_sags and af.body_torques and af.gyro_effects
    assert af.motor.kf == iris.motor.kf * draw["kf"]
    one_axis = iris.scaled(rate_damping=(None, 0.02, None))  # an axis not drawn keeps the airframe's
    assert one_axis.rate_damping == (0.0, 0.02, 0.0)
    with pytest.raises(TypeError, match="unknown effect"):
        iris.scaled(drag=1.0)


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


def _batch_matches_single(ranges, steps: int = 60, n: int = 1, episode_s: float = 0.2, **env) -> bool:
    """Copy i of a batch and a single env seeded 3 + i, the same actions, across auto-resets."""
    batch = BatchedRateEnv(n, randomize=ranges, episode_s=episode_s, **env)
    singles = [RateControlEnv(randomize=ranges, episode_s=episode_s, **env) for _ in range(n)]
    ob, _ = batch.reset(seed=3)
    same = all(np.array_equal(ob[i], e.reset(seed=3 + i)[0]) for i, e in enumerate(singles))
    rng = np.random.default_rng(0)
    for _ in range(steps):
        a = rng.uniform(-1, 1, (n, 4)).astype(np.float32)
        ob, reward, _, truncated, _ = batch.step(a)
        for i, env in enumerate(singles):
            o, r, _, trunc, _ = env.step(a[i])
            if trunc:
                o, _ = env.reset()
            same &= np.array_equal(ob[i], o) and r == reward[i] and trunc == truncated[i]
    return bool(same)


def test_the_batched_training_env_honours_the_file_for_mass_inertia_and_motor_constants(tmp_path):
    def pin_motor_lag(raw):
        for key in ("tau_up", "tau_down"):
            p = raw["parameters"][key]
            p["range"] = [p["nominal"], p["nominal"]]
    assert _batch_matches_single(load_randomization(_write(tmp_path, pin_motor_lag)))


def test_the_batched_training_env_honours_the_motor_lag_ranges():
    assert _batch_matches_single(load_randomization("iris"))


def test_the_batched_training_env_draws_every_effect_per_copy_and_episode():
    """Four copies, each its own airframe per episode (lag, delays, noise, battery...), as single envs."""
    ranges = load_randomization("iris")
    assert _batch_matches_single(ranges, steps=130, n=4, episode_s=0.04)
    batch = BatchedRateEnv(4, randomize=ranges, episode_s=0.04)
    batch.reset(seed=3)
    drawn = batch.episode_factors
    assert len({f["esc_delay_ticks"] for f in drawn} | {f["gyro_delay_ticks"] for f in drawn}) > 1
    assert len({f["gyro_noise_std"] for f in drawn}) == 4 and len({f["tau_up"] for f in drawn}) == 4


def test_the_nominal_draw_is_the_airframe_itself():
    ranges = load_randomization("iris")
    iris = ranges.base_airframe()
    assert iris.scaled(**ranges.nominal()) == iris
    assert set(ranges.nominal()) == set(ranges.draw(np.random.default_rng(0)))  # replaces all a draw sets


def test_a_share_of_episodes_flies_the_nominal_airframe():
    from fcemu.sim_bridge.env import EnvConfig, draw_episode

    ranges = load_randomization("iris")
    nominal = ranges.nominal()

    def nominal_share(share: float) -> float:
        cfg, rng = EnvConfig(randomize=ranges, randomize_share=share), np.random.default_rng(5)
        return float(np.mean([draw_episode(rng, cfg).factors == nominal for _ in range(400)]))

    assert nominal_share(1.0) == 0.0 and nominal_share(0.0) == 1.0
    assert 0.4 < nominal_share(0.5) < 0.6
    all_drawn, rng_a, rng_b = EnvConfig(randomize=ranges), np.random.default_rng(2), np.random.default_rng(2)
    assert [draw_episode(rng_a, all_drawn).factors for _ in range(3)] == [
        draw_episode(rng_b, EnvConfig(randomize=ranges, randomize_share=1.0)).factors for _ in range(3)]
    # a copy that flew a drawn airframe flies the nominal one again, in the batch as in a single env
    assert _batch_matches_single(ranges, steps=130, n=4, episode_s=0.04, randomize_share=0.5)
    for bad, message in ((1.5, "must be in"), (-0.1, "must be in")):
        with pytest.raises(ValueError, match=message):
            EnvConfig(randomize=ranges, randomize_share=bad)
    with pytest.raises(ValueError, match="needs randomisation ranges"):
        EnvConfig(randomize={"mass": 0.1}, randomize_share=0.5)


def test_the_fine_tuning_ranges_are_the_shipped_ones_with_the_esc_delay_at_its_top():
    full, esc2 = load_randomization("iris"), load_randomization("iris_esc2")
    assert esc2.airframe == full.airframe and list(esc2) == list(full)
    for p, q in zip(full.parameters, esc2.parameters, strict=True):
        assert p.key == q.key and p.nominal == q.nominal
        if p.key == "esc_delay_ticks":
            assert (q.lo, q.hi) == (p.hi, p.hi) == (2, 2)
        else:
            assert (q.lo, q.hi) == (p.lo, p.hi), p.key


def test_the_distillation_ranges_add_the_esc_telemetry_bus_to_the_fine_tuning_ones():
    esc2, sensors = load_randomization("iris_esc2"), load_randomization("iris_sensors")
    assert [p for p in sensors.parameters if p.key not in BUS_PARAMETERS] == list(esc2.parameters)
    late, lost = sensors.parameter("esc_telemetry_delay_ticks"), sensors.parameter("esc_telemetry_loss")
    assert (late.lo, late.hi, lost.lo, lost.hi) == (0, 5, 0.0, 0.05)
    draws = [sensors.draw(np.random.default_rng(s)) for s in range(200)]
    assert {d["esc_telemetry_delay_ticks"] for d in draws} == set(range(6))
    assert all(0.0 <= d["esc_telemetry_loss"] <= 0.05 for d in draws)
    with pytest.raises(RandomizationError, match="below 1"):
        parse_randomization({"airframe": "iris", "parameters": {"esc_telemetry_loss": {
            "nominal": 0, "range": [0, 1], "unit": "share", "source": "every frame"}}})


# ── ranges relative to any airframe ───────────────────────────────────────────────────
PHYSICAL = ("mass", "inertia_xx", "inertia_yy", "inertia_zz", "kf", "km", "tau_up", "tau_down")


def test_the_relative_ranges_on_the_iris_are_the_iris_ranges():
    iris_ranges, iris = load_randomization("iris"), load_airframe("iris")
    relative = load_randomization("relative", iris)
    assert relative.path == AIRFRAME_DIR / "relative.randomization.json" and relative.base_airframe() is iris
    assert [p.key for p in relative.parameters] == [p.key for p in iris_ranges.parameters]
    for p in iris_ranges.parameters:
        q = relative.parameter(p.key)
        assert q.nominal == p.nominal, p.key
        if p.key in PHYSICAL or PARAMETERS[p.key].kind == "ticks" or p.key == "gyro_noise_std":
            assert (q.lo, q.hi) == pytest.approx((p.lo, p.hi), rel=1e-9, abs=1e-15), p.key
        else:  # the effects' physical estimates (vibration: per hover speed²), calibrated on the Iris's own
            assert q.lo == pytest.approx(p.lo, rel=0.04) and q.hi == pytest.approx(p.hi, rel=0.04), p.key


def test_ranges_for_an_airframe_are_its_own_file_else_the_relative_ones():
    assert ranges_for("iris") == load_randomization("iris")
    for name in ("crazyflie", "x500", "racer5", "iris_realistic"):
        ranges, airframe = ranges_for(name), load_airframe(name)
        assert ranges.path.name == "relative.randomization.json" and ranges.airframe == name
        ranges.check_airframe(airframe)
        assert {p.key for p in ranges.parameters} == set(PARAMETERS) - BUS_PARAMETERS
        for key in PHYSICAL:
            p = ranges.parameter(key)
            assert p.lo < PARAMETERS[key].nominal(airframe) < p.hi, key
    with pytest.raises(RandomizationError, match="ranges are for airframe 'iris', not 'crazyflie'"):
        ranges_for("crazyflie", "iris")
    with pytest.raises(RandomizationError, match=r"relative to the airframe .*ranges_for\(airframe, 'rel"):
        load_randomization("relative")


@pytest.mark.parametrize("name", ["crazyflie", "x500", "racer5"])
def test_every_relative_draw_is_a_rigid_body_the_twin_builds(name):
    """The inertia corner a draw can reach that is nearest breaking I_zz <= I_xx + I_yy, built in MuJoCo."""
    ranges = ranges_for(name)
    xx, yy, zz = (ranges.parameter(k) for k in ("inertia_xx", "inertia_yy", "inertia_zz"))
    assert zz.hi <= xx.lo + yy.lo and xx.hi <= yy.lo + zz.lo and yy.hi <= xx.lo + zz.lo
    corner = ranges.base_airframe().scaled(inertia=(xx.lo / xx.nominal, yy.lo / yy.nominal,
                                                    zz.hi / zz.nominal))
    mujoco.MjModel.from_xml_string(build_mjcf(corner, "free"))


def _relative(tmp_path, edit) -> str:
    raw = json.loads((AIRFRAME_DIR / "relative.randomization.json").read_text())
    edit(raw)
    path = tmp_path / "rel.randomization.json"
    path.write_text(json.dumps(raw))
    return str(path)


@pytest.mark.parametrize(("edit", "message"), [
    (_set("mass", "of", "pack_charge"), r"mass: \"of\" must be one of \['nominal'\] for a scale parameter"),
    (_set("esc_delay_ticks", "of", "nominal"), r"esc_delay_ticks: \"of\" must be one of \['absolute'\]"),
    (_set("rotor_inertia", "of", "rotor_mass"), r"rotor_inertia: \"of\" must be one of \['absolute', "),
    (_set("kf", "range", [1.05, 1.2]), r"kf: factors of the nominal must hold 1, got \[1.05, 1.2\]"),
    (_set("km", "range", [1.2, 0.8]), r"km: range must be \[lo, hi\] with 0 <= lo <= hi"),
    (lambda raw: raw["parameters"]["tau_up"].pop("of"), r"tau_up: missing \['of'\]"),
])
def test_a_bad_relative_file_is_refused(tmp_path, edit, message):
    path = _relative(tmp_path, edit)
    with pytest.raises(RandomizationError, match=message):
        ranges_for("crazyflie", path)


def test_the_training_envs_draw_a_new_airframe_from_the_relative_ranges():
    ranges = ranges_for("crazyflie")
    env = RateControlEnv(airframe="crazyflie", randomize=ranges, episode_s=0.05)
    factors = env.reset(seed=2)[1]["factors"]
    assert env.twin.airframe.mass == pytest.approx(0.027 * factors["mass"])
    assert _batch_matches_single(ranges, steps=60, n=2, episode_s=0.04, airframe="crazyflie")
