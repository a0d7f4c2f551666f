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
