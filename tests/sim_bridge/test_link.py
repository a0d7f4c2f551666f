"""The lockstep link over real loopback sockets: parity with in-process, and loss, duplication and
delay (from `LossyProxy`, a real UDP relay between client and server). Malformed and foreign
packets, sessions and the client's failure modes: test_link_packets.py."""

from __future__ import annotations

import numpy as np
import pytest

from fcemu.sim_bridge.link import (
    InProcessLink,
    spawn_server,
)
from fcemu.sim_bridge.twin import Twin
from fcemu.sim_bridge.twin_server import UdpTwinServer
from tests.sim_bridge.link_rig import (
    NOISE,
    START,
    TIMEOUT,
    assert_identical,
    client_of,
    pwm_sequence,
    reference,
    run,
    wait_for,
)

pytestmark = pytest.mark.timeout(30)


# --- parity -------------------------------------------------------------------------------------


def test_in_process_link_is_the_twin() -> None:
    pwms = pwm_sequence(50)
    twin = Twin()
    assert_identical(run(InProcessLink(Twin()), pwms), [twin.reset(7)] + [twin.step(p) for p in pwms])


def test_udp_frames_are_bit_identical_to_in_process(server: UdpTwinServer) -> None:
    pwms = pwm_sequence(300)
    with client_of(server.address) as client:
        assert_identical(run(client, pwms), reference(pwms))
        assert_identical(run(client, pwms[:100], seed=8), reference(pwms[:100], seed=8))
    assert server.counters["steps"] == 400 and server.counters["resets"] == 2
    assert server.bad_packets == 0


def test_parity_holds_with_noise_and_an_initial_state() -> None:
    pwms = pwm_sequence(300, seed=2)
    with UdpTwinServer(Twin(rig="free", noise=NOISE)) as srv, client_of(srv.address) as client:
        got = run(client, pwms, seed=11, state=START)
    assert_identical(got, reference(pwms, "free", NOISE, seed=11, state=START))
    assert not np.array_equal(got[5].gyro, reference(pwms, "free", NOISE, seed=12, state=START)[5].gyro)


def test_fcemu_twin_serve_subprocess_matches_in_process() -> None:
    proc, address = spawn_server(rig="free")
    try:
        pwms = pwm_sequence(200, seed=3)
        with client_of(address) as client:
            assert_identical(run(client, pwms, state=START), reference(pwms, "free", state=START))
    finally:
        proc.terminate()
        assert proc.wait(timeout=10) == 0


# --- loss, duplication, delay ---------------------------------------------------------------------


@pytest.mark.parametrize("proxied", [{"drop_requests": {0, 3, 4}}], indirect=True)
def test_lost_requests_are_resent_and_applied_once(proxied, server: UdpTwinServer) -> None:
    client, _ = proxied
    pwms = pwm_sequence(20)
    assert_identical(run(client, pwms), reference(pwms))
    assert client.counters["retries"] == 3
    assert server.counters["steps"] == 20 and server.counters["duplicates"] == 0


@pytest.mark.parametrize("proxied", [{"drop_replies": {0, 3, 7, 8}}], indirect=True)
def test_lost_replies_are_answered_from_the_cache(proxied, server: UdpTwinServer) -> None:
    client, _ = proxied
    pwms = pwm_sequence(20)
    assert_identical(run(client, pwms), reference(pwms))
    assert client.counters["retries"] == 4
    assert server.counters["steps"] == 20 and server.counters["resets"] == 1
    assert server.counters["duplicates"] == 4


@pytest.mark.parametrize("proxied", [{"duplicate_requests": {0, 2, 5}}], indirect=True)
def test_duplicated_requests_step_once(proxied, server: UdpTwinServer) -> None:
    client, _ = proxied
    pwms = pwm_sequence(20)
    assert_identical(run(client, pwms), reference(pwms))
    assert server.counters["steps"] == 20 and server.counters["duplicates"] == 3
    assert client.counters["discarded"] == 3  # the cached replies to the copies arrive late


@pytest.mark.parametrize("proxied", [{"duplicate_replies": {1, 4}}], indirect=True)
def test_duplicated_replies_are_discarded(proxied, server: UdpTwinServer) -> None:
    client, _ = proxied
    pwms = pwm_sequence(20)
    assert_identical(run(client, pwms), reference(pwms))
    assert client.counters["discarded"] == 2 and server.counters["steps"] == 20


@pytest.mark.parametrize("proxied", [{"delay_requests": {3: 4 * TIMEOUT}}], indirect=True)
def test_a_request_overtaken_by_its_retry_is_not_applied_twice(proxied, server: UdpTwinServer) -> None:
    client, _ = proxied
    pwms = pwm_sequence(20)
    assert_identical(run(client, pwms), reference(pwms))
    wait_for(lambda: server.counters["received"] == 21 + client.counters["retries"])
    assert server.counters["steps"] == 20
    assert server.counters["stale"] + server.counters["duplicates"] == 1  # the late original
