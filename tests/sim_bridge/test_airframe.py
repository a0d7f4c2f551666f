from __future__ import annotations

import json
import math

import mujoco
import numpy as np
import pytest

from fcemu.firmware.action import PWM_MIN, PWM_SPAN
from fcemu.firmware.errors import UserError
from fcemu.sim_bridge.airframe import AIRFRAME_DIR, EFFECT_KEYS, airframe_names, build_mjcf, load_airframe
from fcemu.sim_bridge.airframe_file import SOURCED, AirframeError

NEW = ("crazyflie", "x500", "racer5")


@pytest.mark.parametrize("mass", [1.0, 1.3])
def test_hover_throttle_holds_the_weight(mass: float) -> None:
    airframe = load_airframe("iris").scaled(mass=mass)
    throttle = airframe.hover_throttle()
    m = airframe.motor
    omega = (PWM_MIN + PWM_SPAN * throttle - m.pwm_min) / (m.pwm_max - m.pwm_min) * m.max_rotor_speed
    assert 4 * m.kf * omega**2 == pytest.approx(airframe.mass * 9.81, rel=1e-12)
    assert 0.0 < throttle < 1.0


def test_the_published_airframes_are_shipped_beside_the_iris():
    assert set(NEW) | {"iris", "iris_realistic"} <= set(airframe_names())


def _sourced_numbers(raw: dict) -> set[str]:
    """The file's fields that hold numbers (SOURCED names them), as "sources" keys."""
    present = {key for key in SOURCED if not key.startswith("motor.") and key in raw}
    return present | {f"motor.{key}" for key in raw.get("motor", {})}


@pytest.mark.parametrize("name", airframe_names())
def test_each_shipped_airframe_loads_cites_every_number_and_can_hover(name):
    airframe = load_airframe(name)
    raw = json.loads((AIRFRAME_DIR / f"{name}.json").read_text())
    if "base" not in raw:  # a variant takes its numbers (and their sources) from its base
        assert _sourced_numbers(raw) <= set(raw["sources"]), name
        assert all(len(text) >= 10 for text in raw["sources"].values())
    for key, entry in raw.get("effects", {}).items():
        assert key in EFFECT_KEYS and len(entry["source"]) > 15, key
    assert 0.0 < airframe.hover_throttle() < 1.0
    assert airframe.thrust_to_weight() > 1.0
    for rig in ("rig", "free"):
        mujoco.MjModel.from_xml_string(build_mjcf(airframe, rig))


def test_the_poles_are_the_motors_and_the_brushed_crazyflie_has_none():
    assert load_airframe("iris").motor.poles == 14 and load_airframe("iris_realistic").motor.poles == 14
    assert load_airframe("x500").motor.poles == load_airframe("racer5").motor.poles == 14
    assert load_airframe("crazyflie").motor.poles is None


def test_derived_motor_constants_give_back_the_sources_thrust_to_weight():
    """The top speeds were derived from gym-pybullet-drones' thrust2weight (2.25 and 4.17)."""
    assert load_airframe("crazyflie").thrust_to_weight() == pytest.approx(2.25, rel=1e-4)
    assert load_airframe("racer5").thrust_to_weight() == pytest.approx(4.17, rel=1e-4)
    iris = load_airframe("iris")
    assert iris.thrust_to_weight() == pytest.approx(4 * 5.84e-6 * 1100**2 / (1.6 * 9.81), rel=1e-12)


@pytest.mark.parametrize("name", ["iris", *NEW])
def test_max_angular_acceleration_is_what_the_twin_does_at_full_differential_thrust(name):
    """Each rotor at hover ± δ on the ball-joint rig: MuJoCo's angular acceleration, axis by axis."""
    airframe = load_airframe(name)
    model = mujoco.MjModel.from_xml_string(build_mjcf(airframe, "rig"))
    data = mujoco.MjData(model)
    m = airframe.motor
    hover = airframe.mass * 9.81 / 4
    delta = min(m.kf * m.max_rotor_speed**2 - hover, hover)
    x, y = airframe.rotor_positions[:, 0], airframe.rotor_positions[:, 1]
    patterns = (-np.sign(y), -np.sign(x), -airframe.spin.astype(float))  # roll, pitch, yaw
    expected = airframe.max_angular_acceleration()
    for axis, pattern in enumerate(patterns):
        data.ctrl[:] = hover + delta * pattern
        mujoco.mj_forward(model, data)
        assert abs(data.qacc[axis]) == pytest.approx(expected[axis], rel=1e-6), (name, axis)
        if axis < 2:  # yaw moves roll too where the front and rear arms differ (the Iris)
            assert np.abs(np.delete(data.qacc, axis)).max() < 1e-6 * expected[axis]


