"""Betaflight blackbox headers read for fcemu: the two real logs' headers (Betaflight 4.2.8 and 3.1.5,
decoded by orangebox) checked against their own frames, and synthetic headers for the other versions."""

from __future__ import annotations

import itertools
import logging
import math
from pathlib import Path

import numpy as np
import pytest

from fcemu.evaluation.blackbox_header import (
    firmware,
    gyro_filter_lag_s,
    logged_interval_s,
    stick_setpoint_dps,
    yaw_motors_reversed,
)
from fcemu.evaluation.identify_log import LogError

pytestmark = pytest.mark.no_wall_clock

LOGS = Path(__file__).resolve().parents[1] / "data" / "real_logs"
GECKO, CS110 = LOGS / "gecko_btfl_002.bbl", LOGS / "cs110_example_smooth_tune.BBL"

BF46 = {  # a Betaflight 4.6 header's filter and rate part, everything but lowpass 1 off
    "Firmware type": "Betaflight", "Firmware revision": "Betaflight 4.6.0 (abcdef) STM32H743",
    "I interval": 256, "P interval": 4, "P ratio": 64, "looptime": 125, "gyro_sync_denom": 1,
    "pid_process_denom": 1, "gyro_lpf1_type": 0, "gyro_lpf1_static_hz": 300, "gyro_lpf1_dyn_hz": [0, 500],
    "gyro_lpf1_dyn_expo": 5, "gyro_lpf2_type": 0, "gyro_lpf2_static_hz": 0, "gyro_notch_hz": [0, 0],
    "gyro_notch_cutoff": [0, 0], "dyn_notch_count": 0, "dyn_notch_q": 500, "dyn_notch_min_hz": 100,
    "dyn_notch_max_hz": 600, "dshot_bidir": 0, "rpm_filter_harmonics": 3, "rpm_filter_q": 500,
    "rpm_filter_min_hz": 100, "rollPID": [45, 80, 30], "pitchPID": [47, 84, 34], "yawPID": [45, 80, 0],
    "d_max": [40, 46, 0], "ff_weight": [120, 125, 120], "dterm_lpf1_type": 0, "dterm_lpf1_static_hz": 75,
    "dterm_lpf1_dyn_hz": [75, 150], "dterm_lpf1_dyn_expo": 5, "dterm_lpf2_type": 0,
    "dterm_lpf2_static_hz": 150, "yaw_lowpass_hz": 100, "iterm_windup": 80, "iterm_relax": 1,
    "iterm_relax_type": 1, "iterm_relax_cutoff": 15,
    "use_integrated_yaw": 0, "pidsum_limit": 500, "pidsum_limit_yaw": 400, "tpa_mode": 1, "tpa_rate": 65,
    "tpa_breakpoint": 1350, "motorOutput": [158, 2047], "motor_idle": 550, "features": 1 << 22,
    "rates_type": 3, "rc_rates": [7, 7, 7], "rc_expo": [0, 0, 0], "rates": [67, 67, 67],
    "rate_limits": [1998, 1998, 1998], "deadband": 0, "yaw_deadband": 0,
}
V32 = {  # a Betaflight 3.2 header: 3.2's names, a FIR gyro lowpass, analog motors
    "Firmware type": "Cleanflight", "Firmware revision": "Betaflight 3.2.5 (abc) SPRACINGF3",
    "looptime": 125, "gyro_sync_denom": 1, "pid_process_denom": 2, "P interval": "1/4", "rc_rate": 100,
    "rc_expo": 0, "rc_rate_yaw": 100, "rc_expo_yaw": 0, "rates": [70, 70, 60], "tpa_rate": 10,
    "tpa_breakpoint": 1650, "rollPID": [44, 40, 20], "pitchPID": [58, 50, 22], "yawPID": [70, 45, 20],
    "dterm_filter_type": 1, "dterm_lpf_hz": 100, "yaw_lpf_hz": 0, "iterm_windup": 50,
    "dterm_setpoint_weight": 127, "setpoint_relaxation_ratio": 20, "pidsum_limit": 500,
    "pidsum_limit_yaw": 400, "gyro_lowpass_type": 2, "gyro_lowpass_hz": 100,
    "motorOutput": [1070, 2000], "features": 0,
}


