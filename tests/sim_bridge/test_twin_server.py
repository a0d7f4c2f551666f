"""The twin server under a reset storm from another process: the owner keeps its session, a storm
cannot hold it. Real `fcemu twin serve`, real stormer process, real client, all on loopback."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from fcemu.firmware.health import HealthMonitor, HealthRules
from fcemu.firmware.sensors import SensorFrame
from fcemu.sim_bridge.airframe import load_airframe
from fcemu.sim_bridge.airframe_spec import airframe_spec
from fcemu.sim_bridge.fault_spec import parse_fault, session_faults
from fcemu.sim_bridge.link import (
    InProcessLink,
    LinkError,
    RemoteError,
    Transport,
    UdpTwinClient,
    spawn_server,
)
from fcemu.sim_bridge.protocol import (
    VERSION,
    Error,
    ErrorCode,
    decode,
    encode_error,
    encode_reset,
    peek_header,
)
from fcemu.sim_bridge.twin import Twin
from fcemu.sim_bridge.twin_server import UdpTwinServer
from tests.sim_bridge.link_rig import assert_identical, pwm_sequence

pytestmark = pytest.mark.timeout(90)
ROOT = Path(__file__).resolve().parents[2]

# Sends RESETs with fresh sequence numbers as fast as one Python process can, from `n_socks` sockets.
STORM = """
import socket, sys, time
from fcemu.sim_bridge.protocol import encode_reset
host, port, seconds, n_socks = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(n_socks)]
for s in socks:
    s.setblocking(False)
    s.connect((host, port))
