"""Imports point one way, downwards: firmware < sim_bridge < sitl < the tools; and no module
imports itself through others.

Every `import` and `from ... import` in the source tree, at module level, inside a function or
for type checking only, is checked against the layer it is in. A package may import itself and
what `ALLOWED` lists for it, nothing else of ours. Within the tree the imports between modules
form no cycle: two modules that need each other share a third they both import.
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


def modules(root: Path = ROOT, layers: dict[str, set[str]] = ALLOWED) -> dict[str, Path]:
    """Every module of the tree by its import name (`training/fit.py` → fcemu.training.fit)."""
    found = {}
    for package in layers:
        for path in sorted((root / package).rglob("*.py")):
            parts = [p for p in path.relative_to(root / package).with_suffix("").parts if p != "__init__"]
            found[".".join(["fcemu", *([] if package == "fcemu" else [package]), *parts])] = path
    return found


def import_graph(root: Path = ROOT, layers: dict[str, set[str]] = ALLOWED) -> dict[str, set[str]]:
    """Each module's imports of other modules of the tree: `from a.b import c` is a.b.c where that
    is a module, else a.b (the longest of its prefixes that is one)."""
    names = modules(root, layers)
    graph: dict[str, set[str]] = {name: set() for name in names}
    for name, path in names.items():
        package = path.relative_to(root).parts[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                imported = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = f"fcemu.{package}" if node.level else node.module or ""
                imported = [f"{base}.{alias.name}" for alias in node.names]
            else:
                continue
            for target in imported:
                while target and target not in names:
                    target = target.rpartition(".")[0]
                if target and target != name:
                    graph[name].add(target)
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[set[str]]:
    """The groups of more than one module each of which imports, through the others, every other."""
    reach: dict[str, set[str]] = {}
    for start in graph:
        seen, todo = set(), [start]
        while todo:
            for target in graph[todo.pop()] - seen:
                seen.add(target)
                todo.append(target)
        reach[start] = seen
    groups = {frozenset({m, *(n for n in reach[m] if m in reach[n])}) for m in sorted(graph)}
    return sorted((set(g) for g in groups if len(g) > 1), key=sorted)


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


def test_no_module_imports_itself_through_others() -> None:
    assert [sorted(c) for c in import_cycles(import_graph())] == []


def test_the_cycle_finder_sees_function_and_type_checking_imports(tmp_path) -> None:
    (tmp_path / "training").mkdir()
    (tmp_path / "training" / "a.py").write_text("from fcemu.training import b\n")
    (tmp_path / "training" / "b.py").write_text("def f():\n    from fcemu.training.c import g\n")
    (tmp_path / "training" / "c.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                                "    from fcemu.training.a import A\n")
    (tmp_path / "training" / "d.py").write_text("import fcemu.training.a\n")
    graph = import_graph(tmp_path, {"training": set()})
    assert graph["fcemu.training.d"] == {"fcemu.training.a"}
    assert import_cycles(graph) == [{"fcemu.training.a", "fcemu.training.b", "fcemu.training.c"}]


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
