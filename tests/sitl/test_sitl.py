"""The one line that says which controller flies, and which instances spin on a CPU of their own."""

from __future__ import annotations

import json
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


def test_a_policy_or_pid_not_made_for_the_airframe_is_refused_in_one_line(untuned_airframe: Path) -> None:
    for controller in ([], ["--controller", "pid"]):
        done = subprocess.run([sys.executable, "-m", "fcemu", "sitl", "--airframe", str(untuned_airframe),
                               "--no-mavlink", "--speed", "max", "--duration", "1", *controller],
                              capture_output=True, text=True, timeout=60)
        assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
        assert done.stderr.startswith("fcemu: error: ")
        assert "my_quad" in done.stderr


def test_json_prints_the_flight_s_summary_as_one_object() -> None:
    done = subprocess.run([sys.executable, "-m", "fcemu", "sitl", "--no-mavlink", "--quiet", "--speed", "max",
                           "--duration", "0.2", "--controller", "pid", "--json"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert (summary["controller"], summary["rig"], summary["airframe"]) == ("pid", "free", "iris")
    assert summary["timing"]["ticks"] == 200 and summary["ulog"] is None and "vehicle" not in summary


def test_a_policy_that_names_its_pid_flies_over_it_unless_told_otherwise(tmp_path, capsys) -> None:
    from fcemu.cli import main
    from fcemu.firmware.controllers import load_controller
    from tests.evaluation.test_evaluate import policy_naming_its_pid

    policy = str(policy_naming_its_pid(tmp_path / "fit"))
    named = load_controller(f"pid:{tmp_path / 'fit' / 'pid.json'}").gains
    assert named != load_controller("pid:iris").gains
    for fallback, gains in ((None, named), ("pid", load_controller("pid:iris").gains),
                            ("pid:betaflight", load_controller("pid:betaflight").gains)):
        built = sitl.build_sitl(policy, rig="rig", realtime=False, fallback=fallback)
        assert built.selected == "neural" and built.loop.controllers["pid"].gains == gains
    (tmp_path / "fit" / "pid.json").unlink()
    assert main(["sitl", "--controller", policy, "--rig", "rig", "--no-mavlink", "--speed", "max",
                 "--duration", "0.1", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fcemu: error: ") and err.count("\n") == 1
    assert f"names its fallback PID {tmp_path / 'fit' / 'pid.json'}, which is missing" in err
