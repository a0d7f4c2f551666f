"""Betaflight 4.6 built with the shipped policy (`fcemu export --target betaflight`) on the rig:
NEURAL on, the policy flies (its first answers are fcemu's C policy's); off, Betaflight's PID.
With the twin's ESC telemetry losing frames NEURAL flies on; with a motor's telemetry stopped it
hands over to the PID at the first tick past neural_esc_max_age_ms, with the gyro stopped at the
first tick past neural_gyro_max_age_ms, with the telemetry 5 ms late once its lag rule has fitted
it past neural_esc_max_lag_us."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from fcemu.cli import main
from fcemu.evaluation.betaflight_crosscheck import check_clock
from fcemu.export.betaflight.build import BetaflightExportError, betaflight_source, export_betaflight
from fcemu.firmware.c_policy import CPolicyController
from fcemu.firmware.controller import RateSetpoint
from fcemu.firmware.sensors import SensorFrame
from fcemu.sim_bridge.betaflight_link import pack_fdm, unpack_fdm
from fcemu.sim_bridge.twin import Twin
from fcemu.sitl.betaflight import BetaflightFlight
from fcemu.sitl.betaflight_health import SCENARIOS, fly_scenarios
from fcemu.sitl.betaflight_process import BetaflightError, neural_firmware, port_in_use
from fcemu.sitl.betaflight_rc import RcMap
from fcemu.sitl.traces import Traces
from tests.export.mcu_tools import SHIPPED, require_codegen

pytestmark = pytest.mark.quiet_machine

try:
    betaflight_source()
except BetaflightExportError as exc:
    pytest.skip(f"Betaflight source unavailable: {exc}", allow_module_level=True)

HOVER = 0.745
TICKS = 500


@pytest.fixture(scope="module")
def firmware(tmp_path_factory):
    require_codegen()
    if shutil.which("gcc") is None:
        pytest.skip("no gcc to build the SITL")
    out = tmp_path_factory.mktemp("betaflight_neural_sitl")
    export_betaflight(SHIPPED, out, ["SITL"], parity_samples=1000)
    return neural_firmware(out)


@pytest.fixture
def _no_other_sitl():
    if port_in_use(5761):
        pytest.fail("another Betaflight SITL holds TCP 5761; its UDP ports would take our packets")


def _fly(firmware, run_dir, neural: bool, step: np.ndarray):
    rc = RcMap()
    rate, pwm = np.zeros((TICKS, 3)), np.zeros((TICKS, 4))
    with BetaflightFlight(run_dir, Twin(rig="rig"), rc, speed=0.25, firmware=firmware,
                          neural=neural) as flight:
        flight.fly_episode(step, rc.throttle_channel(HOVER), TICKS, rate, pwm)
        throttle = rc.fcemu_throttle(rc.throttle_channel(HOVER))
    return rate, pwm, throttle


def _c_policy_first_answer(firmware, step: np.ndarray, throttle: float) -> np.ndarray:
    """fcemu's C policy on the first recorded tick (the twin at rest, the step commanded)."""
    twin = Twin(rig="rig")
    frame = twin.reset()
    policy = CPolicyController(firmware.policy_dir)
    at_rest = SensorFrame(frame.t_us, np.zeros(3), frame.accel, frame.rotor_speed)
    return policy.update(RateSetpoint(step, throttle), at_rest, 1e-3)


@pytest.mark.slow
def test_neural_on_the_policy_tracks_a_roll_step_and_off_the_pid_does(firmware, tmp_path, _no_other_sitl):
    step = RcMap().quantise(np.array([2.0, 0.0, 0.0]))
    for neural in (True, False):
        rate, pwm, throttle = _fly(firmware, tmp_path / f"neural_{neural}", neural, step)
        reached = np.flatnonzero(rate[:, 0] >= 0.9 * step[0])
        assert reached.size and reached[0] < 150, f"NEURAL {neural}: roll rate not at 90 % within 150 ms"
        assert np.abs(rate[-100:, 0] - step[0]).mean() < 0.1 * step[0], f"NEURAL {neural}: no tracking"
        first = _c_policy_first_answer(firmware, step, throttle)
        if neural:  # the policy flew: Betaflight's first answer is the C policy's (to its 1 µs output)
            assert np.abs(pwm[0] - first).max() <= 1.5
        else:  # Betaflight's PID answers the step differently
            assert np.abs(pwm[0] - first).max() > 20.0


@pytest.fixture(scope="module")
def telemetry_faults(firmware, tmp_path_factory):
    """Fault-free, 1 % and 5 % of the rpm frames lost, the rpm 5 ms late, motor 1's telemetry or the
    gyro stopped at tick 100."""
    if port_in_use(5761):
        pytest.fail("another Betaflight SITL holds TCP 5761; its UDP ports would take our packets")
    names = ("fault-free", "esc-telemetry:intermittent:1%", "esc-telemetry:intermittent:5%",
             "esc-telemetry:delayed:5ms", "esc-telemetry:1:off at 100 ms", "gyro:off at 100 ms")
    scenarios = tuple(s for s in SCENARIOS if s.name in names)
    rows = fly_scenarios(firmware.directory, tmp_path_factory.mktemp("telemetry_faults"), scenarios)
    return {row["scenario"]: row for row in rows}


