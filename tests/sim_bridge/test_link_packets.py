"""The lockstep link over real loopback sockets: malformed and foreign packets from plain sockets,
sessions passing between clients, and the client's failure modes."""

from __future__ import annotations

import socket
import struct
import subprocess
import threading
import time

import numpy as np
import pytest

from fcemu.firmware.sensors import SensorFrame
from fcemu.sim_bridge.link import (
    AdaptiveSpin,
    InProcessLink,
    LinkError,
    LinkTimeout,
    RemoteError,
    UdpTwinClient,
    spawn_server,
)
from fcemu.sim_bridge.protocol import (
    HEADER,
    MAGIC,
    VERSION,
    Error,
    ErrorCode,
    Frame,
    decode,
    encode_bye,
    encode_error,
    encode_frame,
    encode_pwm,
    encode_reset,
)
from fcemu.sim_bridge.twin import Twin
from fcemu.sim_bridge.twin_server import UdpTwinServer
from tests.sim_bridge.link_rig import (
    TIMEOUT,
    client_of,
    wait_for,
)

pytestmark = pytest.mark.timeout(30)


# --- malformed and foreign packets ----------------------------------------------------------------


def pwm_header_with(magic: bytes = MAGIC, version: int = VERSION, msg_type: int = 1) -> bytes:
    return HEADER.pack(magic, version, msg_type, 0, 99) + bytes(32)


BAD_PACKETS = {
    "empty": (b"", ErrorCode.MALFORMED, "malformed"),
    "short header": (b"FCTW\x01", ErrorCode.MALFORMED, "malformed"),
    "truncated pwm": (encode_pwm(99, [1500] * 4)[:-1], ErrorCode.MALFORMED, "malformed"),
    "oversized pwm": (encode_pwm(99, [1500] * 4) + bytes(600), ErrorCode.MALFORMED, "malformed"),
    "foreign magic": (pwm_header_with(magic=b"\xfd\x09\x00\x00"), ErrorCode.MALFORMED, "malformed"),
    "foreign version": (pwm_header_with(version=VERSION + 1), ErrorCode.BAD_VERSION, "bad_version"),
    "unknown type": (pwm_header_with(msg_type=0x42), ErrorCode.UNKNOWN_TYPE, "unknown_type"),
    "garbage": (bytes(np.random.default_rng(5).integers(0, 256, 77, dtype=np.uint8)),
                ErrorCode.MALFORMED, "malformed"),
    "text": (b"GET / HTTP/1.1\r\n\r\n", ErrorCode.MALFORMED, "malformed"),
}


@pytest.mark.parametrize("case", list(BAD_PACKETS))
def test_bad_packets_are_answered_counted_and_harmless(server: UdpTwinServer, case: str) -> None:
    packet, code, counter = BAD_PACKETS[case]
    with client_of(server.address) as client, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rogue:
        client.reset(seed=1)
        client.pwm_write(np.full(4, 1500.0))
        rogue.settimeout(2.0)
        rogue.sendto(packet, server.address)
        raw = rogue.recv(2048)
        if code == ErrorCode.BAD_VERSION:  # refused in the sender's own version, so it can read why
            assert raw[4] == VERSION + 1
            raw = raw[:4] + bytes([VERSION]) + raw[5:]
        answer = decode(raw)
        assert isinstance(answer, Error) and answer.code == code
        assert server.counters[counter] == 1 and server.bad_packets == 1
        assert client.pwm_write(np.full(4, 1500.0)).t_us == 2000  # the session did not notice
    assert server.counters["steps"] == 2


@pytest.mark.parametrize("reply", [encode_frame(5, Twin().reset()), encode_error(5, ErrorCode.BUSY, "x")],
                         ids=["frame", "error"])
def test_replies_sent_to_the_server_are_counted_not_answered(server: UdpTwinServer, reply: bytes) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rogue:
        rogue.settimeout(0.2)
        rogue.sendto(reply, server.address)
        with pytest.raises(TimeoutError):
            rogue.recv(2048)  # two servers must never ping-pong errors
    assert server.counters["unexpected_reply"] == 1


