"""Quad X mixer: signs, saturation handling, idle and output bounds, for both tables."""

from __future__ import annotations

import numpy as np
import pytest

from fcemu.firmware.mixer import BETAFLIGHT_QUAD_X, PAPER_IRIS, TABLES, QuadXMixer
from fcemu.sim_bridge.twin import Twin

LEFT, FRONT, CCW = (2, 3), (1, 3), (1, 2)  # zero-based motor indices: 3/4, 2/4, 2/3


def _raised(out: list[float]) -> set[int]:
    mid = sum(out) / 4
    return {i for i, v in enumerate(out) if v > mid}


@pytest.mark.parametrize("table", sorted(TABLES))
@pytest.mark.parametrize(("axis", "motors"), [(0, LEFT), (1, FRONT), (2, CCW)])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_each_axis_reaches_the_right_motors(table, axis, motors, sign):
    mixer = QuadXMixer(table)
    demand = [0.0, 0.0, 0.0]
    demand[axis] = 0.1 * sign
    out = mixer.mix(demand, 0.5)
    expected = set(motors) if sign > 0 else {0, 1, 2, 3} - set(motors)
    assert _raised(out) == expected


@pytest.mark.parametrize("table", sorted(TABLES))
@pytest.mark.parametrize("axis", [0, 1, 2])
def test_each_axis_sign_turns_the_twin_that_way(table, axis):
    """The FRD tables are physically right: a positive demand accelerates the twin positively."""
    twin = Twin(rig="rig")
    mixer = QuadXMixer(table)
    throttle = mixer.throttle_for_pwm(twin.airframe.hover_pwm())
    for sign in (1.0, -1.0):
        frame = twin.reset(seed=0)
        demand = [0.0, 0.0, 0.0]
        demand[axis] = 0.1 * sign
        pwm = np.array(mixer.mix(demand, throttle))
        for _ in range(30):
            frame = twin.step(pwm)
        assert np.sign(frame.gyro[axis]) == sign
        # the strongest response is on the commanded axis (the Iris' uneven arms couple yaw into roll)
        assert int(np.argmax(np.abs(frame.gyro))) == axis


def test_betaflight_table_is_betaflight_quadx_in_frd():
    # mixerQuadX {roll, pitch, yaw} with pitch negated (Betaflight pitch is nose-down positive)
    betaflight = [(-1, 1, -1), (-1, -1, 1), (1, 1, 1), (1, -1, -1)]
    assert [(r, -p, y) for r, p, y in betaflight] == [tuple(int(v) for v in row) for row in BETAFLIGHT_QUAD_X]
    paper = {"m1": [-1.0, 0.598, -1.0], "m2": [-0.927, -0.598, 1.0], "m3": [1.0, 0.598, 1.0],
             "m4": [0.927, -0.598, -1.0]}
    assert [(r, -p, y) for r, p, y in paper.values()] == list(PAPER_IRIS)


def test_exact_output_inside_the_range():
    mixer = QuadXMixer("betaflight", idle=0.055)
    out = mixer.mix([0.1, 0.0, 0.0], 0.5)  # throttle: 1500 µs; a demand of 1 spans idle..max (945 µs)
    assert out == pytest.approx([1500 - 94.5, 1500 - 94.5, 1500 + 94.5, 1500 + 94.5])
    assert mixer.mix_range == pytest.approx(0.2)
    assert mixer.mix([0.0, 0.0, 0.0], 0.745) == pytest.approx([1745.0] * 4)  # hover means the same to all


@pytest.mark.parametrize("table", sorted(TABLES))
def test_saturation_scales_the_mix_and_no_motor_clips(table):
    mixer = QuadXMixer(table, idle=0.055)
    demand = [0.6, -0.5, 0.4]  # a mix range well above 1
    rows = np.array(mixer.table)
    raw = rows @ np.array(demand)
    for throttle in (0.0, 0.3, 0.5, 0.9, 1.0):
        out = np.array(mixer.mix(demand, throttle))
        assert mixer.mix_range == pytest.approx(max(raw.max(), 0) - min(raw.min(), 0))
        assert mixer.mix_range > 1.0
        # the whole output range is used, exactly, and the motors keep the mix's proportions
        assert out.min() == pytest.approx(mixer.out_low)
        assert out.max() == pytest.approx(2000.0)
        np.testing.assert_allclose((out - out.mean()) / mixer.out_range, (raw - raw.mean()) / mixer.mix_range,
                                   atol=1e-12)


def test_throttle_is_shifted_to_keep_authority_airmode():
    mixer = QuadXMixer("betaflight", idle=0.0)
    out = mixer.mix([0.2, 0.0, 0.0], 0.95)  # would clip at the top
    assert mixer.throttle == pytest.approx(0.8)
    assert out == pytest.approx([1600.0, 1600.0, 2000.0, 2000.0])
    out = mixer.mix([0.2, 0.0, 0.0], 0.0)  # airmode: full authority at zero throttle
    assert mixer.throttle == pytest.approx(0.2)
    assert out == pytest.approx([1000.0, 1000.0, 1400.0, 1400.0])