@pytest.mark.slow
def test_lost_rpm_frames_are_held_and_neural_flies_on(telemetry_faults):
    clean = telemetry_faults["fault-free"]
    assert clean["dropped"] == "" and clean["max_loss_rate"] == 0.0
    assert clean["max_lag_us"] < 3000  # the link's step (1.2 ms): never past neural_esc_max_lag_us
    for lost in ("esc-telemetry:intermittent:1%", "esc-telemetry:intermittent:5%"):
        row = telemetry_faults[lost]
        assert row["dropped"] == "" and row["state"] == "flying", row
        # the SITL runs in real time: under load it may merge two simulator steps into one loop
        # (neither controller flies the missed one), so a step or two short of every tick is no drop
        assert row["policy_ticks"] >= TICKS - 5, row
        assert 0.0 < row["max_loss_rate"] < 0.2  # frames were lost, below neural_esc_loss_max
        assert row["roll_error_rad_s"] <= 1.3 * clean["roll_error_rad_s"], row


@pytest.mark.slow
def test_rpm_telemetry_5_ms_late_is_found_and_read_ahead_and_neural_flies_on(telemetry_faults):
    row, clean = telemetry_faults["esc-telemetry:delayed:5ms"], telemetry_faults["fault-free"]
    assert row["max_lag_us"] > 4000, row  # found: 5 ms and the link's step, past neural_esc_max_lag_us
    assert row["dropped"] == "" and row["state"] == "flying" and row["policy_ticks"] >= TICKS - 5, row
    # read ahead by the model, the policy tracks as it does on time (late and not read ahead: 31x)
    assert row["roll_error_rad_s"] <= 2.0 * clean["roll_error_rad_s"], row
    # every frame arrives 5 ticks late (fewer loop ticks where the real-time SITL merged simulator steps
    # under load): an age, under the age limit
    assert 1 <= row["max_rpm_age_ticks"] < 20, row


@pytest.mark.slow
def test_a_motor_whose_telemetry_stops_drops_neural_past_the_age_limit(telemetry_faults):
    row = telemetry_faults["esc-telemetry:1:off at 100 ms"]
    assert row["dropped"] == "rpm too old" and row["state"] == "rpm too old", row
    assert row["max_rpm_age_ticks"] == 21  # the first tick past 20 ms (neural_esc_max_age_ms)
    # the fault is injected at a simulator step and the drop counted in Betaflight's loop ticks since
    # NEURAL came on: where the real-time SITL merged steps under load before the fault, its count runs
    # a few behind the steps; where NEURAL came on only after the fault (its switch read late on a slow
    # start), the telemetry was already lost and the drop is its first tick past the age limit
    after = row["dropped_after_ticks"]
    assert after - row["fault_at_tick"] <= 22, row
    assert after - row["fault_at_tick"] >= 20 - 5 or after == 20, row


def test_the_extended_fdm_packet_carries_the_rotor_speeds_in_rpm():
    rotor = np.array([500.0, 600.0, 700.0, 800.0])
    plain = pack_fdm(1.0, [0.1, 0.2, 0.3], [0.0, 0.0, -9.8], [1.0, 0.0, 0.0, 0.0])
    extended = pack_fdm(1.0, [0.1, 0.2, 0.3], [0.0, 0.0, -9.8], [1.0, 0.0, 0.0, 0.0], rotor_speed=rotor)
    assert len(plain) == 144 and len(extended) == 176 and extended[:144] == plain
    assert unpack_fdm(extended)["rotor_rpm"] == pytest.approx(rotor * 60.0 / (2.0 * np.pi))


def _episodes_with_drift(drift: list[float]) -> Traces:
    n = len(drift)
    return Traces(np.arange(3) * 1e-3, np.zeros((n, 3, 3)), np.zeros((n, 3, 3)), np.zeros((n, 3, 4)),
                  controller="betaflight", task="episodic", extra={"clock_drift_per_episode": drift})


def test_a_run_whose_sitl_clock_drifted_is_refused_and_one_that_kept_time_is_not():
    kept = check_clock(_episodes_with_drift([0.01, -0.02, 0.03]), speed=0.25)
    assert kept["median"] == 0.02 and kept["max"] == 0.03
    with pytest.raises(BetaflightError, match=r"drifted .* --speed 0.5"):
        check_clock(_episodes_with_drift([0.18, 0.2, 0.25]), speed=1.0)
    with pytest.raises(BetaflightError, match="episode 1"):
        check_clock(_episodes_with_drift([0.01, 0.3, 0.02]), speed=0.25)


def test_fcemu_betaflight_rejects_a_directory_that_is_not_an_export(tmp_path, capsys):
    assert main(["betaflight", "--firmware", str(tmp_path), "--episodes", "1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fcemu: error: ") and "not a Betaflight export" in err


@pytest.mark.slow
def test_a_gyro_that_stops_drops_neural_past_its_age_limit(telemetry_faults):
    row = telemetry_faults["gyro:off at 100 ms"]
    assert row["dropped"] == "gyro too old" and row["max_rpm_age_ticks"] == 0, row
    # 11: past 10 ms; counted in Betaflight's loop ticks, which run a few behind the simulator's steps
    # where the real-time SITL merged steps under load before the fault (as for the rpm's age above)
    assert 10 - 5 <= row["dropped_after_ticks"] - row["fault_at_tick"] <= 12, row