def exchange(sock: socket.socket, packet: bytes) -> Frame | Error:
    sock.send(packet)
    msg = decode(sock.recv(2048))
    assert isinstance(msg, Frame | Error)
    return msg


def test_out_of_order_sequence_numbers_are_rejected(server: UdpTwinServer) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as peer:
        peer.settimeout(2.0)
        peer.connect(server.address)
        hover = [1500.0] * 4
        assert exchange(peer, encode_pwm(5, hover)).code == ErrorCode.NO_SESSION
        assert exchange(peer, encode_reset(10, seed=1)).seq == 10
        assert exchange(peer, encode_pwm(11, hover)).frame.t_us == 1000
        peer.send(encode_pwm(12, hover))
        first_reply = peer.recv(2048)
        assert exchange(peer, encode_pwm(11, hover)).code == ErrorCode.STALE_SEQ
        assert exchange(peer, encode_pwm(14, hover)).code == ErrorCode.SEQ_GAP
        assert exchange(peer, encode_reset(9, seed=1)).code == ErrorCode.STALE_SEQ
        assert exchange(peer, encode_pwm(12, [1600.0] * 4)).code == ErrorCode.STALE_SEQ  # seq reused
        peer.send(encode_pwm(12, hover))
        assert peer.recv(2048) == first_reply  # an exact repeat gets the cached reply
        assert exchange(peer, encode_pwm(13, hover)).frame.t_us == 3000
        assert exchange(peer, encode_reset(20, seed=1)).frame.t_us == 0  # RESET may jump ahead
    counts = {k: server.counters[k] for k in ("steps", "resets", "stale", "gap", "no_session", "duplicates")}
    assert counts == {"steps": 3, "resets": 2, "stale": 3, "gap": 1, "no_session": 1, "duplicates": 1}


def test_another_client_mid_session_is_refused(server: UdpTwinServer) -> None:
    with client_of(server.address) as owner, client_of(server.address) as intruder, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rogue:
        owner.reset(seed=1)
        owner.pwm_write(np.full(4, 1500.0))
        with pytest.raises(RemoteError) as info:
            intruder.reset(seed=2)
        assert info.value.code == ErrorCode.BUSY
        rogue.settimeout(2.0)
        rogue.sendto(encode_pwm(owner._seq + 1, [2000.0] * 4), server.address)  # the owner's next seq
        assert decode(rogue.recv(2048)).code == ErrorCode.BUSY
        rogue.sendto(encode_bye(owner._seq + 1), server.address)  # cannot end someone else's session
        wait_for(lambda: server.counters["foreign_peer"] == 3)  # (the owner's own queue is served first)
        assert owner.pwm_write(np.full(4, 1500.0)).t_us == 2000
    assert server.counters["foreign_peer"] == 3 and server.counters["steps"] == 2


def test_the_session_passes_on_after_bye() -> None:
    with UdpTwinServer(session_timeout=60.0) as srv:
        with client_of(srv.address) as first:
            first.reset(seed=1)
        with client_of(srv.address) as second:
            wait_for(lambda: srv.counters["byes"] == 1)
            assert second.reset(seed=1).t_us == 0
            assert second.pwm_write(np.full(4, 1500.0)).t_us == 1000


def test_an_idle_session_can_be_taken_over() -> None:
    with UdpTwinServer(session_timeout=0.2) as srv, client_of(srv.address) as first, \
            client_of(srv.address) as second:
        first.reset(seed=1)
        time.sleep(0.3)
        second.reset(seed=1)
        with pytest.raises(RemoteError, match="BUSY"):
            first.pwm_write(np.full(4, 1500.0))
        assert srv.counters["takeovers"] == 1


