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
that step, the latest at each; slower ones are used at their own interval.

What the header says (the firmware and its version, the logging interval, the gyro filters'
lag, the rates that turn sticks into a setpoint) is `blackbox_header`'s; the pilot's tune is
`blackbox_tune`'s. Each arming in a file is a log of its own (`read_blackbox_logs`); frames a
storage error garbled are left out and counted.
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from fcemu.evaluation.blackbox_header import (
    firmware,
    gyro_filter_lag_s,
    logged_interval_s,
    stick_setpoint_dps,
    yaw_motors_reversed,
)
from fcemu.evaluation.blackbox_tune import log_tune
from fcemu.evaluation.identify_log import IDLE, FlightLog, LogError, flown_stretch

MAGIC = b"H Product:Blackbox flight data recorder by Nicholas Sherlock"
GRID_S = 0.001  # the twin's step: logs faster than this are held onto it
DSHOT_PROTOCOLS = (5, 6, 7, 8)  # Betaflight's motorProtocol_e: DSHOT150, 300, 600, PROSHOT1000
DSHOT_ZERO, DSHOT_SPAN = 48.0, 1999.0  # DShot's throttle values 48..2047
PWM_ZERO, PWM_SPAN = 1000.0, 1000.0  # Betaflight's analog outputs, µs
BOXARM_BIT = 1  # flightModeFlags is Betaflight's rcModeActivationMask; BOXARM is box 0
MAX_LOG_INTERVAL_S = 1 / 200  # slower than 200 Hz the rates' response (tens of ms) is a handful of samples
INTRA = "fcemu:intra"  # the column _frames adds: 1 for an intra (key) frame
MIN_THROTTLE = 0.05  # of the pilot's throttle range, held by no quad that flies
MIN_MOTOR_TRAVEL = 0.02  # of the output range: motors that never move say nothing of the vehicle


def is_blackbox(path: Path) -> bool:
    try:
        with open(path, "rb") as handle:
            return handle.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


def _log_starts(path: Path) -> tuple[bytes, list[int]]:
    data = path.read_bytes()
    starts = [0]
    while (found := data.find(MAGIC, starts[-1] + 1)) > 0:
        starts.append(found)
    return data, starts


def _parser(path: Path, index: int):
    """orangebox's parser on log `index` (1-based) of the file (a flash chip holds one per arming)."""
    try:
        from orangebox import Parser
    except ImportError:
        raise LogError(f"{path}: a Betaflight blackbox log; reading it needs the blackbox decoder: "
                       "pip install 'fcemu[blackbox]' (orangebox, GPL-3.0: docs/identify.md)") from None
    logging.getLogger("orangebox").setLevel(logging.CRITICAL)  # its per-frame warnings are not the user's
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # orangebox prints unknown events
            return Parser.load(str(path), index)
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
        with contextlib.redirect_stdout(io.StringIO()):
            for frame in parser.frames():
                rows.append((*frame.data[:len(names)], *[np.nan] * (len(names) - len(frame.data)),
                             1.0 if frame.type.value == "I" else 0.0))
    except (RuntimeError, IndexError, ValueError, KeyError, TypeError):  # orangebox on data cut mid-frame
        cut = True
    if len(rows) < 2:
        raise LogError(f"{path}: {len(rows)} data frames decoded: no flight in the log (truncated?)")
    table = np.array([[np.nan if v == "" else v for v in row] for row in rows], dtype=np.float64)
    return [*names, INTRA], table, cut


def _sound_frames(names: list[str], table: np.ndarray) -> np.ndarray:
    """Frames a corrupted stretch of the log did not garble: from an intra frame on, time running
    forward by less than a second from the last sound frame, motors and gyro in their ranges (inter
    frames before the first intra frame, or after a storage error, decode as garbage until the next
    intra frame; Betaflight's own viewer drops them too)."""
    t = table[:, names.index("time")]
    ok = np.isfinite(t)
    for base, limit in (("motor", 2100.0), ("gyroADC", 40000.0)):
        columns = [names.index(f"{base}[{i}]") for i in range(4 if base == "motor" else 3)
                   if f"{base}[{i}]" in names]
        if columns:
            values = table[:, columns]
            ok &= np.all((values >= (0.0 if base == "motor" else -limit)) & (values <= limit), axis=1)
    intra = table[:, names.index(INTRA)] > 0
    keep = np.zeros(len(t), dtype=bool)
    last = None
    for k in np.flatnonzero(ok):
        if (intra[k] and (last is None or t[k] > last)) or (last is not None and 0 < t[k] - last < 1e6):
            keep[k] = True
            last = t[k]
    return keep


