"""MAVProxy, run without a human at its prompt, against the real SITL: connect, switch mode, arm,
read and set a parameter. The vehicle side is checked by a second peer and the params file."""

from __future__ import annotations

import json
import os
import queue
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as M

from tests.firmware.mavlink.conftest import connect, free_udp_port, wait_for

MAVPROXY = Path(sys.executable).parent / "mavproxy.py"
pytestmark = [pytest.mark.timeout(120),
              pytest.mark.skipif(not MAVPROXY.exists(), reason="MAVProxy is not installed in this venv")]


class Console:
    """MAVProxy's stdin and stdout: type a line, wait for a pattern in what it prints."""

    def __init__(self, port: int, cwd: Path) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, str(MAVPROXY), f"--master=udpin:127.0.0.1:{port}", "--no-state"],
            cwd=cwd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"}, bufsize=1)
        self.text = ""
        self._seen = 0
        self._chunks: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._chunks.put(line)

    def type(self, line: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def expect(self, pattern: str, timeout: float = 15.0) -> re.Match:
        """The first match of `pattern` after the previous expectation's match."""
        deadline = time.monotonic() + timeout
        while True:
            m = re.compile(pattern).search(self.text, self._seen)
            if m is not None:
                self._seen = m.end()
                return m
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"MAVProxy never printed {pattern!r}; it printed:\n{self.text[-3000:]}")
            try:
                self.text += self._chunks.get(timeout=min(left, 0.2))
            except queue.Empty:
                pass

    def param(self, name: str, until: float | None = None, timeout: float = 10.0) -> float:
        """`param show NAME` (again, until it shows `until`: MAVProxy learns of changes asynchronously)."""
        deadline = time.monotonic() + timeout
        while True:
            self.type(f"param show {name}")
            value = float(self.expect(rf"{name}\s+(-?[0-9.]+)").group(1))
            if until is None or value == pytest.approx(until) or time.monotonic() > deadline:
                return value
            time.sleep(0.2)

    def close(self) -> str:
        if self.proc.poll() is None:
            try:
                assert self.proc.stdin is not None
                self.proc.stdin.close()  # MAVProxy quits at the end of its input ('exit' it does not know)
                self.proc.wait(10)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait()
        return self.text


def px4_mode(hb) -> str:
    return mavutil.interpret_px4_mode(hb.base_mode, hb.custom_mode)


def test_mavproxy_switches_mode_arms_and_sets_a_parameter(sitl, tmp_path) -> None:
    gcs_port = free_udp_port()  # MAVProxy binds it; the offboard port is our own observer
    s = sitl(gcs=gcs_port)
    observer = connect(s.offboard_port)
    mp = Console(gcs_port, tmp_path)
    try:
        mp.expect(r"Detected vehicle 1:1", timeout=30)
        mp.expect(r"Received \d+ parameters", timeout=20)  # the full list, promptly (FTP is refused)
        # `mode ACRO` fails inside MAVProxy 1.8 for PX4 vehicles (it passes pymavlink's px4_map tuple
        # as a number); DO_SET_MODE with the PX4 custom main mode is what it sends when it works.
        mp.type("long DO_SET_MODE 1 5 0")
        mp.expect(r"DO_SET_MODE: ACCEPTED")
        wait_for(observer, "HEARTBEAT", lambda m: px4_mode(m) == "ACRO", timeout=5)
        mp.type("arm throttle")
        mp.expect(r"COMPONENT_ARM_DISARM: ACCEPTED")
        wait_for(observer, "HEARTBEAT", lambda m: m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED, timeout=5)

        assert mp.param("COM_OF_LOSS_T") == pytest.approx(0.5)
        mp.type("param set COM_OF_LOSS_T 1.5")
        assert wait_for(observer, "PARAM_VALUE", lambda m: m.param_id == "COM_OF_LOSS_T",
                        timeout=5).param_value == pytest.approx(1.5)
        assert mp.param("COM_OF_LOSS_T", until=1.5) == pytest.approx(1.5)  # MAVProxy saw it too
        mp.type("param set COM_OF_LOSS_T 100")  # outside its range: refused, value kept
        mp.expect(r"Param rejected: COM_OF_LOSS_T")

        mp.type("disarm")
        mp.expect(r"COMPONENT_ARM_DISARM: ACCEPTED")
        wait_for(observer, "HEARTBEAT", lambda m: not m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED, timeout=5)
    finally:
        mp.close()
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:  # saved atomically a moment after the change
        if s.params.exists() and json.loads(s.params.read_text()).get("COM_OF_LOSS_T") == 1.5:
            break
        time.sleep(0.1)
    assert json.loads(s.params.read_text())["COM_OF_LOSS_T"] == 1.5
