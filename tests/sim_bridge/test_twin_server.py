"""The twin server under a reset storm from another process: the owner keeps its session, a storm
cannot hold it. Real `fcemu twin serve`, real stormer process, real client, all on loopback."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from fcemu.sim_bridge.link import LinkError, RemoteError, UdpTwinClient, spawn_server
from fcemu.sim_bridge.protocol import encode_reset
from fcemu.sim_bridge.twin import Twin
from fcemu.sim_bridge.twin_server import SenderBudget, UdpTwinServer

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


def test_sender_budget_mutes_a_storm_until_it_is_quiet() -> None:
    budget = SenderBudget(rate_hz=10.0, burst=5.0, mute_s=1.0)
    a, b = ("127.0.0.1", 1), ("127.0.0.1", 2)
    assert all(budget.spend(a, 0.0) for _ in range(5))
    assert not budget.spend(a, 0.0) and budget.muted(a, 0.5)
    assert budget.spend(b, 0.5)  # per sender
    assert budget.muted(a, 1.4)  # still sending: the mute runs on
    assert not budget.muted(a, 2.5) and budget.spend(a, 2.5)
    assert all(budget.spend(b, 10.0 + i / 10.0) for i in range(100))  # 10/s forever is within budget


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
