"""Bounds on the work any one peer can make the MAVLink process do.

`InputBudget` admits a link's datagrams per sender (source address) and per link, in short
windows: a sender over its share has its datagrams read and dropped unparsed (counted), and a
link over its ceiling is not read again until the next window (the kernel's socket buffer then
drops the excess at no cost to us). Reading and dropping costs a few microseconds a datagram;
parsing one costs tens.

`ParamStreams` sends PARAM_REQUEST_LIST answers as PX4 does, a few parameters at a time within
a link budget: one list in flight per requesting peer, restarted by a new request, and at most
`max_peers` lists per link, so a flood of requests costs one table update each.
"""

from __future__ import annotations

from collections.abc import Callable

WINDOW_S = 0.1


class InputBudget:
    def __init__(self, peer_datagrams_per_s: float = 2500, peer_bytes_per_s: float = 500_000,
                 link_datagrams_per_s: float = 10_000, max_senders: int = 64) -> None:
        self.peer_datagrams = int(peer_datagrams_per_s * WINDOW_S)
        self.peer_bytes = int(peer_bytes_per_s * WINDOW_S)
        self.link_datagrams = int(link_datagrams_per_s * WINDOW_S)
        self.max_senders = max_senders
        self._window = 0.0
        self._read = 0
        self._senders: dict[object, list[int]] = {}  # address → [datagrams, bytes] this window
        self.shed = 0  # datagrams dropped unparsed

    def open(self, now: float) -> bool:
        """Whether the link may be read now (False: over its ceiling until the next window)."""
        if now - self._window >= WINDOW_S:
            self._window, self._read = now, 0
            self._senders.clear()
        return self._read < self.link_datagrams

    def admit(self, address: object, size: int) -> bool:
        """Count a datagram read from `address`; whether it may be parsed."""
        self._read += 1
        used = self._senders.get(address)
        if used is None:
            if len(self._senders) >= self.max_senders:  # many source ports: they share one share
                address = None
                used = self._senders.setdefault(None, [0, 0])
            else:
                used = self._senders[address] = [0, 0]
        used[0] += 1
        used[1] += size
        if used[0] > self.peer_datagrams or used[1] > self.peer_bytes:
            self.shed += 1
            return False
        return True


class ParamStreams:
    def __init__(self, count: Callable[[], int], send: Callable[[object, int], None],
                 per_s: float = 1000.0, max_peers: int = 4) -> None:
        self._count = count
        self._send = send  # (link, index) → one PARAM_VALUE out on that link
        self.per_s = per_s
        self.max_peers = max_peers
        self._lists: dict[object, dict[tuple[int, int], int]] = {}  # link → peer → next index
        self._credit: dict[object, float] = {}
        self._last: float | None = None
        self.refused = 0

    def request(self, link: object, peer: tuple[int, int]) -> None:
        lists = self._lists.setdefault(link, {})
        if peer not in lists and len(lists) >= self.max_peers:
            self.refused += 1
            return
        lists.pop(peer, None)
        lists[peer] = 0  # (re)started, and last in the round

    def pending(self) -> bool:
        return any(self._lists.values())

    def pump(self, now: float) -> None:
        """Send what the budget allows since the last call, round robin over each link's lists."""
        elapsed = WINDOW_S if self._last is None else min(max(now - self._last, 0.0), WINDOW_S)
        self._last = now
        total = self._count()
        for link, lists in self._lists.items():
            if not lists:
                self._credit.pop(link, None)
                continue
            credit = min(self._credit.get(link, 0.0) + elapsed * self.per_s, self.per_s * WINDOW_S)
            while credit >= 1.0 and lists:
                for peer in list(lists):
                    if credit < 1.0:
                        break
                    index = lists[peer]
                    self._send(link, index)
                    credit -= 1.0
                    if index + 1 >= total:
                        del lists[peer]
                    else:
                        lists[peer] = index + 1
            self._credit[link] = credit
