"""No airframe's numbers outside its airframe file: the Iris's, written once in code, made every
other airframe fly as an Iris. Each finding names file:line.

The source tree is every package's code (tests, airframe and preset files, docs excluded); a line
may keep one only with an `airframe-constant:` comment saying why and until when.
"""

from __future__ import annotations

import re
from pathlib import Path

from tests.test_layers import ALLOWED, ROOT

SUFFIXES = {".py", ".c", ".h", ".patch", ".yaml", ".yml", ".toml"}
EXCLUDED_DIRS = {"airframes", "presets", "__pycache__"}
ALLOWED_MARK = "airframe-constant:"
# The Iris's numbers where they mean the Iris: its top rotor speed, thrust coefficient, masses,
# motor time constants and inertia.
IRIS = {
    "top rotor speed 1100 rad/s": re.compile(r"(?<![\d.])1100(?:\.0*)?(?![\d.])"),
    "thrust coefficient 5.84e-6": re.compile(r"5\.84e-0?6"),
    "mass 1.5 kg (base) or 1.6 kg (total)": re.compile(r"mass\w*\W{1,4}[^\n]{0,30}(?<![\d.])1\.[56](?![\d])"),
    "motor time constants 0.0125 s, 0.025 s": re.compile(
        r"(?:tau|time_constant|time constant)[^\n]{0,30}(?<![\d.])0\.0(?:125|25)(?!\d)"),
    "inertia 0.008, 0.015, 0.017 kg m²": re.compile(r"inertia[^\n]{0,40}(?<![\d.])0\.0(?:08|15|17)(?!\d)"),
}


def sources(root: Path = ROOT) -> list[Path]:
    return sorted(p for package in ALLOWED for p in (root / package).rglob("*")
                  if p.suffix in SUFFIXES and p.is_file() and not EXCLUDED_DIRS & set(p.parts))


def iris_constants(paths: list[Path], root: Path = ROOT) -> list[str]:
    found = []
    for path in paths:
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if ALLOWED_MARK in line:
                continue
            found += [f"{path.relative_to(root)}:{number}: the Iris's {what}: {line.strip()[:80]}"
                      for what, pattern in IRIS.items() if pattern.search(line)]
    return found


def test_no_iris_constant_lives_outside_the_airframe_files() -> None:
    found = iris_constants(sources())
    assert not found, "\n".join(found)


def test_the_check_finds_each_constant_and_passes_others(tmp_path: Path) -> None:
    code = tmp_path / "code.py"
    code.write_text("top = 1100.0\nkf = 5.84e-6\nbase_mass = 1.5\ntau_up: float = 0.0125\n"
                    "base_inertia = (0.008, 0.015, 0.017)\nport = 11000\nx = 1100.5\nmass_scale = 1.25\n"
                    "top = 1100.0  # airframe-constant: an example\n")
    found = iris_constants([code], tmp_path)
    assert [f.split(":")[1] for f in found] == ["1", "2", "3", "4", "5"]
    assert found[0].startswith("code.py:1: the Iris's top rotor speed")
