"""Texts longer than one STATUSTEXT (50 bytes) arrive whole, as MAVLink 2 chunks (id, chunk_seq)."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import common as M

from fcemu.firmware.mavlink.telemetry import statustext
from tests.firmware.mavlink.conftest import connect, wait_for

pytestmark = pytest.mark.timeout(60)


def reassemble(conn, start: str, timeout: float = 5.0) -> str:
    first = wait_for(conn, "STATUSTEXT", lambda m: m.text.startswith(start), timeout)
    if first.id == 0:
        return first.text
    parts = {first.chunk_seq: first.text}
    while len(parts[max(parts)]) == 50:
        m = wait_for(conn, "STATUSTEXT", lambda m: m.id == first.id, timeout)
        parts[m.chunk_seq] = m.text
    assert sorted(parts) == list(range(len(parts)))
    return "".join(parts[i] for i in sorted(parts))


def test_a_long_text_is_sent_whole_in_chunks(sitl) -> None:
    s = sitl()
    gcs = connect(s.gcs_port)
    gcs.mav.param_set_send(1, 1, b"COM_OF_LOSS_T", float("nan"), M.MAV_PARAM_TYPE_REAL32)
    assert reassemble(gcs, "Param rejected") == "Param rejected: COM_OF_LOSS_T: nan is not a finite number"
    out = s.stop()
    assert "Traceback" not in out, out[-3000:]


def test_chunk_boundaries() -> None:
    mav = M.MAVLink(None, srcSystem=1, srcComponent=1)
    assert [(m.id, m.chunk_seq) for m in statustext(mav, 6, "x" * 50, 7)] == [(0, 0)]
    exact = statustext(mav, 6, "y" * 100, 7)  # a multiple of 50: an empty chunk ends it
    assert [(m.id, m.chunk_seq, len(m.text)) for m in exact] == [(7, 0, 50), (7, 1, 50), (7, 2, 0)]
    assert len(statustext(mav, 6, "z" * 10_000, 8)) == 5  # bounded: 200 bytes at most