packets = [encode_reset(seq, seed=1) for seq in range(1, 100_001)]
print("ready", flush=True)
sys.stdin.readline()
sent, end = 0, time.monotonic() + seconds
while time.monotonic() < end:
    s = socks[(sent // 1000) % n_socks]
    for p in packets[sent % 100_000: sent % 100_000 + 1000]:
        try:
            s.send(p)
        except (BlockingIOError, ConnectionRefusedError):
            pass
    sent += 1000
print(sent, flush=True)
"""


@pytest.fixture
def served() -> Iterator[tuple[str, int]]:
    proc, address = spawn_server(rig="rig")
    try:
        yield address
    finally:
        proc.terminate()
        proc.wait(10)


def storm(address: tuple[str, int], seconds: float, sockets: int = 1) -> subprocess.Popen:
    """A stormer process, ready to start on `go(proc)`."""
    args = [address[0], str(address[1]), str(seconds), str(sockets)]
    proc = subprocess.Popen([sys.executable, "-c", STORM, *args], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
    return proc


def go(proc: subprocess.Popen) -> subprocess.Popen:
    assert proc.stdin is not None
    proc.stdin.write("go\n")
    proc.stdin.flush()
    return proc


def fly(client: UdpTwinClient, seconds: float) -> int:
    """Step the twin for `seconds` of wall time; returns the steps taken (LinkTimeout propagates)."""
    hover, steps, end = np.full(4, 1500.0), 0, time.monotonic() + seconds
    while time.monotonic() < end:
        client.pwm_write(hover)
        steps += 1
    return steps


@pytest.mark.parametrize("sockets", [1, 50])
def test_a_reset_storm_does_not_starve_the_session_owner(served: tuple[str, int], sockets: int) -> None:
    stormer = storm(served, 2.5, sockets)
    with UdpTwinClient(*served, timeout=0.1, retries=20) as owner:
        owner.reset(seed=1)
        baseline = fly(owner, 0.5)
        go(stormer)
        try:
            under_storm = fly(owner, 2.0)  # a LinkTimeout here is the bug
        finally:
            stormer.wait(20)
        sent = int(stormer.stdout.read().strip())
        retries = owner.counters["retries"]
    print(f"storm: {sent} resets sent; steps {baseline} in 0.5 s alone, {under_storm} in 2 s under the storm")
    assert sent > 20_000, "the stormer did not storm"
    # CPU is shared with the storm, so the rate may drop; what must not happen is the owner's
    # requests being lost behind the storm (each loss costs a 100 ms retry).
    assert under_storm > 0.02 * baseline * 4 and retries <= 5 + 0.01 * under_storm, (baseline, under_storm,
                                                                                      retries)


def test_a_storm_started_first_cannot_hold_the_session(served: tuple[str, int]) -> None:
    stormer = go(storm(served, 6.0))  # longer than the late client may take; stopped once it flew
    try:
        time.sleep(0.5)  # the storm has the session now (today: for as long as it storms)
        with UdpTwinClient(*served, timeout=0.1, retries=20) as late:
            deadline, last = time.monotonic() + 3.0, None
            while time.monotonic() < deadline:
                try:
                    late.reset(seed=1)
                    break
                except (RemoteError, LinkError) as exc:  # BUSY while the storm is being judged
                    last = exc
                    time.sleep(0.1)
            else:
                pytest.fail(f"the session stayed with the stormer: {last}")
            assert fly(late, 1.0) > 50
        assert stormer.poll() is None, "the storm ended before the late client flew"
    finally:
        stormer.terminate()
        stormer.wait(20)


def test_an_owner_that_storms_resets_loses_its_session() -> None:
    with UdpTwinServer(Twin(rig="rig"), session_timeout=60.0) as srv, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as stormer, \
            UdpTwinClient(*srv.address, timeout=0.05, retries=40) as other:
        stormer.connect(srv.address)
        stormer.settimeout(2.0)
        stormer.send(encode_reset(1, seed=1))
        stormer.recv(2048)
        seq, deadline = 1, time.monotonic() + 10.0
        while srv.counters["revoked"] == 0 and time.monotonic() < deadline:
            for _ in range(100):  # 100 resets per ms or so: a storm, yet paced to fit the receive buffer
                seq += 1
                stormer.send(encode_reset(seq, seed=1))
            time.sleep(0.001)
        assert srv.counters["revoked"] == 1 and srv.counters["shed"] > 0
        assert other.reset(seed=1).t_us == 0 and other.pwm_write(np.full(4, 1500.0)).t_us == 1000


def test_a_second_server_cannot_take_a_port_in_use() -> None:
    with UdpTwinServer(Twin(rig="rig")) as srv:
        with pytest.raises(OSError):  # SO_REUSEPORT must not let it share (and split) the traffic
            UdpTwinServer(Twin(rig="rig"), port=srv.address[1])
        with UdpTwinClient(*srv.address, timeout=0.5) as client:
            client.reset(seed=1)
            client.pwm_write(np.full(4, 1500.0))


# --- faults on the server's side: the frames' ages cross the link --------------------------------

FAULTS = ("esc-telemetry:1:off", "gyro:intermittent:20%")


def faulted_run(link: Transport, pwms: np.ndarray, seed: int) -> list[SensorFrame]:
    return [link.reset(seed)] + [link.pwm_write(p) for p in pwms]


def faulted_twin(specs: tuple[str, ...], seed: int) -> InProcessLink:
    """The in-process twin with the faults a server's session starts with."""
    twin = Twin(rig="rig")
    twin.faults = session_faults(twin, [parse_fault(s) for s in specs], seed)
    return InProcessLink(twin)


def test_a_faulted_session_is_the_in_process_twin_ages_included() -> None:
    pwms = pwm_sequence(200)
    faults = [parse_fault(s) for s in FAULTS]
    with UdpTwinServer(Twin(rig="rig"), faults=faults) as srv, \
            UdpTwinClient(*srv.address, timeout=0.5) as client:
        first = faulted_run(client, pwms, 7)
        again = faulted_run(client, pwms[:50], 7)  # a RESET starts the faults over
    expected = faulted_run(faulted_twin(FAULTS, 7), pwms, 7)
    assert_identical(first, expected)
    assert_identical(again, expected[:51])
    rotor_ages = np.array([f.rotor_speed_age_us() for f in first])
    assert rotor_ages[:, 0].tolist() == [1000 * k for k in range(201)]  # motor 1 off: its last time stays
    assert not rotor_ages[:, 1:].any()
    gyro_ages = [f.gyro_age_us() for f in first]
    assert max(gyro_ages) >= 2000 and gyro_ages.count(0) > 100  # a lost gyro sample keeps its time


def verdicts(link: Transport, pwms: np.ndarray) -> tuple[dict[str, int], str, list[tuple[int, str]]]:
    """The firmware's health monitor on `link`'s frames: each tick's frame with the PWM written before it."""
    monitor = HealthMonitor(HealthRules.for_airframe(airframe_spec(load_airframe("iris"))))
    frame, written = link.reset(3), pwms[0]
    for pwm in pwms:
        monitor.check(frame, written)
        frame, written = link.pwm_write(pwm), pwm
    return monitor.detected, monitor.handover, monitor.outbox


def test_fcemu_twin_serve_fault_reaches_the_health_monitor_across_the_link() -> None:
    """`fcemu twin serve --fault esc-telemetry:2:delayed:25ms`: the client's health monitor sees motor 2's
    telemetry arrive 25 ms old and hands the policy over on the tick it does in-process (a frame without
    its age looks fresh: the same monitor would call the late reading implausible, 3 ticks earlier)."""
    late = "esc-telemetry:2:delayed:25ms"
    pwms = 1500.0 + 50.0 * np.sin(np.arange(120)[:, None] * 0.05 + np.arange(4))
    proc, address = spawn_server(rig="rig", faults=[late])
    try:
        with UdpTwinClient(*address, timeout=0.5) as client:
            remote = verdicts(client, pwms)
    finally:
        proc.terminate()
        proc.wait(10)
    assert remote == verdicts(faulted_twin((late,), 3), pwms)
    assert remote[:2] == ({"handover": 22}, "rotor speed 2 too old")


def test_fcemu_twin_serve_json_prints_its_summary_when_stopped() -> None:
    """With --json the line saying where it listens goes to stderr, and stdout carries one JSON object."""
    command = [sys.executable, "-m", "fcemu", "twin", "serve", "--port", "0", "--quiet", "--json"]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL,
                            text=True)
    try:
        line = ""
        while "udp://" not in line:
            line = proc.stderr.readline()
            assert line, "fcemu twin serve --json exited before it listened"
        host, port = line.rsplit("udp://", 1)[1].strip().rsplit(":", 1)
        with UdpTwinClient(host, int(port), timeout=0.5) as client:
            client.reset(seed=1)
            for _ in range(5):
                client.pwm_write(np.full(4, 1500.0))
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=10)
    assert proc.returncode == 0
    summary = json.loads(out)
    assert (summary["airframe"], summary["rig"], summary["steps"]) == ("iris", "rig", 5)
    assert summary["address"] == f"udp://{host}:{port}" and summary["bad_packets"] == 0


