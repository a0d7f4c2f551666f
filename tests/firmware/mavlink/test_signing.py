"""MAVLink 2 signing required on one link (`--peer host:port:signed --signing-key FILE`): unsigned
and wrongly signed commands from that peer are refused and counted, signed ones obeyed; the
other links stay unsigned."""

from __future__ import annotations

import time

import pytest
from pymavlink.dialects.v20 import common as M

from tests.firmware.mavlink.conftest import command, connect, listen, read_param, wait_for

pytestmark = pytest.mark.timeout(90)
KEY = bytes(range(1, 33))
ARM = M.MAV_CMD_COMPONENT_ARM_DISARM
SIGNED_FLAG = 0x01  # MAVLINK_IFLAG_SIGNED


def armed(conn) -> bool:
    return bool(wait_for(conn, "HEARTBEAT", lambda m: m.get_srcSystem() == 1, timeout=5).base_mode
                & M.MAV_MODE_FLAG_SAFETY_ARMED)


def no_ack(conn, cmd: int, seconds: float = 1.5) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        m = conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.2)
        if m is not None and m.command == cmd:
            return False
    return True


def test_signed_link_refuses_unsigned_and_wrongly_signed_commands_obeys_signed_ones(sitl, tmp_path) -> None:
    key_file = tmp_path / "signing.key"
    key_file.write_text(KEY.hex() + "\n")
    port = listen()
    s = sitl("--peer", f"127.0.0.1:{port}:signed", "--signing-key", str(key_file))
    gcs = connect(s.gcs_port)
    peer = connect(port, source_system=250, source_component=190)
    # The vehicle signs what it sends on the marked link only.
    hb = wait_for(peer, "HEARTBEAT", lambda m: m.get_srcSystem() == 1)
    assert hb._header.incompat_flags & SIGNED_FLAG
    assert not gcs.messages["HEARTBEAT"]._header.incompat_flags & SIGNED_FLAG

    # Unsigned: no answer, nothing done.
    peer.mav.command_long_send(1, 1, ARM, 0, 1, 0, 0, 0, 0, 0, 0)
    peer.mav.param_request_read_send(1, 1, b"COM_OF_LOSS_T", -1)
    assert no_ack(peer, ARM)
    assert "PARAM_VALUE" not in peer.messages  # (every message received is kept there by type)
    assert not armed(gcs)

    # Signed with another key: the same.
    peer.setup_signing(bytes(32 * [7]), sign_outgoing=True)
    peer.mav.command_long_send(1, 1, ARM, 0, 1, 0, 0, 0, 0, 0, 0)
    assert no_ack(peer, ARM)
    assert not armed(gcs)
    rejected = wait_for(gcs, "NAMED_VALUE_INT", lambda m: m.name == "sig_reject" and m.value >= 2, timeout=5)
    assert rejected.value >= 2

    # Signed with the vehicle's key: obeyed, and its replies verify with that key.
    peer.setup_signing(KEY, sign_outgoing=True)
    ack = command(peer, ARM, 1)
    assert ack.result == M.MAV_RESULT_ACCEPTED and ack.get_signed()
    assert armed(gcs)
    assert read_param(peer, b"COM_OF_LOSS_T").get_signed()
    assert command(peer, ARM, 0).result == M.MAV_RESULT_ACCEPTED
    assert not armed(gcs)

    # The unsigned GCS link is unaffected by the other link's requirement.
    assert command(gcs, M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION).result == 0


def forged_frame(src_system: int, src_component: int, timestamp: int) -> bytes:
    """A MAVLink 2 frame from (`src_system`, `src_component`), link_id 0, stamped `timestamp`,
    signed with a key that is not the vehicle's: what anyone on the network can send."""
    mav = M.MAVLink(None, srcSystem=src_system, srcComponent=src_component)
    mav.signing.secret_key = bytes(32 * [0xA5])
    mav.signing.link_id = 0
    mav.signing.timestamp = timestamp
    mav.signing.sign_outgoing = True
    return mav.heartbeat_encode(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0).pack(mav)


def test_a_forged_far_future_timestamp_does_not_lock_the_key_holder_out(sitl, tmp_path) -> None:
    key_file = tmp_path / "signing.key"
    key_file.write_text(KEY.hex() + "\n")
    port = listen()
    s = sitl("--peer", f"127.0.0.1:{port}:signed", "--signing-key", str(key_file))
    gcs = connect(s.gcs_port)
    peer = connect(port, source_system=250, source_component=190)
    peer.setup_signing(KEY, sign_outgoing=True, link_id=0)
    peer.write(forged_frame(250, 190, (1 << 48) - 10))  # the victim's stream, garbage signature
    time.sleep(0.3)
    # The key holder's frames, stamped with today's time, are still obeyed.
    ack = command(peer, ARM, 1)
    assert ack.result == M.MAV_RESULT_ACCEPTED
    assert armed(gcs)
    assert read_param(peer, b"COM_OF_LOSS_T").get_signed()
    assert command(peer, ARM, 0).result == M.MAV_RESULT_ACCEPTED


def param(conn, name: bytes) -> float:
    return read_param(conn, name).param_value


def test_a_signed_frame_captured_on_one_link_is_refused_when_replayed_on_another(sitl, tmp_path) -> None:
    key_file = tmp_path / "signing.key"
    key_file.write_text(KEY.hex() + "\n")
    s = sitl("--signing-key", str(key_file))  # no link marked: every link requires the key
    gcs = connect(s.gcs_port)
    off = connect(s.offboard_port, source_system=245, source_component=190)
    gcs.setup_signing(KEY, sign_outgoing=True, link_id=1)
    off.setup_signing(KEY, sign_outgoing=True, link_id=2)
    captured = off.mav.param_set_encode(1, 1, b"COM_OF_LOSS_T", 0.7, M.MAV_PARAM_TYPE_REAL32).pack(off.mav)
    off.write(captured)
    assert wait_for(gcs, "PARAM_VALUE", lambda m: m.param_id == "COM_OF_LOSS_T").param_value \
        == pytest.approx(0.7)
    gcs.mav.param_set_send(1, 1, b"COM_OF_LOSS_T", 0.9, M.MAV_PARAM_TYPE_REAL32)
    assert wait_for(gcs, "PARAM_VALUE", lambda m: m.param_id == "COM_OF_LOSS_T").param_value \
        == pytest.approx(0.9)
    for conn in (gcs, off):  # replayed to the GCS link's port, and to the link it came from
        conn.write(captured)
        time.sleep(0.3)
        assert param(gcs, b"COM_OF_LOSS_T") == pytest.approx(0.9)
    rejected = wait_for(gcs, "NAMED_VALUE_INT", lambda m: m.name == "sig_reject" and m.value >= 2, timeout=5)
    assert rejected.value >= 2


def test_signing_state_remembers_nothing_from_a_frame_with_a_bad_signature() -> None:
    from fcemu.firmware.mavlink.signing import SigningState, signing_now

    state = SigningState(KEY)
    forged = bytearray(forged_frame(250, 190, (1 << 48) - 10))
    assert not state.check(forged, 250, 190) and state.streams == {} and state.bad_signature == 1
    mav = M.MAVLink(None, srcSystem=250, srcComponent=190)
    mav.signing.secret_key, mav.signing.link_id, mav.signing.sign_outgoing = KEY, 0, True
    mav.signing.timestamp = signing_now()
    good = bytearray(mav.heartbeat_encode(6, 8, 0, 0, 0).pack(mav))
    assert state.check(good, 250, 190)
    assert not state.check(good, 250, 190) and state.replayed == 1  # the same frame again
