"""What keeps one sender from costing the twin server, or its other peers, more than its share.

A token bucket per sender address (`SenderBudget`) mutes a storm. A muted sender's packets then go
to a receive queue of their own that nobody reads (`MutedQueues`): the kernel fills it and drops the
rest, so the storm no longer fills the shared queue that a late client's RESET must get through,
nor costs the server a receive per packet.
"""

from __future__ import annotations

import socket
import sys

# What one sender may do outside the owner's in-sequence steps (RESETs, repeats, refused or bad
# packets): far above any real client's resets and retries, far below a storm.
SENDER_RATE_HZ = 200.0
SENDER_BURST = 400.0
MUTE_S = 1.0
# Linux gives a connected UDP socket bound to the server's port (SO_REUSEPORT) the packets of its
# peer: the session owner, and each muted sender, get a receive queue of their own.
PEER_QUEUES = sys.platform.startswith("linux") and hasattr(socket, "SO_REUSEPORT")
MAX_MUTED_QUEUES = 64  # beyond these, muted senders share the public queue and are shed unread there

Address = tuple[str, int]


def reuse_port_socket() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    if PEER_QUEUES:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
    return sock


def peer_queue(local: Address, peer: Address) -> socket.socket:
    """A socket on the server's port that receives `peer`'s packets only (needs `PEER_QUEUES`); an
    OSError where the kernel refuses one."""
    sock = reuse_port_socket()
    try:
        sock.bind(local)
        sock.connect(peer)
    except OSError:
        sock.close()
        raise
    return sock


class SenderBudget:
    """A token bucket per sender address for the packets that cost the server work.

    A sender that runs dry is muted: its packets are dropped unread until it has been quiet
    for `mute_s`, so a storm costs the server one receive per packet and nothing else.
    """

    def __init__(self, rate_hz: float = SENDER_RATE_HZ, burst: float = SENDER_BURST, mute_s: float = MUTE_S,
                 max_senders: int = 4096) -> None:
        self.rate_hz, self.burst, self.mute_s, self.max_senders = rate_hz, burst, mute_s, max_senders
        self._tokens: dict[Address, tuple[float, float]] = {}  # addr -> (tokens, at)
        self._muted: dict[Address, float] = {}  # addr -> muted until

    def muted(self, addr: Address, now: float) -> bool:
        until = self._muted.get(addr)
        if until is None:
            return False
        if now < until:
            self._muted[addr] = now + self.mute_s  # a storm that goes on stays muted
            return True
        del self._muted[addr]
        return False

    def spend(self, addr: Address, now: float) -> bool:
        """Take one token; False (and the sender muted) when it has none left."""
        tokens, at = self._tokens.get(addr, (self.burst, now))
        tokens = min(self.burst, tokens + (now - at) * self.rate_hz) - 1.0
        if tokens < 0.0:
            self._tokens.pop(addr, None)
            self._muted[addr] = now + self.mute_s
            return False
        if len(self._tokens) >= self.max_senders and addr not in self._tokens:
            self._tokens.clear()  # many senders (or forged ports): forget the ones with full buckets
        self._tokens[addr] = (tokens, now)
        return True


class MutedQueues:
    """Each muted sender's packets held in a queue of its own, unread, until it has been quiet.

    Every `mute_s` a held queue is looked at: a packet in it means the sender still sends, and the
    queue is replaced by an empty one; an empty queue is closed and the sender heard again.
    """

    def __init__(self, local: Address, mute_s: float = MUTE_S, limit: int = MAX_MUTED_QUEUES) -> None:
        self.local, self.mute_s, self.limit = local, mute_s, limit
        self._held: dict[Address, tuple[socket.socket, float]] = {}  # addr -> (queue, look at)
        self.due = float("inf")  # when the next queue is to be looked at

    def __len__(self) -> int:
        return len(self._held)

    def hold(self, addr: Address, now: float) -> bool:
        """Give `addr` a queue of its own; False where it cannot have one (the limit, no SO_REUSEPORT)."""
        if addr in self._held:
            return True
        if len(self._held) >= self.limit or not PEER_QUEUES:
            return False
        try:
            queue = peer_queue(self.local, addr)
        except OSError:  # muted all the same, shed from the shared queue
            return False
        self._held[addr] = (queue, now + self.mute_s)
        self.due = min(self.due, now + self.mute_s)
        return True

    def wait_ms(self, now: float) -> int | None:
        """How long a poll may block before a queue is due (None: no queue held)."""
        return None if not self._held else max(0, int((self.due - now) * 1000.0) + 1)

    def review(self, now: float) -> list[Address]:
        """Look at the queues that are due; the senders found quiet are released and returned."""
        released = []
        for addr, (queue, at) in list(self._held.items()):
            if at > now:
                continue
            try:
                queue.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT)
                sending = True
            except OSError:  # empty, or only an ICMP error queued for the peer: nothing it sent
                sending = False
            queue.close()
            del self._held[addr]
            if sending and self.hold(addr, now):
                continue
            released.append(addr)
        self.due = min((at for _, at in self._held.values()), default=float("inf"))
        return released

    def close(self) -> None:
        for queue, _ in self._held.values():
            queue.close()
        self._held.clear()
        self.due = float("inf")
