"""The STM32 Betaflight images the export tests check, built once per run in the background.

The two images take about 90 s of both cores. Much of the suite flies real-time SITLs that leave
a core idle, so the build starts as soon as collection has chosen a test that needs it, as a
SCHED_IDLE process (it gets only CPU no other process wants, so the timing tests do not feel it),
and those tests run last (`tests/conftest.py`). The build is `fcemu export --target betaflight`
itself, as a user runs it.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from fcemu.export.betaflight.build import CHIPS, MANIFEST
from tests.export.mcu_tools import SHIPPED

FIXTURE = "stm32_export"
_build: dict = {}


def _idle_priority() -> None:
    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))


def start() -> bool:
    """Start the build unless it runs or its tools are missing (the fixture then says why)."""
    if _build or shutil.which("arm-none-eabi-gcc") is None or shutil.which("arm-none-eabi-size") is None:
        return False
    root = Path(tempfile.mkdtemp(prefix="fcemu-stm32-"))
    out = root / "export"
    cmd = [sys.executable, "-m", "fcemu", "export", str(SHIPPED), "--target", "betaflight",
           "--betaflight-targets", ",".join(c.target for c in CHIPS), "--parity-samples", "1000",
           "--out", str(out), "--json"]
    with open(root / "export.log", "w") as log:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=log, start_new_session=True,
                                preexec_fn=_idle_priority if hasattr(os, "SCHED_IDLE") else None)
    _build.update(root=root, out=out, proc=proc)
    return True


def result(timeout_s: float) -> tuple[Path, dict]:
    """(the export directory, its manifest) once the build has ended; an AssertionError with its
    log's tail if it failed."""
    if not _build and not start():
        raise AssertionError("the STM32 build cannot start: no arm-none-eabi-gcc or arm-none-eabi-size")
    proc = _build["proc"]
    try:
        proc.wait(timeout=max(1.0, timeout_s))
    except subprocess.TimeoutExpired:
        raise AssertionError(f"the STM32 build did not end in {timeout_s:.0f} s") from None
    log = (_build["root"] / "export.log").read_text(errors="replace")
    assert proc.returncode == 0, f"fcemu export --target betaflight failed ({proc.returncode}): {log[-2000:]}"
    return _build["out"], json.loads((_build["out"] / MANIFEST).read_text())


def finish() -> None:
    """Stop a build no test waited for, and remove its files."""
    if not _build:
        return
    proc = _build["proc"]
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        deadline = time.monotonic() + 10.0
        while proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    shutil.rmtree(_build["root"], ignore_errors=True)
    _build.clear()