def decode_blackbox(path: Path, index: int | None = None) -> tuple[list[str], np.ndarray, dict, list[str]]:
    """(field names, sound frames (N, fields) in time order, header, notes) of log `index` of the
    file (1-based), or of its longest log."""
    data, starts = _log_starts(path)
    count = len(starts)
    if index is None:
        index = int(np.argmax(np.diff([*starts, len(data)]))) + 1
    elif not 1 <= index <= count:
        raise LogError(f"{path}: log {index} asked for; the file holds {count}")
    parser = _parser(path, index)
    headers = parser.headers
    firmware(headers, path)
    names, table, cut = _frames(parser, path)
    notes = [f"log {index} of the {count} in the file"] if count > 1 else []
    if cut:
        notes.append("the log ends cut off (no end-of-log event): the frames before the cut are used")
    sound = _sound_frames(names, table)
    if sound.sum() < 2:
        raise LogError(f"{path}: no sound data frame in the log (corrupt?)")
    if (~sound).sum():
        notes.append(f"{(~sound).sum()} of {len(sound)} frames garbled (time running back or values out of "
                     "range) and left out")
    table = table[sound]
    order = np.argsort(table[:, names.index("time")], kind="stable")
    return names, table[order], headers, notes


def log_count(path: Path) -> int:
    return len(_log_starts(path)[1])


def read_blackbox_logs(path: Path, motor_poles: int | None = None) -> list[FlightLog]:
    """Every log in the file that holds a flight; a LogError (the longest's) where none does."""
    data, starts = _log_starts(path)
    sizes = np.diff([*starts, len(data)])
    logs, refused = [], []
    for index in range(1, len(starts) + 1):
        try:
            logs.append(read_blackbox_log(path, motor_poles, index))
        except LogError as exc:
            refused.append((sizes[index - 1], exc))
    if not logs:
        raise max(refused, key=lambda pair: pair[0])[1]
    if refused:
        why = str(max(refused, key=lambda pair: pair[0])[1]).removeprefix(f"{path}: ")
        note = (f"{len(refused)} of the {len(starts)} logs in the file hold no flight fcemu reads "
                f"(the longest of them: {why})")
        logs[0] = replace(logs[0], notes=(*logs[0].notes, note))
    return logs


def read_blackbox_log(path: Path, motor_poles: int | None = None, index: int | None = None) -> FlightLog:
    names, table, headers, notes = decode_blackbox(path, index)
    version = firmware(headers, path)
    t_us = table[:, names.index("time")]
    frame_dt = float(np.median(np.diff(t_us))) * 1e-6
    check_rate(path, frame_dt)
    interval = logged_interval_s(headers)
    if interval and abs(frame_dt / interval - 1) > 0.1:
        notes.append(f"the header makes the logging interval {interval * 1e3:.3f} ms, the frames "
                     f"{frame_dt * 1e3:.3f} ms: the frames' time stamps are used")
    gyro_name = "gyroUnfilt" if _columns(names, table, "gyroUnfilt", 3) is not None else "gyroADC"
    gyro_deg = _columns(names, table, gyro_name, 3)
    if gyro_deg is None:
        raise LogError(f"{path}: no gyroADC or gyroUnfilt fields (the gyro): clear blackbox_disable_gyro")
    motors = _columns(names, table, "motor", 4)
    if motors is None:
        raise LogError(f"{path}: no motor[0..3] fields (the motor outputs): clear blackbox_disable_motors")
    scale = 10.0 if headers.get("blackbox_high_resolution") == 1 else 1.0
    frd = np.array([1.0, -1.0, -1.0])  # Betaflight's axes to FRD
    gyro = np.radians(gyro_deg / scale) * frd
    low, high = _output_range(headers, motors)
    digital, zero, span = _protocol_scale(headers, high)
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
    check_motors_move(path, command[keep])
    check_throttle_leaves_idle(path, _mixer_throttle(names, table)[keep])
    rotor, rotor_note = _rotor_speed(names, table, headers, motor_poles)
    if rotor_note:
        notes.append(rotor_note)
    setpoint = _setpoint(names, table, headers)
    battery = _battery(names, table, version)
    lag, lag_note = 0.0, "gyroUnfilt, before the gyro filters"
    if gyro_name == "gyroADC":
        hover = float(np.median(command[keep].mean(axis=1))) if keep.any() else None
        lag, lag_note = gyro_filter_lag_s(headers, hover)
        notes.append(f"the filtered gyroADC is read: its filters' lag, {lag * 1e3:.2f} ms ({lag_note}), is "
                     "known from the header and not fitted as delay")
    sample_t, held, note = _samples(t_us, gyro_deg)
    if note:
        notes.append(note)
    index_text = next((n for n in notes if n.startswith("log ") and " of the " in n), "")
    return flown_stretch(path, sample_t, gyro[held], command[held], keep[held],
                         None if rotor is None else rotor[held], None if throttle is None else throttle[held],
                         source, tuple(notes), setpoint=None if setpoint is None else setpoint[held] * frd,
                         battery_v=None if battery is None else battery[held], gyro_filter_lag_s=lag,
                         gyro_filter_note=lag_note, props_reversed=yaw_motors_reversed(headers),
                         header=dict(headers), title=index_text)


