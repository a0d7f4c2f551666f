"""Shared by the C-export tests: the exported shipped policy and the toolchain checks.

Outside CI a missing tool skips with the reason (`make mcu-tools` installs them); in CI
(the CI environment variable set) it fails, so the cross-compile and QEMU run are never
silently left out there.
"""

from __future__ import annotations

import importlib.util
import os
import shutil

import pytest

from fcemu.firmware.controllers import DEFAULT_POLICY

SHIPPED = DEFAULT_POLICY


def _missing(what: str) -> None:
    message = f"{what} not installed (`make mcu-tools`, `pip install 'fcemu[mcu]'`)"
    if os.environ.get("CI"):
        pytest.fail(f"{message}; CI must run these tests")
    pytest.skip(message)


def require_codegen() -> None:
    if importlib.util.find_spec("emx_onnx_cgen") is None:
        _missing("emx-onnx-cgen")
    if shutil.which("cc") is None:
        _missing("a host C compiler (cc)")


def require_target_tools() -> None:
    from fcemu.export.c.target import missing_tools

    require_codegen()
    missing = missing_tools()
    if missing:
        _missing(", ".join(missing))
