"""User errors: one line `fcemu: error: ...` on stderr, exit 2, a traceback only with --debug."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from fcemu.firmware.contract import META_PREFIX
from fcemu.firmware.controllers import DEFAULT_POLICY

ROOT = Path(__file__).resolve().parents[2]


def fcemu(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "fcemu", *args], capture_output=True, text=True,
                          timeout=120, env=env, cwd=cwd)


def assert_user_error(proc: subprocess.CompletedProcess, *words: str) -> None:
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and lines[0].startswith("fcemu: error: "), proc.stderr
    assert "Traceback" not in proc.stderr
    for word in words:
        assert word in lines[0]


def wrong_shaped(path: Path) -> Path:
    """A float model (batch, 8) -> (batch, 4) carrying the shipped policy's 7-input contract."""
    graph = helper.make_graph(
        [helper.make_node("MatMul", ["observation", "W"], ["action"])], "policy",
        [helper.make_tensor_value_info("observation", TensorProto.FLOAT, ["batch", 8])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", 4])],
        [numpy_helper.from_array(np.zeros((8, 4), np.float32), "W")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=9)
    for p in onnx.load(str(DEFAULT_POLICY)).metadata_props:
        model.metadata_props.add(key=p.key, value=p.value)
    onnx.save(model, str(path))
    return path


def lying(path: Path, key: str, value: str) -> Path:
    model = onnx.load(str(DEFAULT_POLICY))
    for p in model.metadata_props:
        if p.key == META_PREFIX + key:
            p.value = value
    onnx.save(model, str(path))
    return path


@pytest.fixture
def files(tmp_path: Path) -> dict[str, Path]:
    corrupt = tmp_path / "broken.onnx"
    corrupt.write_bytes(DEFAULT_POLICY.read_bytes()[:300])  # a truncated policy
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"\x00garbage" * 40)
    return {"corrupt": corrupt, "garbage": garbage, "wrong_shape": wrong_shaped(tmp_path / "wide.onnx"),
            "lying_rate": lying(tmp_path / "nan_rate.onnx", "loop_rate_hz", "nan"),
            "lying_throttle": lying(tmp_path / "throttle.onnx", "throttle", "[0.9, 0.1]"),
            "directory": (tmp_path / "folder.onnx").mkdir() or tmp_path / "folder.onnx"}


@pytest.mark.parametrize(("case", "words"), [
    ("missing", ("no policy file",)),
    ("corrupt", ("not a loadable ONNX model",)),
    ("garbage", ("not a loadable ONNX model",)),
    ("wrong_shape", ("input shape",)),
    ("lying_rate", ("loop_rate_hz",)),
    ("lying_throttle", ("throttle",)),
    ("directory", ("not a loadable ONNX model",)),
])
def test_a_bad_policy_file_is_one_line_and_exit_2(tmp_path: Path, files: dict[str, Path], case: str,
                                                   words: tuple[str, ...]) -> None:
    path = files.get(case, tmp_path / "missing.onnx")
    assert_user_error(fcemu("sitl", "--controller", str(path), "--no-mavlink", "--duration", "0.1",
                            cwd=tmp_path), *words)


def test_a_policy_at_another_loop_rate_is_refused(tmp_path: Path) -> None:
    assert_user_error(fcemu("sitl", "--controller", str(DEFAULT_POLICY), "--rate", "500", "--speed", "max",
                            "--duration", "0.1", "--no-mavlink", cwd=tmp_path),
                      "trained for a 1000 Hz loop, asked to run at 500 Hz")


@pytest.mark.parametrize("args", [
    ("sitl", "--rate", "abc"),
    ("sitl", "--rate", "nan"),
    ("sitl", "--rate", "-5"),
    ("sitl", "--duration", "inf"),
    ("sitl", "--gcs", "nonsense"),
    ("sitl", "--controller", "bogus"),
    ("sitl", "--controller", "pid:nope", "--no-mavlink"),
    ("sitl", "--no-such-option"),
    ("no-such-command",),
])
def test_a_bad_argument_is_one_line_and_exit_2(tmp_path: Path, args: tuple[str, ...]) -> None:
    assert_user_error(fcemu(*args, cwd=tmp_path))


def test_other_commands_that_load_a_policy(tmp_path: Path, files: dict[str, Path]) -> None:
    broken = str(files["corrupt"])
    assert_user_error(fcemu("eval", "--controller", broken, "--episodes", "2", cwd=tmp_path),
                      "not a loadable")
    assert_user_error(fcemu("bench", "loop", "--controller", broken, "--seconds", "0.1", "--json",
                            cwd=tmp_path), "not a loadable")


def test_debug_shows_the_traceback(tmp_path: Path, files: dict[str, Path]) -> None:
    proc = fcemu("--debug", "sitl", "--controller", str(files["corrupt"]), "--no-mavlink", cwd=tmp_path)
    assert proc.returncode == 2
    assert "Traceback (most recent call last)" in proc.stderr and "PolicyContractError" in proc.stderr
    assert proc.stderr.strip().splitlines()[-1].startswith("fcemu: error: ")


def test_a_good_run_is_unchanged(tmp_path: Path) -> None:
    proc = fcemu("sitl", "--controller", "pid", "--speed", "max", "--duration", "0.2", "--no-mavlink",
                 "--quiet", cwd=tmp_path)
    assert proc.returncode == 0 and "200 ticks" in proc.stdout, proc.stderr
    assert "fcemu: error" not in proc.stderr


@pytest.mark.parametrize("args", [("train", "--steps", "1"), ("fit", "--airframe", "iris"),
                                  ("distill", "policy.onnx")])
def test_a_command_without_its_extra_names_it_in_one_line(tmp_path: Path, args: tuple[str, ...]) -> None:
    """As after `make demo` (the runtime only): torch is not there."""
    script = ("import sys; sys.modules['torch'] = None; from fcemu.cli import main; "
              f"sys.exit(main({[*args, '--out', str(tmp_path / 'out')]!r}))")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120,
                          cwd=tmp_path)
    assert done.returncode == 2, done.stderr[-1500:]
    assert done.stderr.count("\n") == 1 and "pip install 'fcemu[train]'" in done.stderr
    assert not (tmp_path / "out").exists()