# --- peers of another protocol version: one clear line, at once ----------------------------------


def test_a_client_of_another_version_is_refused_in_its_own_version() -> None:
    old_reset = bytearray(encode_reset(5, seed=1))
    old_reset[4] = VERSION - 1
    with UdpTwinServer(Twin(rig="rig")) as srv, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as old:
        old.settimeout(2.0)
        old.sendto(old_reset, srv.address)
        reply = old.recv(2048)
    assert reply[4] == VERSION - 1  # so a client of that version reads the refusal as an ERROR
    assert decode(reply[:4] + bytes([VERSION]) + reply[5:]) == Error(
        5, ErrorCode.BAD_VERSION, f"protocol version {VERSION - 1}, this end speaks {VERSION}")


def test_a_server_of_another_version_is_named_at_once() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as old_server:
        old_server.bind(("127.0.0.1", 0))
        old_server.settimeout(2.0)
        with UdpTwinClient(*old_server.getsockname(), timeout=1.0, retries=5) as client:
            worker = threading.Thread(target=lambda: refuse(old_server))
            worker.start()
            start = time.monotonic()
            expected = f"speaks protocol version {VERSION - 1}, this client {VERSION}"
            with pytest.raises(LinkError, match=expected):
                client.reset(seed=1)
            worker.join(5)
            assert time.monotonic() - start < 0.5 and client.counters["retries"] == 0


def refuse(sock: socket.socket) -> None:
    """Answer one request as a server of the previous version does."""
    request, addr = sock.recvfrom(2048)
    sock.sendto(encode_error(peek_header(request)[1], ErrorCode.BAD_VERSION,
                             f"protocol version {VERSION}, this end speaks {VERSION - 1}", VERSION - 1), addr)
