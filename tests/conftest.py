"""Fixtures and hooks shared across the test packages."""

import json
from pathlib import Path

import pytest

from tests.export import stm32_build
from tests.firmware.mavlink.conftest import sitl

__all__ = ["sitl"]  # a real `fcemu sitl` on loopback ports, stopped after the test


@pytest.fixture
def untuned_airframe(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An airframe file no PID tune is shipped for: the X500 named my_quad, alone in a folder of its own."""
    from fcemu.firmware.pid_controller import PRESET_DIR
    from fcemu.sim_bridge.airframe import AIRFRAME_DIR

    raw = json.loads((AIRFRAME_DIR / "x500.json").read_text())
    raw["name"] = "my_quad"
    assert not (PRESET_DIR / f"pid_{raw['name']}.json").exists()
    path = tmp_path_factory.mktemp("untuned") / "my_quad.json"
    path.write_text(json.dumps(raw, indent=1))
    return path


@pytest.hookimpl(trylast=True)  # after `-m` has deselected: the build only where its tests run
def pytest_collection_modifyitems(session, config, items) -> None:
    """The tests of the STM32 images go last, their build started now in the background."""
    users = [item for item in items if stm32_build.FIXTURE in getattr(item, "fixturenames", ())]
    if users and stm32_build.start():
        items[:] = [item for item in items if item not in users] + users


def pytest_sessionfinish(session, exitstatus) -> None:
    stm32_build.finish()
