"""Fixtures shared across the test packages."""

from tests.firmware.mavlink.conftest import sitl

__all__ = ["sitl"]  # a real `fcemu sitl` on loopback ports, stopped after the test
