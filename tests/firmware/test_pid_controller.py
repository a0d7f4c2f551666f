"""The PID rate controller on the twin (ball-joint rig), and its presets.

Settling criterion for the ±3 rad/s steps: from rest, the stepped axis stays within ±10%
of the step (|Ω − Ω*| ≤ 0.3 rad/s) for every sample in t ∈ [0.5, 1] s, and the other
two axes stay within the same 0.3 rad/s of zero over that window.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from fcemu.firmware.controller import RateSetpoint
from fcemu.firmware.pid import PIDGains
from fcemu.firmware.pid_controller import PRESETS, PIDRateController, load_preset, preset_path
from fcemu.firmware.sensors import SensorFrame
from fcemu.sim_bridge.twin import Twin

TABLES = Path(__file__).resolve().parents[2] / "evaluation" / "data" / "paper_tables.json"
STEP = 3.0
BAND = 0.1 * STEP


@pytest.fixture(scope="module")
def twin() -> Twin:
    return Twin(rig="rig")


def fly_step(controller: PIDRateController, twin: Twin, rates: list[float],
             seconds: float = 1.0) -> np.ndarray:
    throttle = (twin.airframe.hover_pwm() - 1000.0) / 1000.0
    setpoint = RateSetpoint(np.array(rates, dtype=float), throttle)
    frame = twin.reset(seed=0)
    controller.reset()
    out = np.zeros((round(seconds / twin.dt), 3))
    for k in range(len(out)):
        pwm = controller.update(setpoint, frame, twin.dt)
        assert pwm.shape == (4,) and np.isfinite(pwm).all()
        assert pwm.min() >= 1000.0 and pwm.max() <= 2000.0
        frame = twin.step(pwm)
        out[k] = frame.gyro
    return out


# pid_betaflight models Betaflight's defaults; tests/sitl checks it
TUNED = ("pid_iris", "pid_paper", "pid_iris_robust")


@pytest.mark.parametrize("preset", TUNED)
@pytest.mark.parametrize("axis", [0, 1, 2], ids=["roll", "pitch", "yaw"])
@pytest.mark.parametrize("sign", [1.0, -1.0], ids=["pos", "neg"])
def test_tracks_3_rad_s_steps_and_settles_within_10_percent(twin, preset, axis, sign):
    controller = PIDRateController.from_preset(preset)
    target = [0.0, 0.0, 0.0]
    target[axis] = sign * STEP
    rate = fly_step(controller, twin, target)
    window = rate[500:]  # t in [0.5, 1] s
    error = np.abs(window - np.array(target))
    assert error[:, axis].max() <= BAND, f"{preset}: axis {axis} off by {error[:, axis].max():.3f} rad/s"
    assert error.max() <= BAND
    assert np.sign(rate[50, axis]) == sign  # moving the right way within 50 ms


def test_iris_preset_is_better_than_the_paper_preset_on_a_step(twin):
    target = [2.0, -2.0, 2.0]
    errors = {}
    for preset in TUNED:
        rate = fly_step(PIDRateController.from_preset(preset), twin, target)
        errors[preset] = np.abs(rate - np.array(target)).sum(axis=0)  # the paper's Error, per axis
    assert np.all(errors["pid_iris"] < errors["pid_paper"]), errors


def test_paper_preset_is_the_papers_gains_and_mixer():
    preset = load_preset("paper")
    gains = PIDGains.from_dict(preset["pid"])
    assert preset["mixer"]["table"] == "paper_iris"
    ref = json.loads(TABLES.read_text())["pid_gains_kp_ki_kd"]
    for i, axis in enumerate(("roll", "pitch", "yaw")):
        assert [gains.kp[i], gains.ki[i], gains.kd[i]] == ref[axis]
        assert gains.iterm_limit[i] == pytest.approx(ref[axis][1] * 20 / 1000)  # GymFC's windup guard


@pytest.mark.parametrize("name", ["pid_iris", "iris", "pid_paper", "paper"])
def test_preset_names(name):
    controller = PIDRateController.from_preset(name)
    assert controller.name == (name if name.startswith("pid_") else f"pid_{name}")
    assert PIDRateController.from_dict(controller.to_dict()).to_dict() == controller.to_dict()


def test_preset_from_a_path_and_unknown_names(tmp_path):
    path = tmp_path / "mine.json"
    path.write_text(preset_path("paper").read_text())
    paper = PIDRateController.from_preset("paper")
    assert PIDRateController.from_preset(str(path)).pid.gains == paper.pid.gains
    with pytest.raises(ValueError, match="unknown PID preset"):
        PIDRateController.from_preset("race")
    with pytest.raises(FileNotFoundError):
        PIDRateController.from_preset(str(tmp_path / "missing.json"))


def test_presets_are_package_data():
    for name in PRESETS:
        assert preset_path(name).exists()
        assert PIDGains.from_dict(load_preset(name)["pid"])


def test_reset_forgets_the_integral():
    controller = PIDRateController.from_preset("iris")
    frame = SensorFrame(0, np.zeros(3), np.zeros(3), np.zeros(4))
    setpoint = RateSetpoint(np.array([1.0, -1.0, 1.0]), 0.5)
    first = controller.update(setpoint, frame, 0.001)
    for _ in range(200):
        controller.update(setpoint, frame, 0.001)
    assert controller.pid.terms["i"] != [0.0, 0.0, 0.0]
    controller.reset()
    np.testing.assert_allclose(controller.update(setpoint, frame, 0.001), first)


def test_follows_a_new_loop_rate_but_not_jitter():
    controller = PIDRateController.from_preset("iris", dt=0.001)
    frame = SensorFrame(0, np.zeros(3), np.zeros(3), np.zeros(4))
    setpoint = RateSetpoint([0.5, 0.0, 0.0], 0.5)  # plain lists are fine too
    for dt in (0.0011, 0.0009, 0.0025, 0.001):
        controller.update(setpoint, frame, dt)
    assert controller.dt == 0.001
    for _ in range(8):
        controller.update(setpoint, frame, 0.00025)
    assert controller.dt == 0.00025


def test_update_is_cheap():
    controller = PIDRateController.from_preset("iris")
    frame = SensorFrame(0, np.array([0.1, -0.2, 0.3]), np.zeros(3), np.zeros(4))
    setpoint = RateSetpoint(np.array([1.0, -1.0, 2.0]), 0.7)
    samples = []
    for _ in range(20):
        t0 = time.perf_counter()
        for _ in range(200):
            controller.update(setpoint, frame, 0.001)
        samples.append((time.perf_counter() - t0) / 200)
    assert float(np.median(samples)) < 100e-6  # typically ~10 µs; generous for a loaded machine


def test_betaflight_preset_is_betaflight_46_defaults_in_our_units():
    pid = load_preset("betaflight")["pid"]
    p_scale, i_scale, d_scale, tpa_d = 0.032029, 0.244381, 0.000529, 0.62  # pid.h; TPA at throttle 0.73
    assert pid["kp"] == pytest.approx([p_scale * 45, p_scale * 47, p_scale * 45])
    yaw_ki_boost = 2.5  # pidInitConfig: yaw Ki x 2.5 unless use_integrated_yaw (off by default)
    assert pid["ki"] == pytest.approx([i_scale * 80, i_scale * 84, i_scale * 80 * yaw_ki_boost])
    assert pid["kd"] == pytest.approx([d_scale * 30 * tpa_d, d_scale * 34 * tpa_d, 0.0])
    assert pid["iterm_limit"] == pytest.approx([0.4, 0.4, 0.32])  # 80 % of pidsum_limit 500 / 400
    curve = 0.73 * (1 - 0.73) * 0.5 + 0.73  # dynLpfCutoffFreq, expo 5
    assert pid["gyro_lowpass_hz"] == pytest.approx(250 + 250 * curve)
    assert pid["dterm_lowpass_hz"] == pytest.approx(75 + 75 * curve)
    assert PIDRateController.from_preset("betaflight").name == "pid_betaflight"
