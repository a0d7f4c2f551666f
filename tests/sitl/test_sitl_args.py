"""`fcemu sitl` refuses a bad MAVLink argument before anything starts: one `fcemu: error:` line,
exit status 2, for a key or file it cannot use, a peer it cannot send to, or a :signed peer
without a key; the arguments that are fine start the vehicle."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from fcemu.cli import main
from tests.firmware.mavlink.conftest import ROOT


def fcemu_sitl(tmp_path: Path, *argv: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    env = {**os.environ, "XDG_DATA_HOME": str(tmp_path / "data"), "PYTHONUNBUFFERED": "1"}
    peers = [] if "--no-mavlink" in argv else ["--gcs", "127.0.0.1:9", "--offboard", "127.0.0.1:9"]
    return subprocess.run([sys.executable, "-m", "fcemu.cli", "sitl", "--quiet", "--speed", "max",
                           "--duration", "0.3", *peers, *argv],
                          cwd=tmp_path, capture_output=True, text=True, timeout=timeout, env=env)


REFUSED = {
    "missing signing key": (["--signing-key", "missing.key"], "--signing-key missing.key: cannot read it"),
    "signing key a folder": (["--signing-key", "."], "--signing-key .: not a regular file"),
    "empty signing key": (["--signing-key", "empty.key"], "--signing-key empty.key: not a signing key"),
    "tlog where no file can be": (["--tlog", "/proc/x.tlog"], "--tlog /proc/x.tlog: cannot write it"),
    "tlog a folder": (["--tlog", "."], "--tlog .: cannot write it (is a directory)"),
    "params where no file can be": (["--params", "/proc/x.json"], "--params /proc/x.json: cannot save"),
    "params a folder": (["--params", "."], "--params .: cannot save parameters there (is a directory)"),
    "peer not an IPv4 address": (["--peer", "999.1.1.1:14560"], "999.1.1.1 is not an IPv4 address"),
    "peer host that does not resolve": (["--peer", "nowhere.invalid:14560"],
                                        "host nowhere.invalid does not resolve"),
    "peer port 0": (["--peer", "127.0.0.1:0"], "bad peer '127.0.0.1:0': port 0 is not in 1..65535"),
    "peer port past 65535": (["--gcs", "127.0.0.1:65536:signed"], "port 65536 is not in 1..65535"),
    "peer without a port": (["--peer", "127.0.0.1"], "bad peer '127.0.0.1': use host:port[:signed]"),
    "signed peer without a key": (["--peer", "127.0.0.1:14560:signed"],
                                  "--peer 127.0.0.1:14560:signed: a :signed peer needs --signing-key"),
    "signed offboard peer without a key": (["--offboard", "localhost:14540:signed"],
                                           "--offboard localhost:14540:signed: a :signed peer needs"),
    "tlog without MAVLink": (["--no-mavlink", "--tlog", "x.tlog"],
                             "--tlog sets up MAVLink, which --no-mavlink turns off"),
}


@pytest.mark.parametrize("argv, message", REFUSED.values(), ids=REFUSED.keys())
def test_bad_argument_is_one_error_line_and_status_2(tmp_path, monkeypatch, capsys, argv, message) -> None:
    """`fcemu`'s main in this process (what the console script exits with): the refusals start nothing."""
    (tmp_path / "empty.key").write_bytes(b"")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    peers = [] if "--no-mavlink" in argv else ["--gcs", "127.0.0.1:9", "--offboard", "127.0.0.1:9"]
    try:
        status = main(["sitl", "--quiet", "--speed", "max", "--duration", "0.3", *peers, *argv])
    except SystemExit as exc:  # argparse's refusals
        status = exc.code
    out, err = capsys.readouterr()
    lines = err.splitlines()
    assert status == 2, err[-2000:]
    assert len(lines) == 1 and lines[0].startswith("fcemu: error:"), err[-2000:]
    assert message in lines[0]
    assert "flying" not in out + err  # refused before the vehicle started


def test_good_key_signed_peer_and_new_tlog_folder_fly(tmp_path) -> None:
    """A passphrase key, a :signed peer named by host name, a tlog in folders not made yet."""
    (tmp_path / "fleet.key").write_text("correct horse battery staple\n")
    tlog = tmp_path / "logs" / "today" / "flight.tlog"
    result = fcemu_sitl(tmp_path, "--signing-key", "fleet.key", "--peer", "localhost:9:signed",
                        "--tlog", str(tlog), "--params", str(tmp_path / "params" / "p.json"))
    assert result.returncode == 0, result.stderr[-2000:]
    assert "fcemu: flying" in result.stderr
    assert tlog.stat().st_size > 0  # the MAVLink process wrote to the file the parent opened


def test_default_parameter_file_that_cannot_be_saved_only_warns(tmp_path) -> None:
    env_home = "/proc/no-such-place"
    env = {**os.environ, "XDG_DATA_HOME": env_home}
    result = subprocess.run([sys.executable, "-m", "fcemu.cli", "sitl", "--quiet", "--speed", "max",
                             "--duration", "0.3", "--gcs", "127.0.0.1:9", "--offboard", "127.0.0.1:9"],
                            cwd=ROOT, capture_output=True, text=True, timeout=60, env=env)
    assert result.returncode == 0, result.stderr[-2000:]
    assert f"fcemu: warning: {env_home}/fcemu/params.json: cannot save parameters there" in result.stderr