def check_rate(path: Path, interval_s: float) -> None:
    if interval_s > MAX_LOG_INTERVAL_S:
        raise LogError(f"{path}: logged at {1 / interval_s:.0f} Hz: a rate twin needs at least "
                       f"{1 / MAX_LOG_INTERVAL_S:.0f} Hz (set blackbox_sample_rate / P ratio higher)")


def check_motors_move(path: Path, armed_command: np.ndarray) -> None:
    """`armed_command` (N, 4), 0..1, armed and above idle: refused where no motor ever moves."""
    if len(armed_command) and np.ptp(armed_command, axis=0).max() < MIN_MOTOR_TRAVEL:
        raise LogError(f"{path}: the motors never move (their outputs span less than {MIN_MOTOR_TRAVEL:.0%} "
                       "of the range): a ground-only or bench log")


def _mixer_throttle(names: list[str], table: np.ndarray) -> np.ndarray:
    """(N,) the pilot's throttle 0..1 over the mixer's range: `setpoint[3]` (‰), else the stick (3.x)."""
    if "setpoint[3]" in names:
        return np.nan_to_num(table[:, names.index("setpoint[3]")]) / 1000.0
    if "rcCommand[3]" in names:
        return np.clip((np.nan_to_num(table[:, names.index("rcCommand[3]")]) - 1000.0) / 1000.0, 0.0, 1.0)
    return np.ones(len(table))  # not logged: not judged


def check_throttle_leaves_idle(path: Path, armed_throttle: np.ndarray) -> None:
    """`armed_throttle` 0..1 of the mixer's range: refused where it stays at idle (armed on the ground)."""
    if len(armed_throttle) and np.percentile(armed_throttle, 95) < MIN_THROTTLE:
        raise LogError(f"{path}: the throttle stays below {MIN_THROTTLE:.0%} for 95 % of the armed time: "
                       "armed on the ground, not flown")


def _setpoint(names: list[str], table: np.ndarray, headers: dict) -> np.ndarray | None:
    """(N, 3) rad/s in Betaflight's axes: the logged setpoint (4.x), else the sticks through the rates."""
    logged = _columns(names, table, "setpoint", 3)
    if logged is None:
        sticks = _columns(names, table, "rcCommand", 3)
        if sticks is None:
            return None
        logged = stick_setpoint_dps(headers, np.nan_to_num(sticks))
    return np.radians(np.nan_to_num(logged))


def _battery(names: list[str], table: np.ndarray, version: tuple[int, ...]) -> np.ndarray | None:
    """(N,) V from vbatLatest: 0.01 V a unit from Betaflight 4.0, 0.1 V before."""
    if "vbatLatest" not in names:
        return None
    raw = table[:, names.index("vbatLatest")]
    volts = raw * (0.01 if version >= (4, 0) else 0.1)
    return volts if np.nanmax(volts) > 1.0 else None


def _columns(names: list[str], table: np.ndarray, base: str, count: int) -> np.ndarray | None:
    idx = [names.index(f"{base}[{i}]") for i in range(count) if f"{base}[{i}]" in names]
    return table[:, idx] if len(idx) == count else None


def _header_int(headers: dict, key: str) -> int | None:
    value = headers.get(key)
    return int(value) if isinstance(value, int | float) else None


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


def _protocol_scale(headers: dict, high: float) -> tuple[bool, float, float]:
    """(digital, the output at command 0, the span to command 1) of the motor protocol the header
    names (`motor_pwm_protocol`, 3.x `fast_pwm_protocol`), else guessed from the outputs' top."""
    protocol = _header_int(headers, "motor_pwm_protocol")
    if protocol is None:
        protocol = _header_int(headers, "fast_pwm_protocol")
    digital = protocol in DSHOT_PROTOCOLS if protocol is not None else high > 2000
    return (True, DSHOT_ZERO, DSHOT_SPAN) if digital else (False, PWM_ZERO, PWM_SPAN)


def mixer_throttle(header: dict, command: float) -> float:
    """Betaflight's mixer throttle (0..1 of `motorOutput`) for a motor command (0..1 of the protocol)."""
    value = header.get("motorOutput")
    paired = isinstance(value, list) and len(value) == 2
    low, high = (float(value[0]), float(value[1])) if paired else (0.0, 1.0)
    _, zero, span = _protocol_scale(header, high)
    if high <= low:
        return command
    return float(np.clip((zero + span * command - low) / (high - low), 0.0, 1.0))


def own_tune(log: FlightLog) -> dict:
    """The log's own tune as an fcemu preset, its TPA at the flight's median collective."""
    collective = log.throttle if log.throttle is not None else log.command.mean(axis=1)
    hover = mixer_throttle(log.header, float(np.median(collective)))
    return log_tune(log.header, log.path, hover_throttle=hover)
