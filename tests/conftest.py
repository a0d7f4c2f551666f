"""Fixtures and hooks shared across the test packages."""

import pytest

from tests.export import stm32_build
from tests.firmware.mavlink.conftest import sitl

__all__ = ["sitl"]  # a real `fcemu sitl` on loopback ports, stopped after the test


@pytest.hookimpl(trylast=True)  # after `-m` has deselected: the build only where its tests run
def pytest_collection_modifyitems(session, config, items) -> None:
    """The tests of the STM32 images go last, their build started now in the background."""
    users = [item for item in items if stm32_build.FIXTURE in getattr(item, "fixturenames", ())]
    if users and stm32_build.start():
        items[:] = [item for item in items if item not in users] + users


def pytest_sessionfinish(session, exitstatus) -> None:
    stm32_build.finish()