def _bad(tmp_path, edit, base: str = "crazyflie") -> str:
    raw = json.loads((AIRFRAME_DIR / f"{base}.json").read_text())
    edit(raw)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(raw))
    return str(path)


def _set(*keys_and_value):
    *keys, value = keys_and_value

    def edit(raw):
        for key in keys[:-1]:
            raw = raw[key]
        raw[keys[-1]] = value
    return edit


def _rename(old: str, new: str, within: str | None = None):
    def edit(raw):
        target = raw if within is None else raw[within]
        target[new] = target.pop(old)
    return edit


def _positions(*xy):
    def edit(raw):
        for rotor, (x, y) in zip(raw["motors"], xy, strict=True):
            rotor["position_m"][:2] = [x, y]
    return edit


def _spins(*spins):
    def edit(raw):
        for rotor, spin in zip(raw["motors"], spins, strict=True):
            rotor["spin"] = spin
    return edit


BAD_FILES = {
    "missing field": (lambda raw: raw.pop("base_mass_kg"), r"base_mass_kg: missing"),
    "misspelt field": (_rename("base_mass_kg", "base_mas_kg"), r"base_mas_kg: unknown field; did you mean "
                                                               r"'base_mass_kg'\?"),
    "misspelt motor field": (_rename("moment_constant_m", "moment_constnt_m", "motor"),
                             r"motor.moment_constnt_m: unknown field; did you mean 'moment_constant_m'\?"),
    "misspelt source": (_rename("base_box_m", "base_bx_m", "sources"), r"sources.base_bx_m: unknown field; "
                                                                       r"did you mean 'base_box_m'\?"),
    "misspelt effect": (_rename("battery_voltage_full_V", "battery_voltage_ful_V", "effects"),
                        r"effects.battery_voltage_ful_V: unknown effect .*did you mean "
                        r"'battery_voltage_full_V'"),
    "wrong type": (_set("base_mass_kg", "0.027"), r"base_mass_kg: expected a number, got \"0.027\""),
    "boolean": (_set("rotor_radius_m", True), r"rotor_radius_m: expected a number, got true"),
    "zero mass": (_set("base_mass_kg", 0.0), r"base_mass_kg: must be > 0, got 0"),
    "negative inertia": (_set("base_inertia_kg_m2", [1.4e-5, -1.4e-5, 2.17e-5]),
                         r"base_inertia_kg_m2\[1\]: must be > 0"),
    "no rigid body": (_set("base_inertia_kg_m2", [1.4e-5, 1.4e-5, 3e-5]),
                      r"base_inertia_kg_m2: I_zz 3e-05 exceeds the other two axes' sum 2.8e-05"),
    "inertia not 3 numbers": (_set("base_inertia_kg_m2", [1.4e-5, 1.4e-5]), r"expected 3 numbers"),
    "not finite": (_set("motor", "thrust_coefficient_N_per_rad_s2", math.nan),
                   r"motor.thrust_coefficient_N_per_rad_s2: must be finite, got nan"),
    "zero kf": (_set("motor", "thrust_coefficient_N_per_rad_s2", 0.0),
                r"motor.thrust_coefficient_N_per_rad_s2: must be > 0"),
    "negative km": (_set("motor", "moment_constant_m", -0.01), r"motor.moment_constant_m: must be > 0"),
    "zero lag": (_set("motor", "time_constant_up_s", 0), r"motor.time_constant_up_s: must be > 0"),
    "zero top speed": (_set("motor", "max_rotor_speed_rad_s", 0),
                       r"motor.max_rotor_speed_rad_s: must be > 0"),
    "pwm range": (_set("motor", "pwm_min_us", 2000), r"motor.pwm_min_us: must be below pwm_max_us, "
                                                     r"got 2000 >= 2000"),
    "odd poles": (_set("motor", "poles", 13), r"motor.poles: must be an even whole number >= 2"),
    "cannot hover": (_set("motor", "max_rotor_speed_rad_s", 1000.0),
                     r"motor.max_rotor_speed_rad_s: four rotors at 1000 rad/s lift 0.1153 N, not the weight "
                     r"0.2649 N"),
    "three motors": (lambda raw: raw["motors"].pop(), r"motors: a Quad X airframe needs a list of 4 motors, "
                                                      r"found 3"),
    "rotor at the centre": (_positions((-0.028, 0.028), (0.003, 0.002), (-0.028, -0.028), (0.028, -0.028)),
                            r"motors\[1\].position_m: a rotor 3.6 mm from the centre has no lever arm"),
    "motors out of order": (_positions((0.028, 0.028), (-0.028, 0.028), (-0.028, -0.028), (0.028, -0.028)),
                            r"motors\[0\].position_m: motor 1 is the rear right one in Betaflight's Quad X "
                            r"order \(FRD: x < 0, y > 0\), got \(0.028, 0.028\)"),
    "off the centre of mass": (_positions((-0.01, 0.028), (0.06, 0.028), (-0.01, -0.028), (0.06, -0.028)),
                               r"motors: the rotors' centre \(0.025, 0\) m is off the centre of mass"),
    "spins all one way": (_spins("cw", "cw", "cw", "cw"), r"motors: spins \['cw', 'cw', 'cw', 'cw'\] do not "
                                                          r"cancel"),
    "diagonals unlike": (_spins("cw", "ccw", "cw", "ccw"),
                         r"do not cancel: a Quad X needs the diagonal pairs"),
    "unknown spin": (_spins("cw", "ccw", "ccw", "left"), r"motors\[3\].spin: must be \"cw\" or \"ccw\""),
    "negative effect": (_set("effects", "battery_voltage_full_V", "value", -4.2),
                        r"effects.battery_voltage_full_V.value: must be > 0"),
    "half a tick": (_set("effects", "esc_delay_ticks", {"value": 0.5, "source": "x"}),
                    r"effects.esc_delay_ticks.value: must be a whole number of ticks >= 0"),
}


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_a_bad_airframe_file_is_one_error_naming_the_file_and_the_field(tmp_path, case):
    edit, message = BAD_FILES[case]
    path = _bad(tmp_path, edit)
    with pytest.raises(AirframeError, match=message) as err:
        load_airframe(path)
    assert str(err.value).startswith(f"{path}: ") and "\n" not in str(err.value)
    assert isinstance(err.value, UserError) and isinstance(err.value, ValueError)