def _headers(path: Path) -> dict:
    orangebox = pytest.importorskip("orangebox", reason="the blackbox decoder is the extra fcemu[blackbox]")
    logging.getLogger("orangebox").setLevel(logging.ERROR)
    return orangebox.Parser.load(str(path), 1).headers


def _frames(path: Path, fields: list[str], count: int) -> np.ndarray:
    orangebox = pytest.importorskip("orangebox", reason="the blackbox decoder is the extra fcemu[blackbox]")
    parser = orangebox.Parser.load(str(path), 1)
    index = [parser.field_names.index(name) for name in fields]
    return np.array([[frame.data[i] for i in index] for frame in itertools.islice(parser.frames(), count)],
                    dtype=float)


def test_firmware_of_real_and_other_betaflight_headers(gecko: dict, cs110: dict) -> None:
    assert firmware(gecko, GECKO) == (4, 2, 8)  # Firmware type:Cleanflight, revision Betaflight
    assert firmware(cs110, CS110) == (3, 1, 5)
    assert firmware(BF46) == (4, 6, 0)
    calendar = {"Firmware type": "Betaflight", "Firmware revision": "Betaflight 2025.12.1 (x) SITL"}
    assert firmware(calendar) == (2025, 12, 1)


@pytest.mark.parametrize(("kind", "revision", "said"), [
    ("Cleanflight", "INAV 5.1.0 (abc) MATEKF405", "an INAV blackbox log (INAV 5.1.0)"),
    ("Cleanflight", "EmuFlight 0.4.1 (abc) HELIOSPRING", "an EmuFlight blackbox log (EmuFlight 0.4.1)"),
    ("Rotorflight", "Rotorflight 4.3.0 (abc) STM32F7X2", "a Rotorflight blackbox log (Rotorflight 4.3.0)"),
    ("Cleanflight", "Cleanflight 2.5.0 (abc) SPRACINGF3", "a Cleanflight blackbox log (Cleanflight 2.5.0)"),
    ("Mystery", "", "an unknown firmware's blackbox log (Mystery)"),
    ("Cleanflight", "Betaflight 2.9.1 (abc) NAZE", "Betaflight 2.9.1 blackbox log: only 3.0 and later"),
    ("Cleanflight", "Betaflight (abc) NAZE", "Betaflight blackbox log of unknown version"),
])
def test_firmware_refuses_what_is_not_betaflight_3_or_later(kind: str, revision: str, said: str) -> None:
    with pytest.raises(LogError) as error:
        firmware({"Firmware type": kind, "Firmware revision": revision}, "flight.bbl")
    message = str(error.value)
    assert message.startswith("flight.bbl: ") and said in message and "\n" not in message


@pytest.mark.parametrize(("path", "expected_s"), [(GECKO, 0.002), (CS110, 0.0005)])
def test_logged_interval_is_the_frames_own_time_step(path: Path, expected_s: float) -> None:
    interval = logged_interval_s(_headers(path), path)
    assert interval == pytest.approx(expected_s)  # gecko P interval 16 of 8 kHz; cs110 "1/4" of 8 kHz
    step_s = float(np.median(np.diff(_frames(path, ["time"], 3000)[:, 0]))) * 1e-6
    assert interval == pytest.approx(step_s, rel=0.02)  # the cs110's clock logs 1980 Hz against 2000


def test_logged_interval_in_each_versions_units() -> None:
    assert logged_interval_s({**BF46, "pid_process_denom": 2, "P interval": 4}) == pytest.approx(0.001)
    assert logged_interval_s({**BF46, "P interval": 0, "I interval": 256}) == pytest.approx(0.032)
    v32 = {"Firmware revision": "Betaflight 3.2.0 (x) F4", "looptime": 250, "pid_process_denom": 1,
           "gyro_lowpass_hz": 90, "P interval": "1/2"}
    assert logged_interval_s(v32) == pytest.approx(0.0005)
    assert logged_interval_s({**v32, "P interval": "2/3"}) == pytest.approx(0.000375)
    # 3.0-3.2 ran the PID every second gyro loop when the gyro lowpass was off
    assert logged_interval_s({**v32, "gyro_lowpass_hz": 0}) == pytest.approx(0.001)
    assert logged_interval_s({**v32, "Firmware revision": "Betaflight 3.3.0", "gyro_lowpass_hz": 0}) == (
        pytest.approx(0.0005))


