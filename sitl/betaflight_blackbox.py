"""Betaflight SITL's own blackbox: switched on, kept, and handed over as one file.

With `blackbox_device = VIRTUAL` (`USE_BLACKBOX_VIRTUAL` in the SITL target) Betaflight's
blackbox code writes each arming's log to a file in its working directory
(`src/main/blackbox/blackbox_virtual.c`), closing it after the disarm with its end-of-log event.
Betaflight 4.6's SITL names the file `LOG00001.BF`, not `.BFL`: its name buffer is one byte
short. It also looks only for `.BFL` names when it starts, so a restarted SITL numbers from 1
again and would overwrite the earlier logs: each start first moves them to `blackbox/` in the
run directory (`shelve_logs`), and `write_blackbox` joins them, in the order flown, into one
file, as a flash chip holds one log after another.

`blackbox_sample_rate = 1/1` logs every PID loop (8 kHz in the SITL), `blackbox_high_resolution`
keeps the rates to 0.1 deg/s; the default fields include the raw gyro (`gyroUnfilt`) and the
motor outputs.
"""

from __future__ import annotations

import time
from pathlib import Path

BLACKBOX_SETTINGS = (
    "set blackbox_device = VIRTUAL",
    "set blackbox_sample_rate = 1/1",
    "set blackbox_high_resolution = ON",
)
SITL_LOG_GLOB = "LOG[0-9][0-9][0-9][0-9][0-9].BF*"
SHELF = "blackbox"
END_OF_LOG = b"End of log\x00"


def sitl_logs(run_dir: Path) -> list[Path]:
    """The logs the SITL has written in `run_dir`, oldest first."""
    return sorted(Path(run_dir).glob(SITL_LOG_GLOB), key=lambda p: (p.stat().st_mtime_ns, p.name))


def shelve_logs(run_dir: Path) -> list[Path]:
    """Move the SITL's logs into run_dir/blackbox/, numbered after those there; returns the shelf's."""
    shelf = Path(run_dir) / SHELF
    kept = sorted(shelf.glob("*.BFL"))
    for log in sitl_logs(run_dir):
        shelf.mkdir(exist_ok=True)
        target = shelf / f"{len(kept) + 1:05d}.BFL"
        log.replace(target)
        kept.append(target)
    return kept


def logs_finished(run_dir: Path) -> bool:
    """Every log the SITL has open in `run_dir` ends with its end-of-log event."""
    for log in sitl_logs(run_dir):
        with open(log, "rb") as handle:
            handle.seek(max(log.stat().st_size - len(END_OF_LOG), 0))
            if handle.read() != END_OF_LOG:
                return False
    return True


def await_logs(run_dir: Path, keep_alive, timeout_s: float = 2.0) -> bool:
    """Call `keep_alive()` (a step of the link: the SITL's clock runs on its packets) until the
    logs are closed, at most `timeout_s` of wall time; whether they were."""
    end = time.monotonic() + timeout_s
    while not logs_finished(run_dir):
        if time.monotonic() > end:
            return False
        keep_alive()
    return True


def write_blackbox(run_dir: Path, destination: str | Path) -> tuple[Path, int]:
    """Join the run's logs (shelved and still in place) into `destination`; (its path, how many:
    none written where the SITL never armed)."""
    logs = shelve_logs(run_dir)
    destination = Path(destination)
    if not logs:
        return destination, 0
    destination.parent.mkdir(parents=True, exist_ok=True)
    with open(destination, "wb") as out:
        for log in logs:
            out.write(log.read_bytes())
    return destination, len(logs)