def test_a_file_that_is_not_a_json_object_is_refused(tmp_path):
    path = tmp_path / "bad.json"
    path.write_text('{"name": "bad",')
    with pytest.raises(AirframeError, match=f"{path}: cannot read as JSON"):
        load_airframe(path)
    path.write_text("[1, 2]")
    with pytest.raises(AirframeError, match="expected a JSON object, got list"):
        load_airframe(path)


def test_a_missing_file_is_still_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"shipped airframes: .*crazyflie"):
        load_airframe("nosuch")
    with pytest.raises(FileNotFoundError):
        load_airframe(tmp_path / "nosuch.json")


def test_a_variant_is_checked_as_its_merged_whole_and_its_own_misspellings_named(tmp_path):
    path = tmp_path / "variant.json"
    path.write_text(json.dumps({"base": "iris", "name": "heavy", "base_mass_kg": 2.0}))
    assert load_airframe(path).mass == pytest.approx(2.1)
    path.write_text(json.dumps({"base": "iris", "name": "v", "efects": {}}))
    with pytest.raises(AirframeError, match=f"{path}: efects: unknown field; did you mean 'effects'"):
        load_airframe(path)
    path.write_text(json.dumps({"base": "iris", "name": "v", "base_mass_kg": 30.0}))
    with pytest.raises(AirframeError, match=f"{path}: motor.max_rotor_speed_rad_s: .*cannot hover"):
        load_airframe(path)
    path.write_text(json.dumps({"base": "variant", "name": "v"}))
    with pytest.raises(AirframeError, match="is its own base"):
        load_airframe(path)
