"""Imports point one way, downwards: firmware < sim_bridge < sitl < the tools.

Every `import` and `from ... import` in the source tree, at module level or inside a
function, is checked against the layer it is in. A package may import itself and what
`ALLOWED` lists for it, nothing else of ours.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Our top-level packages and, for each, which of the others it may import.
ALLOWED: dict[str, set[str]] = {
    "firmware": set(),  # the vehicle: nothing of ours above it
    "sim_bridge": {"firmware"},  # the simulated world: the firmware's sensor frame, observation, action
    "sitl": {"firmware", "sim_bridge"},  # the vehicle composed with the simulated world
    "evaluation": {"firmware", "sim_bridge", "sitl"},  # flies controllers through the composed vehicle
    "export": {"firmware", "sim_bridge", "fcemu"},  # the airframe a run trained on: its envelope
    # A training run evaluates against the PID as it goes and exports the ONNX policy at its end.
    "training": {"firmware", "sim_bridge", "sitl", "evaluation", "export", "fcemu"},
    "benchmarks": {"firmware", "sim_bridge", "sitl", "evaluation", "export", "training"},
    "fcemu": {"firmware"},  # the console script names its handlers as strings, imported when they run
}
# What a layer below the console script may take from `fcemu`: its version string, nothing else.
FCEMU_FOR_OTHERS = {"fcemu"}


def imports_of(path: Path, package: str) -> list[tuple[int, str]]:
    """(line, module) for every import in the file, relative ones resolved to `package`."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            found.append((node.lineno, f"fcemu.{package}" if node.level else node.module or ""))
    return found


def layer_of(module: str, layers: dict[str, set[str]]) -> str | None:
    """The layer an absolute module name belongs to (`fcemu.sitl.demo` → sitl), None if not ours."""
    parts = module.split(".")
    if parts[0] != "fcemu":
        return None
    if len(parts) > 1 and parts[1] in layers and parts[1] != "fcemu":
        return parts[1]
    return "fcemu"


def violations(root: Path = ROOT, layers: dict[str, set[str]] = ALLOWED) -> list[str]:
    bad = []
    for package, allowed in layers.items():
        sources = sorted((root / package).rglob("*.py"))
        assert sources, f"no sources in {package}/"
        for path in sources:
            for line, module in imports_of(path, package):
                top = layer_of(module, layers)
                if top is None or top == package:
                    continue
                if top not in allowed:
                    bad.append(f"{path.relative_to(root)}:{line}: {package} imports {module}")
                elif top == "fcemu" and package != "fcemu" and module not in FCEMU_FOR_OTHERS:
                    bad.append(f"{path.relative_to(root)}:{line}: {package} imports {module} (only fcemu's "
                               "version is below the tools)")
    return bad


def test_every_package_is_in_a_layer() -> None:
    packages = {p.parent.name for p in ROOT.glob("*/__init__.py")} - {"tests"}
    assert packages == set(ALLOWED)


def test_imports_point_downwards() -> None:
    assert violations() == []


def test_the_checker_sees_function_level_imports(tmp_path) -> None:
    module = tmp_path / "firmware" / "late.py"
    module.parent.mkdir()
    module.write_text("def f():\n    from fcemu.sim_bridge.twin import Twin\n    return Twin\n")
    assert imports_of(module, "firmware") == [(2, "fcemu.sim_bridge.twin")]
    (tmp_path / "sim_bridge").mkdir()
    (tmp_path / "sim_bridge" / "twin.py").write_text("from fcemu.firmware.sensors import SensorFrame\n")
    layers = {"firmware": set(), "sim_bridge": {"firmware"}}
    assert violations(tmp_path, layers) == ["firmware/late.py:2: firmware imports fcemu.sim_bridge.twin"]


@pytest.mark.timeout(120)
def test_the_firmware_loads_without_the_twin() -> None:
    """Every firmware module imported: no MuJoCo, nothing of the layers above."""
    code = (
        "import importlib, pkgutil, sys\n"
        "import fcemu.firmware as firmware, fcemu.firmware.controllers, fcemu.firmware.vehicle\n"
        "assert 'mujoco' not in sys.modules, 'controllers/vehicle load mujoco'\n"
        "for m in pkgutil.walk_packages(firmware.__path__, 'fcemu.firmware.'):\n"
        "    importlib.import_module(m.name)\n"
        "ours = lambda n: n.split('.')[1] if n.startswith('fcemu.') else n.split('.')[0]\n"
        "above = sorted(n for n in sys.modules if ours(n) in "
        "('mujoco', 'sim_bridge', 'sitl', 'training', 'export', 'evaluation', 'benchmarks', 'torch'))\n"
        "assert not above, above\n"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=110)
    assert done.returncode == 0, done.stderr[-2000:]
