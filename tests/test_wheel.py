"""The wheel is the product: built, installed in a fresh virtual environment outside the
checkout, `fcemu demo` flies the shipped policy to the end.

The environment is made with `python -m venv` (no system site-packages) and gets the wheel
with `pip install --no-deps --no-index`; its runtime dependencies are the closure of the
wheel's own `Requires-Dist` (no extras), taken from the test's interpreter and linked in
distribution by distribution (each one's files, as its RECORD lists them). So it holds
exactly what the wheel declares, at the versions the rest of the suite tested, and nothing
else of ours or of the dev extras (torch, SB3): a missing dependency or a missing file of
package data fails here. `pip check` in the new environment confirms the declared
requirements are met. Resolving the same dependencies from the registry takes 3–4 minutes
on this machine and needs the network, so it is not what this test does.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from importlib.metadata import Distribution, PackageNotFoundError, distribution
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[1]

pytestmark = [pytest.mark.slow, pytest.mark.timeout(420)]


def runtime_closure(requirements: list[str], extras: tuple[str, ...] = ()) -> dict[str, Distribution]:
    """The installed distributions that `requirements` need, transitively: without extras but
    `extras` of the first level (as `pip install 'fcemu[train]'`), and each dependency's own
    extras where a requirement names them (`ray[tune]`)."""
    found: dict[str, Distribution] = {}
    seen: set[tuple[str, str]] = set()
    todo = [(text, ("", *extras)) for text in requirements]
    while todo:
        text, active = todo.pop()
        req = Requirement(text)
        if req.marker is not None and not any(req.marker.evaluate({"extra": e}) for e in active):
            continue
        name = canonicalize_name(req.name)
        wanted = tuple(e for e in ("", *sorted(req.extras)) if (name, e) not in seen)
        if not wanted:
            continue
        seen.update((name, e) for e in wanted)
        if name not in found:
            try:
                dist = distribution(req.name)
            except PackageNotFoundError:
                pytest.fail(f"the wheel requires {req}, which the test's environment lacks")
            assert dist.version in req.specifier or not req.specifier, f"{req}: installed {dist.version}"
            found[name] = dist
        todo += [(dep, wanted) for dep in found[name].requires or []]
    return found


def link_distribution(dist: Distribution, site: Path) -> None:
    """Link the top-level entries (packages, modules, .libs, dist-info) of `dist` into `site`."""
    base = Path(dist.locate_file(""))
    for top in {f.parts[0] for f in dist.files or () if f.parts[0] != ".."}:
        target = site / top
        if not target.exists():
            target.symlink_to(base / top)


def wheel_requirements(wheel: Path) -> list[str]:
    with zipfile.ZipFile(wheel) as zf:
        meta = next(n for n in zf.namelist() if n.endswith(".dist-info/METADATA"))
        lines = zf.read(meta).decode().splitlines()
    return [line.split(":", 1)[1].strip() for line in lines if line.startswith("Requires-Dist:")]


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """A fresh venv with the wheel and its runtime dependencies; returns its bin directory."""
    work = tmp_path_factory.mktemp("wheel")
    return install_wheel(build_wheel(work), work / "venv")


def build_wheel(work: Path) -> Path:
    """The wheel, built from a copy of the checkout so that the build leaves nothing in it."""
    source = work / "source"
    shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns(
        ".git", ".venv", "runs", "build", "out", "*.egg-info", "__pycache__", ".pytest_cache", ".ruff_cache"))
    dist = work / "dist"
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "--no-build-isolation",
                    "-q", "-w", str(dist)], check=True, timeout=300)
    return next(dist.glob("fcemu-*.whl"))


def install_wheel(wheel: Path, venv: Path, extras: tuple[str, ...] = ()) -> Path:
    """A fresh venv at `venv` with `wheel` and the closure of its requirements (with `extras`),
    linked from the test's interpreter; returns its bin directory."""
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120, env=clean_env())
    python = venv / "bin" / "python"
    purelib = "import sysconfig; print(sysconfig.get_paths()['purelib'])"
    site = Path(subprocess.run([str(python), "-c", purelib], capture_output=True, text=True, check=True,
                               env=clean_env()).stdout.strip())
    assert site != Path(sysconfig.get_paths()["purelib"])
    for dep in runtime_closure(wheel_requirements(wheel), extras).values():
        link_distribution(dep, site)
    subprocess.run([str(python), "-m", "pip", "install", "-q", "--no-deps", "--no-index",
                    "--disable-pip-version-check", str(wheel)], check=True, timeout=300, env=clean_env())
    check = subprocess.run([str(python), "-m", "pip", "check"], capture_output=True, text=True, timeout=120,
                           env=clean_env())
    assert check.returncode == 0, check.stdout + check.stderr
    return venv / "bin"


def clean_env() -> dict[str, str]:
    """This environment without what points Python at the checkout or the test's venv."""
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME")}


def test_the_installed_wheel_has_no_dev_extras(installed: Path, tmp_path: Path) -> None:
    code = ("import importlib.util as u, fcemu.firmware as firmware, fcemu.sitl; "
            "print(firmware.__file__); print([m for m in ('torch', 'stable_baselines3') if u.find_spec(m)])")
    out = subprocess.run([str(installed / "python"), "-c", code], cwd=tmp_path, env=clean_env(),
                         capture_output=True, text=True, check=True).stdout.splitlines()
    assert Path(out[0]).is_relative_to(installed.parent) and out[1] == "[]"


def test_fcemu_demo_flies_the_shipped_policy_from_the_wheel(installed: Path, tmp_path: Path) -> None:
    done = subprocess.run([str(installed / "fcemu"), "demo", "--speed", "3"], cwd=tmp_path, env=clean_env(),
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr[-3000:]
    flying = [line for line in done.stderr.splitlines() if line.startswith("fcemu: flying ")]
    assert len(flying) == 1 and flying[0].startswith("fcemu: flying neural:iris_rate_ppo ("), done.stderr
    policy = Path(flying[0].rsplit("(", 1)[1].rstrip(")"))
    assert policy.is_relative_to(installed.parent) and policy.is_file()
    result = json.loads((tmp_path / "runs" / "demo" / "demo.json").read_text())
    assert result["flight"]["completed"] and result["controller"] == str(policy)
    assert (tmp_path / "runs" / "demo" / "flight.png").stat().st_size > 0


def test_the_wheel_installs_one_top_level_package(installed: Path) -> None:
    site = next((installed.parent / "lib").glob("python*/site-packages"))
    ours = {line.strip() for dist in site.glob("fcemu-*.dist-info") for line in
            (dist / "RECORD").read_text().splitlines() if line and not line.startswith(("fcemu-", "../"))}
    assert {entry.split("/")[0] for entry in ours} == {"fcemu"}


def test_a_users_training_folder_does_not_shadow_ours(installed: Path, tmp_path: Path) -> None:
    (tmp_path / "training").mkdir()
    (tmp_path / "training" / "__init__.py").write_text("raise SystemExit('the user\\'s training package')\n")
    done = subprocess.run([str(installed / "python"), "-m", "fcemu", "train", "--help"], cwd=tmp_path,
                          env=clean_env(), capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "usage: fcemu train" in done.stdout, done.stdout + done.stderr
