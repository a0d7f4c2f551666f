"""A PX4 ULog read for identification: gyro, motor commands and ESC rpm on one time grid.

The grid is the gyro's samples (`vehicle_angular_velocity.timestamp_sample`); the motor
commands (`actuator_motors.control`, normalised 0..1, or else `actuator_outputs.output` in µs on
the firmware's 1000-2000 µs scale) are held from the gyro sample each was computed from, and the
ESC rpm (`esc_status.esc[i].esc_rpm`) is interpolated to it. Only the armed stretch of the log,
motors above idle, is kept. A log that cannot be identified is one `LogError` line saying what
it lacks.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fcemu.firmware.action import PWM_MIN, PWM_SPAN
from fcemu.firmware.errors import UserError

GYRO = "vehicle_angular_velocity"
MIN_FLIGHT_S = 1.0  # of armed flight with the motors above idle
MIN_RATE = 0.3  # rad/s: a log whose rates never reach it was not flown (or never excited)
IDLE = 0.02  # motor command 0..1 below which a motor is at rest
MIN_ESC_SHARE = 0.5  # ESC telemetry slower than this share of the gyro's rate cannot show the motor lag


class LogError(UserError):
    """A log that cannot be identified: not a ULog, truncated, missing a topic, not a flight."""


@dataclass(frozen=True)
class FlightLog:
    path: Path
    t: np.ndarray  # (T,) s from the first sample kept
    gyro: np.ndarray  # (T, 3) rad/s FRD
    command: np.ndarray  # (T, 4) 0..1, Betaflight/PX4 motor order
    rotor_speed: np.ndarray | None  # (T, 4) rad/s from the ESC telemetry; None where none was logged
    throttle: np.ndarray | None  # (T,) the collective setpoint, 0..1
    command_source: str  # which topic the motor commands came from
    notes: tuple[str, ...] = ()  # what of the log was left unused, and why
    setpoint: np.ndarray | None = None  # (T, 3) rad/s FRD: the rate setpoint the log's controller flew
    battery_v: np.ndarray | None = None  # (T,) the battery voltage, V
    gyro_filter_lag_s: float = 0.0  # the logged gyro's known filter lag (Betaflight's gyroADC)
    gyro_filter_note: str = ""  # which filters make that lag
    props_reversed: bool | None = None  # the log's header on the motors' spin (None: it does not say)
    header: dict | None = None  # a Betaflight log's header: its own tune, rates and filters
    title: str = ""  # which log of the file, where it holds several

    @property
    def dt(self) -> float:
        return float(np.median(np.diff(self.t)))

    @property
    def name(self) -> str:
        return self.path.name + (f" ({self.title})" if self.title else "")


def _read(path: Path):
    """The ULog at `path`, read up to its last complete message: a log cut off mid-message (the
    battery pulled while it was written) keeps the messages before the cut, and says so in the
    `fcemu_notes` it is given (empty where the file is whole)."""
    import io

    from pyulog import ULog
    from pyulog.core import ULogException

    try:
        data = path.read_bytes()
    except OSError as exc:
        raise LogError(f"{path}: cannot read it ({(exc.strerror or type(exc).__name__).lower()})") from None
    if data[:7] != bytes(ULog.HEADER_BYTES[:7]):
        raise LogError(f"{path}: not a PX4 ULog or a Betaflight blackbox log (no header of either)")
    cut = _check_complete(path, data)
    try:
        log = ULog(io.BytesIO(data[:cut]))
    except (ULogException, ValueError, struct.error, IndexError, UnicodeDecodeError) as exc:
        raise LogError(f"{path}: not a readable ULog ({' '.join(str(exc).split())[:120]})") from None
    if log.file_corruption:
        raise LogError(f"{path}: the ULog is truncated or corrupt (pyulog found a broken message)")
    log.fcemu_notes = () if cut == len(data) else (
        f"the log ends cut off (power lost?): read up to byte {cut} of {len(data)}",)
    return log


def _check_complete(path: Path, data: bytes) -> int:
    """The byte the ULog's last complete message ends at: the file's length where it is whole.
    pyulog drops a message cut off at the end of the file without a word, so walk the messages
    (each a uint16 size, a uint8 type and the payload, after the 16-byte file header) to the end.
    A file that ends before its first logged data (`D` message) has nothing to read: a LogError."""
    position, logged = 16, False
    while position + 3 <= len(data):
        size, kind = struct.unpack_from("<HB", data, position)
        if position + 3 + size > len(data):
            break
        logged |= kind == ord("D")
        position += 3 + size
    if not logged:
        inside = " (inside its 16-byte file header)" if len(data) < 16 else ""
        raise LogError(f"{path}: the ULog ends at byte {len(data)} before any logged data{inside}: no flight "
                       "to read (cut off?)")
    return position


def _dataset(log, name: str):
    found = [d for d in log.data_list if d.name == name]
    return min(found, key=lambda d: d.multi_id) if found else None


def _times(data: dict, key: str = "timestamp_sample") -> np.ndarray:
    return (data[key] if key in data else data["timestamp"]).astype(np.int64)


def read_ulog(path: str | Path) -> FlightLog:
    """The flight in a PX4 ULog (`flight_logs.read_flight_log` reads a Betaflight log as well)."""
    path = Path(path)
    log = _read(path)
    gyro_set = _dataset(log, GYRO)
    motors_set = _dataset(log, "actuator_motors")
    outputs_set = _dataset(log, "actuator_outputs")
    if gyro_set is None:
        raise LogError(f"{path}: no {GYRO} topic (the gyro); log it at the loop rate "
                       "(SDLOG_PROFILE: high rate)")
    if motors_set is None and outputs_set is None:
        raise LogError(f"{path}: no actuator_motors or actuator_outputs topic (the motor commands)")
    g = gyro_set.data
    t_us = _times(g)
    gyro = np.stack([g[f"xyz[{i}]"] for i in range(3)], axis=1).astype(np.float64)
    if motors_set is not None:
        m = motors_set.data
        raw = np.stack([m[f"control[{i}]"] for i in range(4)], axis=1).astype(np.float64)
        source, cmd_t = "actuator_motors", _times(m)
    else:
        m = outputs_set.data
        raw = (np.stack([m[f"output[{i}]"] for i in range(4)], axis=1) - PWM_MIN) / PWM_SPAN
        source, cmd_t = "actuator_outputs (1000-2000 µs)", _times(m, "timestamp")
    if len(t_us) < 2 or len(cmd_t) < 2:
        raise LogError(f"{path}: {GYRO} and {source} need more than one sample each")
    held = np.clip(np.searchsorted(cmd_t, t_us, side="right") - 1, 0, len(cmd_t) - 1)
    command = np.nan_to_num(raw[held], nan=0.0)
    keep = (t_us >= cmd_t[0]) & (command.max(axis=1) > IDLE)
    armed_set = _dataset(log, "actuator_armed")
    if armed_set is not None:
        a = armed_set.data
        at = _times(a, "timestamp")
        was = a["armed"][np.clip(np.searchsorted(at, t_us, side="right") - 1, 0, len(at) - 1)]
        if not np.any(a["armed"]):
            raise LogError(f"{path}: the vehicle was never armed (actuator_armed): a ground-only log")
        keep &= was.astype(bool)
    rotor, esc_hz = _rotor_speed(log, t_us)
    gyro_hz = 1e6 / float(np.median(np.diff(t_us)))
    notes = log.fcemu_notes
    if rotor is not None and esc_hz < MIN_ESC_SHARE * gyro_hz:
        rotor = None
        notes += (f"esc_status at {esc_hz:.0f} Hz against the gyro's {gyro_hz:.0f} Hz is too slow for the "
                  "motor lag: its rpm is left out (log esc_status at the loop rate: docs/identify.md)",)
    throttle = setpoint = None
    setpoint_set = _dataset(log, "vehicle_rates_setpoint")
    if setpoint_set is not None:
        s = setpoint_set.data
        at = np.clip(np.searchsorted(_times(s, "timestamp"), t_us, side="right") - 1, 0, None)
        if "thrust_body[2]" in s:
            throttle = -s["thrust_body[2]"][at]
        if all(axis in s for axis in ("roll", "pitch", "yaw")):
            setpoint = np.stack([s[axis][at] for axis in ("roll", "pitch", "yaw")], axis=1).astype(np.float64)
    return flown_stretch(path, t_us, gyro, command, keep, rotor, throttle, source, notes, setpoint=setpoint)


def flown_stretch(path: Path, t_us: np.ndarray, gyro: np.ndarray, command: np.ndarray, keep: np.ndarray,
                  rotor: np.ndarray | None, throttle: np.ndarray | None, source: str,
                  notes: tuple[str, ...], **per_sample_and_more) -> FlightLog:
    """The log's samples from the first to the last `keep` (armed, motors above idle), or a
    LogError where that is no flight: too short, never turning, an axis never excited. Keyword
    arguments are further FlightLog fields; `setpoint` and `battery_v` are cut to the same stretch."""
    dt = float(np.median(np.diff(t_us))) * 1e-6
    if keep.sum() * dt < MIN_FLIGHT_S:
        raise LogError(f"{path}: {keep.sum() * dt:.2f} s with the motors armed and above idle, at least "
                       f"{MIN_FLIGHT_S:g} s needed: a ground-only log")
    first, last = np.flatnonzero(keep)[[0, -1]]
    window = slice(first, last + 1)
    peak = np.abs(gyro[window]).max(axis=0)
    if peak.max() < MIN_RATE:
        raise LogError(f"{path}: the body rates never reach {MIN_RATE} rad/s (peak "
                       f"{', '.join(f'{p:.2f}' for p in peak)}): a ground-only or unexcited log")
    quiet = [axis for axis, p in zip(("roll", "pitch", "yaw"), peak, strict=True) if p < MIN_RATE]
    if quiet:
        raise LogError(f"{path}: {' and '.join(quiet)} never turned faster than {MIN_RATE} rad/s: fly a "
                       "doublet or chirp on every axis (docs/identify.md)")
    more = dict(per_sample_and_more)
    for key in ("setpoint", "battery_v"):
        if more.get(key) is not None:
            more[key] = np.asarray(more[key], dtype=np.float64)[window]
    return FlightLog(path, (t_us[window] - t_us[first]) * 1e-6, gyro[window], command[window],
                     None if rotor is None else rotor[window],
                     None if throttle is None else np.asarray(throttle[window], dtype=np.float64), source,
                     notes, **more)


def _rotor_speed(log, t_us: np.ndarray) -> tuple[np.ndarray | None, float]:
    """(T, 4) rad/s from esc_status (None where it is not logged or reports no rpm) and its rate, Hz."""
    esc = _dataset(log, "esc_status")
    if esc is None or "esc[3].esc_rpm" not in esc.data or len(esc.data["timestamp"]) < 2:
        return None, 0.0
    speeds = []
    for i in range(4):
        key = f"esc[{i}].timestamp"
        stamped = key in esc.data and esc.data[key].any()
        et = (esc.data[key] if stamped else esc.data["timestamp"]).astype(np.int64)
        rpm = esc.data[f"esc[{i}].esc_rpm"].astype(np.float64)
        order = np.argsort(et, kind="stable")
        speeds.append(np.interp(t_us, et[order], rpm[order]) * (2 * math.pi / 60))
    out = np.stack(speeds, axis=1)
    rate = 1e6 / max(float(np.median(np.diff(esc.data["timestamp"].astype(np.int64)))), 1.0)
    return (out if np.abs(out).max() > 0 else None), rate


def joined(logs: list[FlightLog]) -> FlightLog:
    """The flights one after another as one log (the fits see a seam as one odd sample among
    thousands); refused where they were logged at different rates."""
    if len(logs) == 1:
        return logs[0]
    rates = [1 / log.dt for log in logs]
    if max(rates) > 1.02 * min(rates):
        raise LogError(f"the logs are at different rates ({', '.join(f'{r:.0f}' for r in rates)} Hz): "
                       "identify "
                       "them apart, or from logs of one rate")
    first = logs[0]

    def stack(field: str) -> np.ndarray | None:
        values = [getattr(log, field) for log in logs]
        return None if any(v is None for v in values) else np.concatenate(values)

    t = np.arange(sum(len(log.t) for log in logs)) * first.dt
    notes = tuple(dict.fromkeys(n for log in logs for n in log.notes if not n.startswith("log ")))
    names = ", ".join(log.name for log in logs)
    return FlightLog(first.path, t, stack("gyro"), stack("command"), stack("rotor_speed"), stack("throttle"),
                     first.command_source, (f"{len(logs)} flights joined: {names}", *notes),
                     setpoint=stack("setpoint"), battery_v=stack("battery_v"),
                     gyro_filter_lag_s=first.gyro_filter_lag_s, gyro_filter_note=first.gyro_filter_note,
                     props_reversed=first.props_reversed, header=first.header,
                     title=f"{len(logs)} flights")
