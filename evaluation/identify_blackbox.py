"""A Betaflight blackbox log read for identification: the same arrays as a PX4 ULog gives.

The decoder is orangebox (PyPI, GPL-3.0, the optional extra `fcemu[blackbox]`), imported here
and nowhere else, so fcemu without that extra stays MIT and never loads it (docs/identify.md).
Betaflight logs every `blackbox_sample_rate`-th PID loop: the frames' `time` (µs), the raw gyro
`gyroUnfilt` (else the filtered `gyroADC`) in deg/s (×10 with `blackbox_high_resolution`), in
Betaflight's axes (roll, pitch and yaw with pitch and yaw the other way round from FRD), the
motor outputs `motor[0..3]` in the protocol's units (1000-2000 µs for PWM-like, 48-2047 for
DShot: `motorOutput` and `motor_pwm_protocol` in the header), the mixer throttle `setpoint[3]`
(‰ of the motor output range), `eRPM[0..3]` (eRPM / 100) with bidirectional DShot, and the
arm switch in `flightModeFlags` (bit 0, BOXARM). A sample is a frame with a new gyro reading:
Betaflight's SITL logs its 8 kHz loop while its gyro is new once per simulator packet (1 kHz),
and holding frames onto a time grid there would pick readings a packet early or late on its
jittering clock (seen as four times the gyro noise); its clock also runs on while it waits for
a packet, so the readings, not its time stamps, count the twin's steps. (A gyro without noise,
reading the same for several packets at rest, loses those steps; a real one never does.)
Readings faster than the twin's 1 ms step (a board's 8 kHz gyro logged at 1/1) are held onto
that step, the latest at each.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from fcemu.evaluation.identify_log import IDLE, FlightLog, LogError, flown_stretch

MAGIC = b"H Product:Blackbox flight data recorder by Nicholas Sherlock"
GRID_S = 0.001  # the twin's step: logs faster than this are held onto it
DSHOT_PROTOCOLS = (5, 6, 7, 8)  # Betaflight's motorProtocol_e: DSHOT150, 300, 600, PROSHOT1000
DSHOT_ZERO, DSHOT_SPAN = 48.0, 1999.0  # DShot's throttle values 48..2047
PWM_ZERO, PWM_SPAN = 1000.0, 1000.0  # Betaflight's analog outputs, µs
BOXARM_BIT = 1  # flightModeFlags is Betaflight's rcModeActivationMask; BOXARM is box 0


def is_blackbox(path: Path) -> bool:
    try:
        with open(path, "rb") as handle:
            return handle.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


def _parser(path: Path):
    """orangebox's parser on the longest log in the file (a flash chip holds one per arming)."""
    try:
        from orangebox import Parser
    except ImportError:
        raise LogError(f"{path}: a Betaflight blackbox log; reading it needs the blackbox decoder: "
                       "pip install 'fcemu[blackbox]' (orangebox, GPL-3.0: docs/identify.md)") from None
    data = path.read_bytes()
    starts = [0]
    while (found := data.find(MAGIC, starts[-1] + 1)) > 0:
        starts.append(found)
    sizes = np.diff([*starts, len(data)])
    index = int(np.argmax(sizes)) + 1
    logging.getLogger("orangebox").setLevel(logging.ERROR)  # its per-frame warnings are not the user's
    try:
        return Parser.load(str(path), index), index, len(starts)
    except Exception as exc:  # orangebox raises bare exceptions on a broken header
        raise LogError(f"{path}: not a readable blackbox log ({type(exc).__name__}: "
                       f"{' '.join(str(exc).split())[:100]})") from None


def _frames(parser, path: Path) -> tuple[list[str], np.ndarray, bool]:
    """The main frames as a (N, fields) float array (slow fields held, NaN before the first), and
    whether the log ends cut off (no end-of-log event: the frames before the cut are kept)."""
    names = parser.field_names
    rows = []
    cut = False
    try:
        for frame in parser.frames():
            rows.append(frame.data[:len(names)])
    except (RuntimeError, IndexError, ValueError, KeyError, TypeError):  # orangebox on data cut mid-frame
        cut = True
    if len(rows) < 2:
        raise LogError(f"{path}: {len(rows)} data frames decoded: no flight in the log (truncated?)")
    table = np.array([[np.nan if v == "" else v for v in row] for row in rows], dtype=np.float64)
    return names, table, cut


def _columns(names: list[str], table: np.ndarray, base: str, count: int) -> np.ndarray | None:
    idx = [names.index(f"{base}[{i}]") for i in range(count) if f"{base}[{i}]" in names]
    return table[:, idx] if len(idx) == count else None


def _header_int(headers: dict, key: str) -> int | None:
    value = headers.get(key)
    return int(value) if isinstance(value, int | float) else None


def decode_blackbox(path: Path) -> tuple[list[str], np.ndarray, dict, list[str]]:
    """(field names, frames (N, fields) in time order, header, notes) of the longest Betaflight log."""
    parser, index, count = _parser(path)
    headers = parser.headers
    firmware = str(headers.get("Firmware type", "?"))
    if firmware != "Betaflight":
        raise LogError(f"{path}: a {firmware} blackbox log; only Betaflight's units are read")
    names, table, cut = _frames(parser, path)
    notes = [f"log {index} of the {count} in the file (the longest)"] if count > 1 else []
    if cut:
        notes.append("the log ends cut off (no end-of-log event): the frames before the cut are used")
    order = np.argsort(table[:, names.index("time")], kind="stable")
    return names, table[order], headers, notes


