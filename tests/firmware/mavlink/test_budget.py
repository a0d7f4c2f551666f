"""The per-peer bounds of the MAVLink process, as pure classes: input shares and parameter streams."""

from __future__ import annotations

from fcemu.firmware.mavlink.budget import WINDOW_S, InputBudget, ParamStreams


def test_a_sender_over_its_share_is_shed_while_another_sender_gets_through() -> None:
    budget = InputBudget(peer_datagrams_per_s=100, link_datagrams_per_s=1000)
    assert budget.open(0.0)
    flood = [budget.admit(("127.0.0.1", 1), 20) for _ in range(50)]
    assert flood.count(True) == 10 and budget.shed == 40  # 100/s is 10 a window
    assert budget.admit(("127.0.0.1", 2), 20)
    assert budget.open(WINDOW_S) and budget.admit(("127.0.0.1", 1), 20)  # a new window


def test_a_link_over_its_ceiling_is_closed_until_the_next_window() -> None:
    budget = InputBudget(peer_datagrams_per_s=10_000, link_datagrams_per_s=300, max_senders=4)
    for port in range(20):  # many source ports share one share beyond max_senders
        budget.admit(("127.0.0.1", port), 10)
    assert budget.open(0.01) and len(budget._senders) == 5
    for _ in range(10):
        budget.admit(("127.0.0.1", 1), 10)
    assert not budget.open(0.02)
    assert budget.open(0.02 + WINDOW_S)


def test_param_lists_stream_within_the_budget_one_per_peer_restarted_by_a_new_request() -> None:
    sent: list[tuple[str, int]] = []
    streams = ParamStreams(lambda: 30, lambda link, i: sent.append((link, i)), per_s=100.0, max_peers=2)
    for _ in range(1000):  # a flood of requests from one peer: one list
        streams.request("gcs", (255, 0))
    streams.request("gcs", (1, 1))
    streams.request("gcs", (2, 2))  # a third peer on the link: refused
    assert streams.refused == 1
    streams.pump(0.0)
    assert len(sent) == 10  # 100/s, at most a window's worth at once
    streams.pump(0.05)
    assert len(sent) == 15
    streams.request("gcs", (255, 0))  # restarted
    for k in range(1, 20):
        streams.pump(0.05 + 0.1 * k)
    assert not streams.pending()
    by_peer = [i for _, i in sent]
    assert by_peer.count(0) == 3 and sorted(set(by_peer)) == list(range(30))