def test_gyro_lag_of_the_real_logs(gecko: dict, cs110: dict) -> None:
    lag, what = gyro_filter_lag_s(gecko, path=GECKO)
    # PT1 300 Hz (0.53 ms) + notches 115/105 and 162/152 Hz + the dual dynamic notch at its 100 Hz minimum
    assert 1.5e-3 < lag < 2.2e-3
    assert "lowpass 1 PT1 300 Hz" in what and "dynamic notch" in what and "not counted" in what
    assert "RPM filter" in what.split("not counted")[1]  # no motor speed given
    with_rpm, _ = gyro_filter_lag_s(gecko, motor_hz=250.0, path=GECKO)
    assert with_rpm > lag + 0.4e-3  # 4 motors x 3 harmonics
    lag, what = gyro_filter_lag_s(cs110, path=CS110)
    # 3.1.5: PT1 90 Hz (1 / (2π 90) = 1.77 ms at 0 Hz) and the 220/150 Hz notch
    assert 2.0e-3 < lag < 2.5e-3 and "notch 220/150 Hz" in what


def test_gyro_lag_of_one_lowpass_and_of_more_filters() -> None:
    only_pt1 = {**BF46, "gyro_lpf1_static_hz": 300}
    lag, _ = gyro_filter_lag_s(only_pt1)
    assert lag == pytest.approx(1 / (2 * math.pi * 300), rel=0.02)
    biquad, _ = gyro_filter_lag_s({**only_pt1, "gyro_lpf1_type": 1})
    assert biquad == pytest.approx(math.sqrt(2) / (2 * math.pi * 300), rel=0.03)
    pt2, _ = gyro_filter_lag_s({**only_pt1, "gyro_lpf1_type": 2})
    assert pt2 == pytest.approx(2 / (2 * math.pi * 300 * 1.553774), rel=0.03)
    lower, _ = gyro_filter_lag_s({**only_pt1, "gyro_lpf1_static_hz": 150})
    more = {**only_pt1, "gyro_lpf2_static_hz": 500, "gyro_notch_hz": [200, 0], "gyro_notch_cutoff": [150, 0]}
    more_lag, _ = gyro_filter_lag_s(more)
    dyn_notch, _ = gyro_filter_lag_s({**more, "dyn_notch_count": 3})
    assert lag < more_lag < dyn_notch and lower > 1.9 * lag
    dynamic = {**only_pt1, "gyro_lpf1_dyn_hz": [250, 500]}
    at_min, what = gyro_filter_lag_s(dynamic)
    at_hover, how = gyro_filter_lag_s(dynamic, hover_throttle=0.73)  # 457.1 Hz (pid_betaflight.json)
    assert at_min == pytest.approx(1 / (2 * math.pi * 250), rel=0.02) and "minimum" in what
    assert at_hover == pytest.approx(1 / (2 * math.pi * 457.1375), rel=0.02) and "457.1 Hz" in how
    averaged, _ = gyro_filter_lag_s({**only_pt1, "pid_process_denom": 4})  # 4 samples averaged: 1.5 of them
    assert averaged - lag == pytest.approx(1.5 * 125e-6, rel=0.1)


def test_a_3_2_header() -> None:
    """3.2's names (rc_rate, rc_expo_yaw), a FIR gyro lowpass (its tune: test_blackbox_tune)."""
    assert logged_interval_s(V32) == pytest.approx(0.001)  # 1 of 4 PID loops, each 2 gyro loops of 125 µs
    lag, what = gyro_filter_lag_s(V32)
    assert lag == pytest.approx(79 / 2 / 8000, rel=1e-3) and "FIR 100 Hz" in what  # an 80-sample average
    full = stick_setpoint_dps(V32, np.array([[500, -500, 500]]))
    assert full[0] == pytest.approx([200 / 0.3, -200 / 0.3, 200 / 0.4])