def read_blackbox_log(path: Path, motor_poles: int | None = None) -> FlightLog:
    names, table, headers, notes = decode_blackbox(path)
    t_us = table[:, names.index("time")]
    gyro_name = "gyroUnfilt" if _columns(names, table, "gyroUnfilt", 3) is not None else "gyroADC"
    gyro_deg = _columns(names, table, gyro_name, 3)
    if gyro_deg is None:
        raise LogError(f"{path}: no gyroADC or gyroUnfilt fields (the gyro): clear blackbox_disable_gyro")
    if gyro_name == "gyroADC":
        notes.append("gyroUnfilt is not logged: the filtered gyroADC stands in (its filters' lag counts "
                     "as gyro delay)")
    motors = _columns(names, table, "motor", 4)
    if motors is None:
        raise LogError(f"{path}: no motor[0..3] fields (the motor outputs): clear blackbox_disable_motors")
    scale = 10.0 if headers.get("blackbox_high_resolution") == 1 else 1.0
    gyro = np.radians(gyro_deg / scale) * np.array([1.0, -1.0, -1.0])  # Betaflight's axes to FRD
    low, high = _output_range(headers, motors)
    protocol = _header_int(headers, "motor_pwm_protocol")
    digital = protocol in DSHOT_PROTOCOLS if protocol is not None else high > 2000
    zero, span = (DSHOT_ZERO, DSHOT_SPAN) if digital else (PWM_ZERO, PWM_SPAN)
    command = np.clip((motors - zero) / span, 0.0, 1.0)
    source = f"motor[0..3] ({'DShot 48-2047' if digital else '1000-2000 µs'})"
    throttle = None
    if "setpoint[3]" in names:
        mixer = table[:, names.index("setpoint[3]")] / 1000.0
        throttle = (low + (high - low) * mixer - zero) / span
    keep = command.max(axis=1) > IDLE
    if "flightModeFlags" in names:
        flags = np.nan_to_num(table[:, names.index("flightModeFlags")], nan=0.0).astype(np.int64)
        armed = (flags & BOXARM_BIT) > 0
        if not armed.any():
            raise LogError(f"{path}: the arm switch is never on (flightModeFlags): a ground-only log")
        keep &= armed
    rotor, rotor_note = _rotor_speed(names, table, headers, motor_poles)
    if rotor_note:
        notes.append(rotor_note)
    sample_t, held, note = _samples(t_us, gyro_deg)
    if note:
        notes.append(note)
    return flown_stretch(path, sample_t, gyro[held], command[held], keep[held],
                         None if rotor is None else rotor[held], None if throttle is None else throttle[held],
                         source, tuple(notes))


def _output_range(headers: dict, motors: np.ndarray) -> tuple[float, float]:
    value = headers.get("motorOutput")
    if isinstance(value, list) and len(value) == 2:
        return float(value[0]), float(value[1])
    return float(np.nanmin(motors)), float(np.nanmax(motors))


def _rotor_speed(names: list[str], table: np.ndarray, headers: dict,
                 motor_poles: int | None) -> tuple[np.ndarray | None, str]:
    """(N, 4) rad/s from the eRPM fields, or None and why not."""
    erpm = _columns(names, table, "eRPM", 4)
    if erpm is None:
        return None, ""
    poles = _header_int(headers, "motor_poles") or motor_poles
    if not poles:
        return None, "eRPM is logged but no pole count is known (motor_poles): the rpm is left out"
    rpm = np.nan_to_num(erpm) * 100.0 / (poles / 2)
    if not np.any(rpm > 0):
        return None, "eRPM is logged but always 0 (no bidirectional DShot telemetry): the rpm is left out"
    return rpm * (2 * math.pi / 60), ""


def _samples(t_us: np.ndarray, raw_gyro: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
    """(times µs, frame index of each sample, what was done): one sample per new gyro reading (a
    frame repeating the last reading carries none), then, for readings faster than the twin's
    step, the latest at each step."""
    new = np.ones(len(t_us), dtype=bool)
    new[1:] = np.any(raw_gyro[1:] != raw_gyro[:-1], axis=1)
    index = np.flatnonzero(new)
    frame_hz = 1e6 / float(np.median(np.diff(t_us)))
    note = ""
    if len(index) < 0.9 * len(t_us) and len(index) > 2:
        interval_us = float(np.median(np.diff(t_us[index])))
        times = t_us[index[0]] + np.arange(len(index)) * interval_us  # each reading one step
        note = (f"{frame_hz:.0f} Hz frames with the raw gyro new at {1e6 / interval_us:.0f} Hz: one sample "
                "per reading")
    else:
        index = np.arange(len(t_us))
        times = t_us
    interval_s = float(np.median(np.diff(times))) * 1e-6
    if interval_s < 0.75 * GRID_S:  # readings faster than the twin's step: hold the latest at each step
        grid = times[0] + np.arange(int((times[-1] - times[0]) // (GRID_S * 1e6)) + 1) * GRID_S * 1e6
        index = index[np.clip(np.searchsorted(times, grid, side="right") - 1, 0, len(times) - 1)]
        times = grid
        note = f"{1 / interval_s:.0f} Hz gyro readings held onto the twin's {1 / GRID_S:.0f} Hz step"
    return times, index, note
