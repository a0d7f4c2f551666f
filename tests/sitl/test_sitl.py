"""The one line that says which controller flies, and which instances spin on a CPU of their own."""

from __future__ import annotations

import os
from pathlib import Path

import firmware.controllers
from firmware.controllers import DEFAULT_POLICY, default_controller
from sitl import sitl


def test_the_shipped_policy_is_package_data_and_flies_by_default() -> None:
    assert DEFAULT_POLICY.is_file()
    assert DEFAULT_POLICY.parent == Path(firmware.controllers.__file__).parent / "policies"
    assert default_controller() == str(DEFAULT_POLICY)
    assert sitl.flying_line(default_controller()) == f"fcemu: flying neural:iris_rate_ppo ({DEFAULT_POLICY})"


def test_without_a_policy_the_line_says_the_pid_flies_and_why(monkeypatch, tmp_path) -> None:
    missing = tmp_path / "iris_rate_ppo.onnx"
    monkeypatch.setattr(firmware.controllers, "DEFAULT_POLICY", missing)
    assert firmware.controllers.default_controller() == "pid"
    assert sitl.flying_line("pid") == f"fcemu: flying pid (no policy found at {missing})"
    assert sitl.flying_line("pid:paper") == "fcemu: flying pid:paper"


def test_instance_zero_owns_a_core_and_more_only_with_cpus_to_spare(monkeypatch) -> None:
    monkeypatch.setattr(os, "sched_getaffinity", lambda _pid: {0, 1})
    assert [sitl.owns_a_core(n) for n in range(3)] == [True, False, False]
    monkeypatch.setattr(os, "sched_getaffinity", lambda _pid: set(range(8)))
    assert [sitl.owns_a_core(n) for n in range(5)] == [True, True, True, True, False]
