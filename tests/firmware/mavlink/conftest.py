"""Start `fcemu sitl` for real, on free loopback ports, and talk to it as a peer would."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]


# pymavlink listeners bound to port 0 before the SITL starts, by port: a port the kernel gave us
# and we still hold cannot be taken by another test or process in the meantime.
_LISTENERS: dict[int, object] = {}


def free_udp_port() -> int:
    """A free port for a peer that binds it itself (MAVProxy, MAVSDK): probed, then released."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def listen() -> int:
    """Bind a pymavlink GCS connection on a kernel-chosen loopback port; `connect(port)` takes it."""
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255)
    port = conn.port.getsockname()[1]
    _LISTENERS[port] = conn
    return port


@dataclass
class SitlProcess:
    proc: subprocess.Popen
    gcs_port: int
    offboard_port: int
    params: Path
    tlog: Path
    output: str = ""

    def stop(self, timeout: float = 15.0) -> str:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        try:
            out, err = self.proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, err = self.proc.communicate()
        self.output = out + err
        return self.output


def start_sitl(tmp_path: Path, *extra: str, speed: str = "realtime", rig: str = "free",
               controller: str = "pid", duration: float = 120.0, gcs: int | None = None,
               offboard: int | None = None) -> SitlProcess:
    """`fcemu sitl` sending to `gcs` and `offboard` (default: fresh pymavlink listeners)."""
    gcs = gcs if gcs is not None else listen()
    offboard = offboard if offboard is not None else listen()
    params = tmp_path / "params.json"
    tlog = tmp_path / f"session{len(list(tmp_path.glob('session*.tlog')))}.tlog"
    cmd = [sys.executable, "-m", "fcemu.cli", "sitl", "--controller", controller, "--rig", rig,
           "--speed", speed, "--quiet", "--duration", str(duration), "--gcs", f"127.0.0.1:{gcs}",
           "--offboard", f"127.0.0.1:{offboard}", "--params", str(params), "--tlog", str(tlog), *extra]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    return SitlProcess(proc, gcs, offboard, params, tlog)


@pytest.fixture
def sitl(tmp_path):
    started: list[SitlProcess] = []

    def factory(*extra: str, **kw) -> SitlProcess:
        s = start_sitl(tmp_path, *extra, **kw)
        started.append(s)
        return s

    yield factory
    for s in started:
        s.stop()
        for port in (s.gcs_port, s.offboard_port):
            conn = _LISTENERS.pop(port, None)
            if conn is not None:
                conn.close()


def connect(port: int, timeout: float = 30.0, source_system: int = 255, source_component: int = 0):
    """A pymavlink GCS listening where the vehicle sends (its udpout), once the first HEARTBEAT is in."""
    from pymavlink import mavutil

    conn = _LISTENERS.pop(port, None)
    if conn is None:
        conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=source_system,
                                          source_component=source_component)
    conn.source_system = conn.mav.srcSystem = source_system
    conn.source_component = conn.mav.srcComponent = source_component
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if conn.wait_heartbeat(timeout=1.0) is not None:
            return conn
    raise TimeoutError(f"no HEARTBEAT on {port} within {timeout} s")


def wait_for(conn, kind: str, cond=lambda m: True, timeout: float = 10.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        msg = conn.recv_match(type=kind, blocking=True, timeout=0.2)
        if msg is not None and cond(msg):
            return msg
    raise TimeoutError(f"no {kind} matching within {timeout} s")


def read_param(conn, name: bytes, timeout: float = 10.0):
    """The PARAM_VALUE for `name`, the request sent again each second until it comes, as a GCS does
    (MAVLink's parameter protocol retries an unanswered read: a datagram can be lost on a busy host)."""
    deadline = time.monotonic() + timeout
    while (left := deadline - time.monotonic()) > 0:
        conn.mav.param_request_read_send(1, 1, name, -1)
        try:
            return wait_for(conn, "PARAM_VALUE", lambda m: m.param_id == name.decode(), min(1.0, left))
        except TimeoutError:
            continue
    raise TimeoutError(f"no PARAM_VALUE for {name.decode()} within {timeout} s")


def command(conn, cmd: int, *params: float, timeout: float = 5.0):
    p = [*params, 0, 0, 0, 0, 0, 0, 0][:7]
    conn.mav.command_long_send(conn.target_system, 1, cmd, 0, *p)
    return wait_for(conn, "COMMAND_ACK", lambda m: m.command == cmd, timeout)
