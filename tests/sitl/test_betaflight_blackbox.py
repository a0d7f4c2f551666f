"""Betaflight SITL's blackbox files: kept across SITL restarts and joined in the order flown."""

from __future__ import annotations

import os

from fcemu.sitl.betaflight_blackbox import END_OF_LOG, logs_finished, shelve_logs, write_blackbox


def _sitl_log(run_dir, name: str, body: bytes, mtime_s: int) -> None:
    path = run_dir / name
    path.write_bytes(body)
    os.utime(path, (mtime_s, mtime_s))


def test_a_restarted_sitls_logs_do_not_overwrite_the_earlier_ones(tmp_path) -> None:
    _sitl_log(tmp_path, "LOG00002.BF", b"second" + END_OF_LOG, 20)
    _sitl_log(tmp_path, "LOG00001.BF", b"first" + END_OF_LOG, 10)
    assert [p.name for p in shelve_logs(tmp_path)] == ["00001.BFL", "00002.BFL"]
    _sitl_log(tmp_path, "LOG00001.BF", b"third" + END_OF_LOG, 30)  # a new process numbers from 1 again
    path, count = write_blackbox(tmp_path, tmp_path / "out" / "flight.BFL")
    assert count == 3
    assert path.read_bytes() == b"first" + END_OF_LOG + b"second" + END_OF_LOG + b"third" + END_OF_LOG
    assert not list(tmp_path.glob("LOG*"))


def test_no_arming_writes_no_file(tmp_path) -> None:
    path, count = write_blackbox(tmp_path, tmp_path / "flight.BFL")
    assert count == 0 and not path.exists()


def test_a_log_still_open_is_not_finished(tmp_path) -> None:
    _sitl_log(tmp_path, "LOG00001.BF", b"H Product:Blackbox", 10)
    assert not logs_finished(tmp_path)
    _sitl_log(tmp_path, "LOG00001.BF", b"H Product:Blackbox" + END_OF_LOG, 10)
    assert logs_finished(tmp_path)
