"""The sender budget and the muted senders' own queues, on real loopback sockets."""

from __future__ import annotations

import socket
import time

import pytest

from fcemu.sim_bridge.sender_guard import PEER_QUEUES, MutedQueues, SenderBudget, reuse_port_socket


def test_sender_budget_mutes_a_storm_until_it_is_quiet() -> None:
    budget = SenderBudget(rate_hz=10.0, burst=5.0, mute_s=1.0)
    a, b = ("127.0.0.1", 1), ("127.0.0.1", 2)
    assert all(budget.spend(a, 0.0) for _ in range(5))
    assert not budget.spend(a, 0.0) and budget.muted(a, 0.5)
    assert budget.spend(b, 0.5)  # per sender
    assert budget.muted(a, 1.4)  # still sending: the mute runs on
    assert not budget.muted(a, 2.5) and budget.spend(a, 2.5)
    assert all(budget.spend(b, 10.0 + i / 10.0) for i in range(100))  # 10/s forever is within budget


def _received(sock: socket.socket) -> list[bytes]:
    out = []
    while True:
        try:
            out.append(sock.recv(64, socket.MSG_DONTWAIT))
        except BlockingIOError:
            return out


@pytest.mark.skipif(not PEER_QUEUES, reason="a queue per peer needs Linux's SO_REUSEPORT")
def test_a_muted_sender_fills_its_own_queue_and_is_heard_again_once_quiet() -> None:
    with reuse_port_socket() as public, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as storm, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other:
        public.bind(("127.0.0.1", 0))
        storm.connect(public.getsockname())
        other.connect(public.getsockname())
        queues = MutedQueues(public.getsockname(), mute_s=1.0)
        assert queues.hold(storm.getsockname(), now=0.0) and queues.wait_ms(0.0) == 1001
        for _ in range(5000):  # more than a receive queue holds: the kernel drops the rest
            storm.send(b"storm")
        other.send(b"other")
        time.sleep(0.05)
        assert _received(public) == [b"other"]  # the storm never reached the shared queue
        assert queues.review(0.5) == [] and len(queues) == 1  # not due yet
        assert queues.review(1.0) == [] and len(queues) == 1  # it sent since: held afresh
        assert queues.due == 2.0
        assert queues.review(2.0) == [storm.getsockname()] and len(queues) == 0  # quiet: released
        assert queues.wait_ms(2.0) is None
        storm.send(b"again")
        time.sleep(0.05)
        assert _received(public) == [b"again"]
        queues.close()


def test_muted_queues_stop_at_their_limit() -> None:
    queues = MutedQueues(("127.0.0.1", 9), limit=0)
    assert not queues.hold(("127.0.0.1", 1), now=0.0) and len(queues) == 0
