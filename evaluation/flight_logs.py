"""A flight log of either kind, told apart by its first bytes: a PX4 ULog (`identify_log`) or a
Betaflight blackbox log (`identify_blackbox`)."""

from __future__ import annotations

from pathlib import Path

from fcemu.evaluation.identify_blackbox import is_blackbox, read_blackbox_log, read_blackbox_logs
from fcemu.evaluation.identify_log import FlightLog, read_ulog


def read_flight_log(path: str | Path, motor_poles: int | None = None) -> FlightLog:
    """The flight in a PX4 ULog or a Betaflight blackbox log (`motor_poles` turns a blackbox log's
    eRPM into rotor speed where its header does not say)."""
    path = Path(path)
    return read_blackbox_log(path, motor_poles) if is_blackbox(path) else read_ulog(path)


def read_flight_logs(paths: list[str | Path], motor_poles: int | None = None) -> list[FlightLog]:
    """Every flight in the logs: a blackbox file's every arming that flew, a ULog's flight."""
    logs: list[FlightLog] = []
    for path in map(Path, paths):
        logs += read_blackbox_logs(path, motor_poles) if is_blackbox(path) else [read_ulog(path)]
    return logs
