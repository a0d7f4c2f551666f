"""Attitude estimator, Betaflight Actual rates and the parameter table: pure classes."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from fcemu.firmware.estimator import GRAVITY, AttitudeEstimator, euler_from_quat, quat_from_euler
from fcemu.firmware.params import INT32, ParamTable, bytewise_from_int
from fcemu.firmware.stick_rates import ActualRates, StickRates


def accel_for(roll: float, pitch: float) -> tuple[float, float, float]:
    """Specific force at rest (FRD) for a vehicle at roll/pitch: the NED 'up' g in body axes."""
    w, x, y, z = quat_from_euler(roll, pitch, 0.0)
    r20, r21, r22 = 2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z
    return (-GRAVITY * r20, -GRAVITY * r21, -GRAVITY * r22)


def test_euler_quaternion_round_trip() -> None:
    for angles in [(0.3, -0.2, 1.0), (-1.2, 0.5, -2.5), (0.0, 0.0, 0.0)]:
        assert np.allclose(euler_from_quat(quat_from_euler(*angles)), angles, atol=1e-12)


def test_level_start_and_accel_convergence() -> None:
    est = AttitudeEstimator()
    est.level_from_accel(*accel_for(0.4, -0.3))
    assert np.allclose(est.euler()[:2], (0.4, -0.3), atol=1e-9)
    est.reset()
    for _ in range(8000):  # 8 s at 1 kHz from a wrong (level) start, still vehicle
        est.update(0, 0, 0, *accel_for(0.2, 0.1), 0.001)
    roll, pitch, _ = est.euler()
    assert roll == pytest.approx(0.2, abs=0.01) and pitch == pytest.approx(0.1, abs=0.01)
    est.vz = 0.0
    for _ in range(2000):
        est.update(0, 0, 0, *accel_for(0.2, 0.1), 0.001)
    assert abs(est.vz) < 0.01


def test_gyro_integration_roll_right_is_positive() -> None:
    est = AttitudeEstimator()
    for k in range(500):  # 1 rad/s of roll for 0.5 s, accel consistent with the true attitude
        est.update(1.0, 0.0, 0.0, *accel_for(k * 0.001, 0.0), 0.001)
    assert est.euler()[0] == pytest.approx(0.5, abs=0.01)


def test_gyro_bias_is_learned() -> None:
    est = AttitudeEstimator()
    for _ in range(60000):
        est.update(0.02, -0.01, 0.0, *accel_for(0, 0), 0.001)
    roll, pitch, _ = est.euler()
    assert abs(roll) < 0.01 and abs(pitch) < 0.01


def test_estimator_tracks_twin_truth_in_ball_rig() -> None:
    from fcemu.sim_bridge.twin import Twin

    twin = Twin(rig="rig")
    frame = twin.reset(seed=0)
    est = AttitudeEstimator()
    est.level_from_accel(*frame.accel)
    worst = spun = 0.0
    for k in range(2000):  # rock the rig in roll and pitch with differential thrust
        s = math.sin(2 * math.pi * k / 1000)
        pwm = np.array([1600 - 60 * s, 1600 - 60 * s * 0.5, 1600 + 60 * s, 1600 + 60 * s * 0.5])
        frame = twin.step(pwm)
        est.update(*frame.gyro, *frame.accel, 0.001)
        q_true, q_est = twin.truth().attitude, est.q
        worst = max(worst, math.degrees(2 * math.acos(min(1.0, abs(float(np.dot(q_true, q_est)))))))
        spun = max(spun, float(abs(twin.truth().body_rates).max()))
    assert spun > 1.0 and worst < 2.0  # degrees, whole attitude (yaw from the gyro alone)


def test_actual_rates_match_betaflight_formula() -> None:
    r = ActualRates(center_dps=200, max_dps=670, expo=0.54)
    assert r.rate(0.0) == 0.0
    assert r.rate(1.0) == pytest.approx(math.radians(670))
    assert r.rate(-1.0) == pytest.approx(-math.radians(670))
    x = 0.5
    expo = abs(x) * (x ** 5 * 0.54 + x * (1 - 0.54))
    assert r.rate(x) == pytest.approx(math.radians(x * 200 + (670 - 200) * expo))
    eps = 1e-4  # centre slope is the centre sensitivity
    assert r.rate(eps) / eps == pytest.approx(math.radians(200), rel=1e-3)
    assert r.rate(3.0) == r.rate(1.0) and r.rate(float("nan")) == 0.0
    with pytest.raises(ValueError):
        ActualRates(center_dps=800, max_dps=670)
    full = math.radians(670)
    assert StickRates().rates(1, -1, 0)[:2] == (pytest.approx(full), pytest.approx(-full))


def test_params_validate_and_persist_atomically(tmp_path) -> None:
    table = ParamTable()
    assert table.set("COM_OF_LOSS_T", 1.5) == ""
    assert "outside" in table.set("COM_OF_LOSS_T", 1e6)
    assert "finite" in table.set("PID_ROLL_P", float("nan"))
    assert "unknown" in table.set("NO_SUCH", 1.0)
    assert "integer" in table.set("CTRL_SEL", 0.5)
    assert table["COM_OF_LOSS_T"] == 1.5
    path = tmp_path / "params.json"
    table.save(path)
    assert [p.name for p in tmp_path.iterdir()] == ["params.json"]  # no temporary left behind
    fresh = ParamTable()
    assert fresh.load(path) == [] and fresh["COM_OF_LOSS_T"] == 1.5
    path.write_text(json.dumps({"COM_OF_LOSS_T": -3, "BOGUS": 1, "FS_HOLD_T": 2.0}))
    again = ParamTable()
    assert len(again.load(path)) == 2 and again["FS_HOLD_T"] == 2.0 and again["COM_OF_LOSS_T"] == 0.5
    path.write_text("{not json")
    assert ParamTable().load(path)


def test_int_params_on_the_wire_are_bytewise_like_px4() -> None:
    table = ParamTable()
    assert table.specs["CTRL_SEL"].kind == INT32
    assert table.decode_wire("CTRL_SEL", bytewise_from_int(1), INT32) == 1
    assert table.decode_wire("CTRL_SEL", 1.0, INT32) == 1.0  # a client that casts instead
    table.set("CTRL_SEL", 1)
    assert table.encode_wire("CTRL_SEL") == bytewise_from_int(1)


def test_set_default_moves_untouched_values_only() -> None:
    table = ParamTable()
    table.set("PID_ROLL_I", 3.0)
    table.set_default("PID_ROLL_P", 7.0)
    table.set_default("PID_ROLL_I", 9.0)
    assert table["PID_ROLL_P"] == 7.0 and table["PID_ROLL_I"] == 3.0
