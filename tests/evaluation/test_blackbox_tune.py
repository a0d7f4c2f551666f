"""The pilot's tune read from Betaflight blackbox headers as an fcemu PID preset: the two real logs'
headers (Betaflight 4.2.8 and 3.1.5, decoded by orangebox) and synthetic headers for the other
versions, each taken as it is by fcemu's own PID loader."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fcemu.evaluation.blackbox_tune import (
    DTERM_SCALE,
    FEEDFORWARD_SCALE,
    ITERM_SCALE,
    PTERM_SCALE,
    log_tune,
)
from fcemu.firmware.pid_controller import PIDRateController
from tests.evaluation.test_blackbox_header import BF46, CS110, GECKO, V32

pytestmark = pytest.mark.no_wall_clock


def test_log_tune_of_the_gecko(gecko: dict) -> None:
    tune = log_tune(gecko, GECKO, hover_throttle=0.6)
    pid = tune["pid"]
    tpa = 1 - 0.70 * (0.6 - 0.45) / (1 - 0.45)  # tpa_rate 70, breakpoint 1450; 4.2 scales D only
    assert pid["kp"] == pytest.approx([35 * PTERM_SCALE, 39 * PTERM_SCALE, 40 * PTERM_SCALE])
    assert pid["ki"] == pytest.approx([75 * ITERM_SCALE, 80 * ITERM_SCALE, 60 * ITERM_SCALE * 2.5])
    assert pid["kd"] == pytest.approx([27 * DTERM_SCALE * tpa, 30 * DTERM_SCALE * tpa, 0.0])  # at d_min
    assert pid["kff"] == pytest.approx(np.array([140, 170, 90]) * FEEDFORWARD_SCALE / 100)
    assert pid["pidsum_limit"] == [0.5, 0.5, 0.4] and pid["iterm_limit"] == [0.4, 0.4, 0.4]
    assert (pid["gyro_lowpass_type"], pid["gyro_lowpass_hz"], pid["gyro_lowpass2_hz"]) == ("pt1", 300.0, 0.0)
    assert (pid["dterm_lowpass_type"], pid["dterm_lowpass_hz"]) == ("biquad", 100.0)
    assert (pid["iterm_relax"], pid["iterm_relax_cutoff_hz"], pid["iterm_windup"]) == ("rp", 15.0, 1.0)
    assert tune["mixer"] == {"table": "betaflight", "idle": 0.055, "airmode": True}
    kinds = [line.split(":")[0] for line in tune["not_modelled"]]
    for kind in ("anti-gravity", "D-min/D-max dynamics", "feedforward shaping", "static gyro notches",
                 "dynamic notch", "RPM filter", "TPA dynamics", "RC smoothing"):
        assert kind in kinds
    assert "ff_boost=15" in " ".join(tune["not_modelled"])
    assert tune["source"]["rollPID"] == [35, 75, 35] and "4.2.8" in tune["description"]
    controller = PIDRateController.from_dict(tune, dt=0.001)  # fcemu's own loader takes it as it is
    out = controller.pid.update([0.5, 0.0, 0.0], [0.0, 0.0, 0.0])
    assert out[0] > 0 and np.all(np.isfinite(out))
    assert log_tune(gecko, GECKO)["pid"]["kd"][0] == pytest.approx(27 * DTERM_SCALE)  # no hover: no TPA


def test_log_tune_of_the_cs110(cs110: dict) -> None:
    tune = log_tune(cs110, CS110)
    pid = tune["pid"]
    assert pid["kp"] == pytest.approx([14 * PTERM_SCALE, 18 * PTERM_SCALE, 70 * PTERM_SCALE])
    assert pid["ki"] == pytest.approx([10 * ITERM_SCALE, 10 * ITERM_SCALE, 20 * ITERM_SCALE])  # no yaw x2.5
    assert pid["kd"] == pytest.approx([18 * DTERM_SCALE, 22 * DTERM_SCALE, 0.0])  # 3.1 has no yaw D
    # dtermSetpointWeight 100: 3.1's D acts on setpoint - gyro, the setpoint part a feedforward
    assert pid["kff"] == pytest.approx([18 * DTERM_SCALE, 22 * DTERM_SCALE, 0.0])
    assert pid["ff_lowpass_hz"] == 100.0 and pid["yaw_p_lowpass_hz"] == 100.0
    assert pid["iterm_windup"] == 0.5 and pid["pidsum_limit"] == [0.5, 0.5, 0.5]
    assert (pid["gyro_lowpass_hz"], pid["dterm_lowpass_type"], pid["iterm_relax"]) == (90.0, "pt1", "off")
    assert tune["mixer"] == {"table": "betaflight", "idle": 0.045, "airmode": False}
    assert "anti-gravity: anti_gravity_gain=1.0, anti_gravity_threshold=350" in tune["not_modelled"]
    PIDRateController.from_dict(tune, dt=0.001)


def test_log_tune_of_a_4_6_header() -> None:
    tune = log_tune({**BF46, "gyro_lpf1_type": 2, "tpa_mode": 0}, "x.bbl", hover_throttle=0.73)
    pid = tune["pid"]
    tpa = 1 - 0.65 * (0.73 - 0.35) / 0.65
    assert pid["kp"][0] == pytest.approx(45 * PTERM_SCALE * tpa)  # tpa_mode 0: P and D
    assert pid["kd"][0] == pytest.approx(30 * DTERM_SCALE * tpa)  # 4.6: D rests at D, rises to d_max
    assert pid["iterm_limit"] == pytest.approx([0.4, 0.4, 0.32]) and pid["iterm_windup"] == 1.0
    assert pid["gyro_lowpass_type"] == "biquad"  # PT2 as the biquad of its low-frequency lag
    assert pid["gyro_lowpass_hz"] == pytest.approx(math.sqrt(2) * 1.553774 / 2 * 300, rel=1e-4)
    assert pid["dterm_lowpass_hz"] == pytest.approx(137.14125)  # 75-150 Hz, expo 5, throttle 0.73
    assert pid["ki"][2] == pytest.approx(80 * ITERM_SCALE * 2.5)
    fast = log_tune({**BF46, "gyro_lpf1_type": 1, "gyro_lpf1_static_hz": 600})["pid"]
    assert (fast["gyro_lowpass_type"], fast["gyro_lowpass_hz"]) == ("pt1", pytest.approx(600 / math.sqrt(2)))
    integrated = log_tune({**BF46, "use_integrated_yaw": 1})["pid"]["ki"][2]
    assert integrated == pytest.approx(80 * ITERM_SCALE)
    PIDRateController.from_dict(tune, dt=0.001)


def test_log_tune_of_a_3_2_header() -> None:
    """3.2's names (dterm_setpoint_weight / 127, dterm_filter_type), a FIR gyro lowpass, analog motors."""
    tune = log_tune(V32, "v32.bfl", hover_throttle=0.8)
    pid = tune["pid"]
    tpa = 1 - 0.1 * (0.8 - 0.65) / 0.35  # 3.x: P and D
    assert pid["kp"][0] == pytest.approx(44 * PTERM_SCALE * tpa) and pid["kd"][2] == 0.0
    assert pid["kff"][:2] == pytest.approx([20 * DTERM_SCALE * tpa, 22 * DTERM_SCALE * tpa])  # weight 127/127
    assert pid["iterm_limit"] == [0.15, 0.15, 0.15] and pid["iterm_windup"] == 0.5
    assert (pid["gyro_lowpass_type"], pid["dterm_lowpass_type"]) == ("pt1", "biquad")
    assert pid["gyro_lowpass_hz"] == pytest.approx(8000 / (math.pi * 79))  # the PT1 of the FIR's lag
    assert tune["mixer"]["idle"] == pytest.approx(0.07) and tune["mixer"]["airmode"] is False
    PIDRateController.from_dict(tune)


def test_log_tune_carries_yaw_motors_reversed() -> None:
    tune = log_tune({**BF46, "yaw_motors_reversed": 1})
    assert tune["mixer"]["yaw_reversed"] is True
    PIDRateController.from_dict(tune)