def test_bad_pwm_raises_value_error_and_does_not_step(server: UdpTwinServer) -> None:
    for link in (InProcessLink(Twin()), client_of(server.address)):
        link.reset(seed=1)
        for bad in (np.array([1500.0, np.nan, 1500.0, 1500.0]), [1500.0, np.inf, 1500.0, 1500.0],
                    np.full(3, 1500.0), np.full((4, 1), 1500.0), None):
            with pytest.raises(ValueError):
                link.pwm_write(bad)
        assert link.pwm_write(np.full(4, 1500.0)).t_us == 1000
        link.close()
    assert server.counters["bad_argument"] == 2


# --- client failure modes -------------------------------------------------------------------------


def test_no_reply_raises_link_timeout_after_the_retries() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as silent:
        silent.bind(("127.0.0.1", 0))
        client = client_of(silent.getsockname(), retries=3)
        start = time.monotonic()
        with pytest.raises(LinkTimeout, match="after 4 tries"):
            client.reset(seed=1)
        assert 4 * TIMEOUT * 0.9 <= time.monotonic() - start < 2.0
        assert client.counters["retries"] == 3 and client.counters["timeouts"] == 1
        with pytest.raises(LinkError, match="reset"):
            client.pwm_write(np.full(4, 1500.0))
        client.close()


def test_nobody_listening_raises_link_timeout() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        closed_port = probe.getsockname()
    with client_of(closed_port, retries=2) as client, pytest.raises(LinkTimeout):
        client.reset(seed=1)
    assert client.counters["refused"] >= 1


def test_client_drops_garbage_stale_and_foreign_replies() -> None:
    """A scripted peer answers badly first; the client must return only the genuine reply."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as fake, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as foreign:
        fake.bind(("127.0.0.1", 0))
        fake.settimeout(2.0)
        client = UdpTwinClient(*fake.getsockname(), timeout=1.0, retries=0)
        result: list[SensorFrame] = []
        worker = threading.Thread(target=lambda: result.append(client.reset(seed=1)))
        worker.start()
        request, client_addr = fake.recvfrom(2048)
        seq = decode(request).seq
        genuine = Twin().reset()
        forged = genuine._replace(t_us=666)
        foreign.sendto(encode_frame(seq, forged), client_addr)  # right seq, wrong origin
        for junk in (b"\x00" * 10, encode_frame(seq - 1, forged), encode_error(seq + 1, ErrorCode.BUSY, "?")):
            fake.sendto(junk, client_addr)
        fake.sendto(encode_frame(seq, genuine), client_addr)
        worker.join(timeout=5)
        assert result and result[0].t_us == 0
        assert client.counters["discarded"] == 3
        raw = client._sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, 16)
        assert struct.unpack("@ll", raw) == (1, 0)  # the junk's shortened wait did not stick
        client.close()


def test_client_recovers_from_a_server_restart() -> None:
    with UdpTwinServer() as first:
        address = first.address
        client = client_of(address)
        client.reset(seed=1)
    with UdpTwinServer(port=address[1]) as second:
        with pytest.raises(RemoteError, match="NO_SESSION"):
            client.pwm_write(np.full(4, 1500.0))
        assert client.reset(seed=1).t_us == 0
        assert client.pwm_write(np.full(4, 1500.0)).t_us == 1000
        assert second.counters["no_session"] == 1
    client.close()


def test_serve_stops_on_sigterm_promptly() -> None:
    proc, _ = spawn_server()
    start = time.monotonic()
    proc.terminate()
    try:
        assert proc.wait(timeout=5) == 0
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    assert time.monotonic() - start < 5


def test_adaptive_spin_backs_off_and_probes_again() -> None:
    spin = AdaptiveSpin(40, probe_every=3)
    spin.miss()
    assert spin.budget == 20
    spin.hit()
    assert spin.budget == 40
    for _ in range(6):
        spin.miss()
    assert spin.budget == 0
    spin.miss()
    spin.miss()
    assert spin.budget == 0
    spin.miss()
    assert spin.budget == 40  # probing again after `probe_every` blocking receives