def test_stick_rates_of_the_cs110(cs110: dict) -> None:
    stick = np.linspace(-500, 500, 1001)[:, None].repeat(3, axis=1)
    rates = stick_setpoint_dps(cs110, stick, CS110)
    assert np.all(np.abs(rates) <= 2000) and np.allclose(rates, -rates[::-1])
    assert np.all(np.diff(rates, axis=0) > 0)
    # rcRate 140, rcExpo 10, super rate 70: full stick 200 x 1.4 / (1 - 0.7); yaw rcYawRate 120, no expo
    assert rates[-1] == pytest.approx([200 * 1.4 / 0.3, 200 * 1.4 / 0.3, 200 * 1.2 / 0.3])
    logged = _frames(CS110, ["rcCommand[0]", "rcCommand[1]", "rcCommand[2]"], 3000)
    assert np.all(np.abs(stick_setpoint_dps(cs110, logged)) < 1000)


def test_stick_rates_of_each_rates_type() -> None:
    x = np.linspace(-1, 1, 201)
    stick = np.stack([x * 500] * 3, axis=1)
    actual_rates = {**BF46, "rc_rates": [20, 20, 20], "rc_expo": [50, 50, 50]}  # centre 200, max 670 deg/s
    actual = stick_setpoint_dps(actual_rates, stick)
    near_centre = stick_setpoint_dps(actual_rates, np.array([[0.05, 0.05, 0.05]]))[0]
    assert near_centre / (0.05 / 500) == pytest.approx([200, 200, 200], rel=5e-4)
    assert actual[-1] == pytest.approx([670, 670, 670]) and actual[150, 0] < 0.5 * (200 + 670) / 2
    deadband = stick_setpoint_dps({**BF46, "deadband": 10, "yaw_deadband": 20}, np.array([[490, -490, 480]]))
    assert deadband[0] == pytest.approx([670, -670, 670])  # 4.2+ divide by 500 - deadband
    for kind in (0, 1, 2, 4):
        rates = stick_setpoint_dps({**BF46, "rates_type": kind, "rc_rates": [100] * 3, "rc_expo": [20] * 3,
                                    "rates": [70] * 3}, stick)
        assert np.allclose(rates, -rates[::-1]) and np.all(np.diff(rates[:, 0]) > 0), kind
        assert 300 < rates[-1, 0] <= 1998, kind
    boosted = stick_setpoint_dps({**BF46, "rates_type": 0, "rc_rates": [250] * 3, "rc_expo": [0] * 3,
                                  "rates": [0] * 3}, np.array([[50, 50, 50]]))
    assert boosted[0] == pytest.approx([200 * (2.5 + 14.54 * 0.5) * 0.1] * 3)  # rc rate above 2
    with pytest.raises(LogError, match="rates_type 7"):
        stick_setpoint_dps({**BF46, "rates_type": 7}, stick)


def test_stick_rates_match_the_gecko_logged_setpoint(gecko: dict) -> None:
    fields = [f"rcCommand[{i}]" for i in range(3)] + [f"setpoint[{i}]" for i in range(3)]
    frames = _frames(GECKO, fields, 20000)
    assert np.abs(frames[:, 3:]).max() > 50  # the sticks moved
    error = stick_setpoint_dps(gecko, frames[:, :3], GECKO) - frames[:, 3:]
    assert np.percentile(np.abs(error), 99) < 1.0  # both rounded to whole deg/s and rcCommand units


def test_yaw_motors_reversed(gecko: dict, cs110: dict) -> None:
    assert yaw_motors_reversed(gecko) is None and yaw_motors_reversed(cs110) is None
    assert yaw_motors_reversed({**BF46, "yaw_motors_reversed": 1}) is True
    assert yaw_motors_reversed({**BF46, "yaw_motors_reversed": "OFF"}) is False
