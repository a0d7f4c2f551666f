"""The one line that says which controller flies, and which instances spin on a CPU of their own."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from fcemu.firmware import controllers
from fcemu.firmware.controllers import DEFAULT_POLICY, default_controller
from fcemu.sitl import sitl


def test_the_shipped_policy_is_package_data_and_flies_by_default() -> None:
    assert DEFAULT_POLICY.is_file()
    assert DEFAULT_POLICY.parent == Path(controllers.__file__).parent / "policies"
    assert default_controller() == str(DEFAULT_POLICY)
    assert sitl.flying_line(default_controller()) == f"fcemu: flying neural:iris_rate_ppo ({DEFAULT_POLICY})"


def test_without_a_policy_the_line_says_the_pid_flies_and_why(monkeypatch, tmp_path) -> None:
    missing = tmp_path / "iris_rate_ppo.onnx"
    monkeypatch.setattr(controllers, "DEFAULT_POLICY", missing)
    assert controllers.default_controller() == "pid"
    assert sitl.flying_line("pid") == f"fcemu: flying pid (no policy found at {missing})"
    assert sitl.flying_line("pid:paper") == "fcemu: flying pid:paper"


def test_instance_zero_owns_a_core_and_more_only_with_cpus_to_spare(monkeypatch) -> None:
    monkeypatch.setattr(os, "sched_getaffinity", lambda _pid: {0, 1})
    assert [sitl.owns_a_core(n) for n in range(3)] == [True, False, False]
    monkeypatch.setattr(os, "sched_getaffinity", lambda _pid: set(range(8)))
    assert [sitl.owns_a_core(n) for n in range(5)] == [True, True, True, True, False]


def test_sigint_stops_the_flight_with_its_summary_also_when_inherited_ignored() -> None:
    """A background job of a non-interactive shell starts with SIGINT ignored; `fcemu sitl` still
    stops on it and prints its summary."""
    command = [sys.executable, "-m", "fcemu", "sitl", "--no-mavlink", "--quiet", "--duration", "60"]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        first = proc.stderr.readline()  # printed once the controller is loaded, as the loop starts
        assert "flying" in first, first
        time.sleep(1.0)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, first + err
    assert "misses" in out


def test_the_twin_health_rules_hover_and_controllers_are_the_airframe_s() -> None:
    from fcemu.sim_bridge.airframe_spec import airframe_spec

    crazyflie = airframe_spec("crazyflie")
    built = sitl.build_sitl("pid:iris", rig="rig", realtime=False, airframe="crazyflie")
    assert built.airframe == crazyflie and built.twin.airframe.name == "crazyflie"
    assert built.loop.health.rules.rotor_speed_max == crazyflie.max_rotor_speed
    built.loop.run(0.5)
    sample = built.loop.last_sample
    assert sample.command.setpoint.throttle == crazyflie.hover_throttle
    assert sample.frame.rotor_speed.max() > 1100.0  # beyond the Iris's top speed: the crazyflie's rotors
    assert built.loop.health.policy_trusted and not built.loop.faults


def test_a_policy_or_pid_not_made_for_the_airframe_is_refused_in_one_line() -> None:
    for controller in ([], ["--controller", "pid"]):
        done = subprocess.run([sys.executable, "-m", "fcemu", "sitl", "--airframe", "x500",
                               "--no-mavlink", "--speed", "max", "--duration", "1", *controller],
                              capture_output=True, text=True, timeout=60)
        assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
        assert done.stderr.startswith("fcemu: error: ")
        assert "x500" in done.stderr
