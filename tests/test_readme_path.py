"""The README's "Your quad" path, run as written from the installed wheel at small budgets.

The commands are the README's own: its "Your quad" block line by line, then its "Export" lines
that take the policy, so a line that stops working fails here. Each gets small-budget options
appended (argparse keeps the last of a repeated option) and a scratch folder for cwd. The wheel
is installed as `pip install 'fcemu[train,mcu,blackbox,betaflight]'` would install it, the
closure linked from the test's interpreter (tests/test_wheel.py).

LOG.BFL is the gecko's real log (tests/data/real_logs), whose 134 s the README's spans fit. The
lines after it fly a copy of the shipped racer5 as the identified twin's file: the gecko's props
spin out, for which `fcemu fit` makes no policy, and the other real log's twin (cs110) comes back
from its own identification flight with an inertia no rigid body has.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.test_wheel import build_wheel, clean_env, install_wheel

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
LOG = ROOT / "tests" / "data" / "real_logs" / "gecko_btfl_002.bbl"
AIRFRAME = ROOT / "sim_bridge" / "airframes" / "racer5.json"
EXTRAS = ("train", "mcu", "blackbox", "betaflight")
BUDGETS = {
    "identify": ["--no-refine"],  # a log: no refining flights with the log's tune (about a minute)
    "eval": ["--episodes", "2"],
    "tune": ["--budget-s", "5", "--episodes", "1", "--check-episodes", "1", "--rounds", "1", "--jobs", "1"],
    "sitl": ["--rig", "rig", "--no-mavlink", "--duration", "1", "--speed", "max", "--quiet"],
    # held-out commands as the tune's (its bound cached); the teacher's speed given, not chosen
    "fit": ["--episodes", "1", "--rounds", "1", "--steps", "100", "--envs", "2", "--fit-steps", "10",
            "--lag-multiple", "0.5", "--jobs", "1", "--no-mcu"],
    "export": ["--parity-samples", "200"],
}
# --target betaflight: the patched tree and the policy's C, not built (each target compiles
# Betaflight for minutes)
NO_BUILD = ["--betaflight-targets", ""]

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]


def readme_block(heading: str) -> list[list[str]]:
    """The `fcemu …` lines of the first fenced block under `## heading`, comments stripped."""
    section = README.read_text().split(f"\n## {heading}\n", 1)[1]
    block = re.search(r"^```[a-z]*\n(.*?)^```", section, re.M | re.S)
    assert block, f"README.md: no code block under ## {heading}"
    lines = [line.split("  #")[0].strip() for line in block.group(1).splitlines()]
    return [shlex.split(line) for line in lines if line.startswith("fcemu ")]


def option(argv: list[str], name: str) -> str:
    return argv[argv.index(name) + 1]


def with_budget(argv: list[str]) -> list[str]:
    if "--fly" in argv:
        return argv
    no_build = NO_BUILD if argv[1] == "export" and option(argv, "--target") == "betaflight" else []
    return argv + BUDGETS.get(argv[1], []) + no_build


@pytest.fixture(scope="module")
def fcemu(tmp_path_factory) -> Path:
    """The wheel's `fcemu` in a venv with the extras' closure."""
    work = tmp_path_factory.mktemp("readme_path")
    return install_wheel(build_wheel(work), work / "venv", EXTRAS) / "fcemu"


def run(fcemu: Path, argv: list[str], cwd: Path, home: Path) -> subprocess.CompletedProcess:
    """`argv` by the wheel's console script in `cwd`, with caches and parameters under `home`,
    and without the test's venv on PATH."""
    env = clean_env() | {"XDG_CACHE_HOME": str(home / "cache"), "XDG_DATA_HOME": str(home / "data"),
                         "MPLBACKEND": "Agg"}
    ours = Path(sys.executable).parent
    env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep) if Path(p) != ours)
    done = subprocess.run([str(fcemu), *argv[1:]], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, f"{shlex.join(argv)}:\n{done.stdout[-2000:]}\n{done.stderr[-3000:]}"
    return done


def test_your_quad_as_the_readme_writes_it(fcemu: Path, tmp_path: Path) -> None:
    lines = readme_block("Your quad")
    from_log = [argv for argv in lines if "LOG.BFL" in argv]
    assert [argv[1] for argv in from_log] == ["identify", "replay"]
    log_dir, quad = tmp_path / "log", tmp_path / "quad"
    log_dir.mkdir()
    for argv in from_log:
        run(fcemu, with_budget([str(LOG) if word == "LOG.BFL" else word for word in argv]), log_dir, tmp_path)
    twin = Path(option(from_log[0], "--out"))
    assert (log_dir / twin).is_file() and (log_dir / twin.parent / "pid_log.json").is_file()
    assert any((log_dir / option(from_log[1], "--out")).iterdir())

    (quad / twin.parent).mkdir(parents=True)
    shutil.copy(AIRFRAME, quad / twin)
    rest = [argv for argv in lines if argv not in from_log]
    assert [argv[1] for argv in rest] == ["eval", "tune", "sitl", "fit", "sitl", "identify"]
    assert all(option(argv, "--airframe") == str(twin) for argv in rest[1:5])
    assert option(rest[5], "--fly") == str(twin)
    tuned: dict[str, bytes] = {}
    for argv in rest:
        done = run(fcemu, with_budget(argv), quad, tmp_path)
        out = quad / option(argv, "--out") if "--out" in argv else quad
        if argv[1] == "tune":
            tuned = {name: (out / name).read_bytes() for name in ("pid.json", "tune.json")}
        elif argv[1] == "fit":  # flies the tune's PID, not tuned again
            assert json.loads((out / "pid.json").read_text())["pid"] == json.loads(tuned["pid.json"])["pid"]
            assert (out / "tune.json").read_bytes() == tuned["tune.json"]
            assert (out / "policy.onnx").is_file() and (out / "report.md").is_file()
        elif argv[1] == "sitl":
            flying = [line for line in done.stderr.splitlines() if line.startswith("fcemu: flying ")]
            assert flying and option(argv, "--controller") in flying[0], done.stderr[-2000:]
        elif "--fly" in argv:
            assert (out / "airframe.json").is_file()

    policy = str(Path(option(rest[3], "--out")) / "policy.onnx")
    exports = [argv for argv in readme_block("Export") if argv[1:3] == ["export", "policy.onnx"]]
    assert sorted(option(argv, "--target") for argv in exports) == ["betaflight", "c"]
    for argv in exports:
        run(fcemu, with_budget([policy if word == "policy.onnx" else word for word in argv]), quad, tmp_path)
        out = quad / option(argv, "--out")
        assert (out / ("parity.json" if option(argv, "--target") == "c" else "export.json")).is_file()
        shutil.rmtree(out)  # the Betaflight tree is some 200 MB