def test_without_airmode_authority_fades_at_low_throttle():
    mixer = QuadXMixer("betaflight", idle=0.0, airmode=False)
    out = mixer.mix([0.2, 0.0, 0.0], 0.0)  # Betaflight: 50% authority at zero throttle
    assert out == pytest.approx([1000.0, 1000.0, 1200.0, 1200.0])
    out = mixer.mix([0.2, 0.0, 0.0], 0.6)  # full authority above half throttle
    assert out == pytest.approx([1400.0, 1400.0, 1800.0, 1800.0])


def test_idle_is_the_minimum_armed_output():
    mixer = QuadXMixer("betaflight", idle=0.055)
    assert mixer.mix([0.0, 0.0, 0.0], 0.0) == pytest.approx([1055.0] * 4)
    assert mixer.mix([0.0, 0.0, 0.0], 0.04) == pytest.approx([1055.0] * 4)
    assert mixer.mix([0.0, 0.0, 0.0], -1.0) == pytest.approx([1055.0] * 4)
    out = mixer.mix([0.1, 0.0, 0.0], 0.0)  # airmode at zero stick: up from idle, the mix intact
    assert out == pytest.approx([1055.0, 1055.0, 1055.0 + 189.0, 1055.0 + 189.0])
    assert mixer.mix([0.0, 0.0, 0.0], 1.0) == pytest.approx([2000.0] * 4)
    assert QuadXMixer("paper_iris", idle=0.07).mix([0.0, 0.0, 0.0], 0.0) == pytest.approx([1070.0] * 4)
    assert mixer.throttle_for_pwm(mixer.mix([0.0, 0.0, 0.0], 0.7)[0]) == pytest.approx(0.7)


@pytest.mark.parametrize("table", sorted(TABLES))
def test_outputs_always_within_1000_2000(table):
    rng = np.random.default_rng(3)
    for airmode in (True, False):
        mixer = QuadXMixer(table, idle=0.0, airmode=airmode)
        for _ in range(500):
            out = np.array(mixer.mix(rng.uniform(-3, 3, 3).tolist(), float(rng.uniform(-0.2, 1.2))))
            assert np.isfinite(out).all()
            assert out.min() >= 1000.0 and out.max() <= 2000.0


def test_custom_table_and_validation():
    custom = [[-1, -1, -1], [-1, 1, 1], [1, -1, 1], [1, 1, -1]]
    assert QuadXMixer(custom).mix([0.1, 0.2, 0.0], 0.5) == QuadXMixer("betaflight").mix([0.1, 0.2, 0.0], 0.5)
    with pytest.raises(ValueError, match="unknown mixer table"):
        QuadXMixer("hexa")
    with pytest.raises(ValueError, match="idle"):
        QuadXMixer(idle=1.5)


def test_props_out_reverse_the_yaw_column_as_betaflights_yaw_motors_reversed() -> None:
    from fcemu.firmware.mixer import QuadXMixer

    ahead, reversed_ = QuadXMixer(), QuadXMixer(yaw_reversed=True)
    yaw = [0.0, 0.0, 0.2]
    a, r = ahead.mix(yaw, 0.5), reversed_.mix(yaw, 0.5)
    np.testing.assert_allclose(np.array(a) - 1500.0, -(np.array(r) - 1500.0), atol=1e-9)
    np.testing.assert_allclose(ahead.mix([0.1, -0.2, 0.0], 0.5), reversed_.mix([0.1, -0.2, 0.0], 0.5))


def test_a_props_out_airframe_flies_the_pid_with_yaw_reversed_and_refuses_a_policy(tmp_path) -> None:
    import json

    from fcemu.firmware.controllers import ControllerSpecError, default_controller, load_controller
    from fcemu.sim_bridge.airframe import AIRFRAME_DIR
    from fcemu.sim_bridge.airframe_spec import airframe_spec

    raw = json.loads((AIRFRAME_DIR / "iris.json").read_text())
    for rotor in raw["motors"]:
        rotor["spin"] = "ccw" if rotor["spin"] == "cw" else "cw"
    raw["name"] = "iris_props_out"
    path = tmp_path / "iris_props_out.json"
    path.write_text(json.dumps(raw))
    spec = airframe_spec(str(path))
    assert spec.props_out and not airframe_spec("iris").props_out
    assert load_controller("pid:pid_iris", 1000.0, spec).mixer.yaw_reversed
    assert not load_controller("pid:pid_iris", 1000.0, airframe_spec("iris")).mixer.yaw_reversed
    policy = default_controller()
    if policy.endswith(".onnx"):
        with pytest.raises(ControllerSpecError, match="props spin out"):
            load_controller(policy, 1000.0, spec)
