"""Hostile parameter files: one warning line, bad entries skipped, defaults kept, file untouched."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from fcemu.firmware.params import MAX_FILE_BYTES, ParamTable, load_warning

ROOT = Path(__file__).resolve().parents[2]

BAD_FILES = {
    "huge_int": '{"PID_ROLL_P": ' + "9" * 400 + ', "COM_OF_LOSS_T": 1.5}',
    "huge_negative_int": '{"PID_ROLL_P": -' + "9" * 400 + ', "COM_OF_LOSS_T": 1.5}',
    "deep_nesting": '{"PID_ROLL_P": ' + "[" * 100_000 + "]" * 100_000 + ', "COM_OF_LOSS_T": 1.5}',
    "deep_top_level": "[" * 100_000 + "]" * 100_000,
    "bool_gain": '{"PID_ROLL_P": true, "COM_OF_LOSS_T": 1.5}',
    "string_gain": '{"PID_ROLL_P": "' + "x" * 10_000 + '", "COM_OF_LOSS_T": 1.5}',
    "nan_literal": '{"PID_ROLL_P": NaN, "COM_OF_LOSS_T": 1.5}',
    "null": '{"PID_ROLL_P": null, "COM_OF_LOSS_T": 1.5}',
    "long_name": '{"' + "A" * 100_000 + '": 1, "COM_OF_LOSS_T": 1.5}',
    "huge_digits": '{"PID_ROLL_P": ' + "9" * 5000 + "}",
    "binary": "\udcff\x00\x01garbage",
}


def _write(path: Path, text: str) -> bytes:
    data = text.encode("utf-8", "surrogateescape")
    path.write_bytes(data)
    return data


@pytest.mark.parametrize("name", sorted(BAD_FILES))
def test_a_bad_file_is_skipped_entry_by_entry_with_one_line(tmp_path: Path, name: str) -> None:
    path = tmp_path / "params.json"
    data = _write(path, BAD_FILES[name])
    table = ParamTable()
    problems = table.load(path)
    assert problems
    assert table["PID_ROLL_P"] == ParamTable()["PID_ROLL_P"]  # the default, never the bad value
    if '"COM_OF_LOSS_T": 1.5' in BAD_FILES[name] and not name.startswith(("deep", "huge_digits")):
        assert table["COM_OF_LOSS_T"] == 1.5  # the good entry beside the bad one is applied
    line = load_warning(path, problems)
    assert "\n" not in line and len(line) < 600 and line.startswith("params: ")
    assert path.read_bytes() == data


def test_an_oversized_file_is_not_read(tmp_path: Path) -> None:
    path = tmp_path / "params.json"
    path.write_text(json.dumps({"PID_ROLL_P": 3.0, "pad": "x" * (MAX_FILE_BYTES + 1)}))
    table = ParamTable()
    assert "too large" in table.load(path)[0] and table["PID_ROLL_P"] == ParamTable()["PID_ROLL_P"]


def test_true_is_not_a_gain() -> None:
    table = ParamTable()
    assert "not a number" in table.set("PID_ROLL_P", True)
    assert "not a number" in table.set("CTRL_SEL", False)
    assert "finite" in table.set("PID_ROLL_P", 10**400)


@pytest.mark.parametrize("name", ["huge_int", "deep_nesting", "bool_gain"])
def test_sitl_starts_and_flies_with_a_bad_params_file(tmp_path: Path, name: str) -> None:
    path = tmp_path / "params.json"
    data = _write(path, BAD_FILES[name])
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run(
        [sys.executable, "-m", "fcemu", "sitl", "--controller", "pid", "--speed", "max", "--duration", "1",
         "--quiet", "--params", str(path)],
        capture_output=True, text=True, timeout=120, env=env, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    warnings = [ln for ln in proc.stderr.splitlines() if ln.startswith("params: ")]
    assert len(warnings) == 1 and ("unreadable" if name == "deep_nesting" else "PID_ROLL_P") in warnings[0]
    assert "1000 ticks" in proc.stdout
    assert path.read_bytes() == data
