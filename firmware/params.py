"""The vehicle's parameter table: typed, ranged, validated, persisted atomically.

Names follow PX4 where PX4 has the same thing (COM_OF_LOSS_T, MPC_THR_HOVER, IMU_GYRO_CUTOFF),
so QGC users find them where they expect. The PID gains are in the PID's own units (see
firmware/pid.py), not PX4's. The file is JSON {name: value}; a save writes a temporary file,
fsyncs it and renames it over the old one, so a crash leaves either the old or the new table.
"""

from __future__ import annotations

import json
import math
import numbers
import os
import reprlib
import struct
import tempfile
from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path

REAL32 = 9  # MAV_PARAM_TYPE_REAL32
INT32 = 6  # MAV_PARAM_TYPE_INT32
NAME_MAX = 16  # MAVLink param_id is char[16]
MAX_FILE_BYTES = 1 << 20  # a saved table is a few kB; anything this large is not one


@dataclass(frozen=True)
class ParamSpec:
    name: str
    default: float
    lo: float
    hi: float
    kind: int = REAL32
    doc: str = ""

    def __post_init__(self) -> None:
        if not 0 < len(self.name) <= NAME_MAX or not self.name.isascii():
            raise ValueError(f"param name {self.name!r} must be 1..{NAME_MAX} ASCII characters")
        if not self.lo <= self.default <= self.hi:
            raise ValueError(f"{self.name}: default {self.default} outside [{self.lo}, {self.hi}]")

    def check(self, value: float) -> str:
        """'' if `value` is acceptable, else why not."""
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            return f"{self.name}: {_shown(value)} is not a number"
        try:
            finite = math.isfinite(value)
        except OverflowError:  # an int too large for a float
            finite = False
        if not finite:
            return f"{self.name}: {_shown(value)} is not a finite number"
        if self.kind == INT32 and value != int(value):
            return f"{self.name}: {value} is not an integer"
        if not self.lo <= value <= self.hi:
            return f"{self.name}: {value:g} outside [{self.lo:g}, {self.hi:g}]"
        return ""


def _shown(value: object, limit: int = 40) -> str:
    """A bounded repr: a hostile file's value must not become a megabyte warning."""
    text = json.dumps(value) if isinstance(value, bool) else reprlib.repr(value)
    return text if len(text) <= limit else f"{text[:limit - 1]}…"


def _axes(prefix: str, what: str, defaults: tuple[float, float, float], lo: float, hi: float,
          doc: str) -> list[ParamSpec]:
    return [ParamSpec(f"{prefix}_{axis}_{what}" if what else f"{prefix}_{axis}", d, lo, hi, doc=doc)
            for axis, d in zip(("ROLL", "PITCH", "YAW"), defaults, strict=True)]


def _rate_curves() -> list[ParamSpec]:
    out = []
    for axis in "RPY":
        out += [ParamSpec(f"RATE_{axis}_CENTER", 70.0, 0.0, 2000.0, doc="Actual rates: centre rate, deg/s"),
                ParamSpec(f"RATE_{axis}_MAX", 670.0, 0.0, 2000.0, doc="Actual rates: full-stick rate, deg/s"),
                ParamSpec(f"RATE_{axis}_EXPO", 0.0, 0.0, 1.0, doc="Actual rates: expo")]
    return out


def _gains() -> list[ParamSpec]:
    out = []
    for axis in ("ROLL", "PITCH", "YAW"):
        out += [ParamSpec(f"PID_{axis}_P", 2.0, 0.0, 100.0, doc="rate P (firmware/pid.py units)"),
                ParamSpec(f"PID_{axis}_I", 10.0, 0.0, 500.0, doc="rate I"),
                ParamSpec(f"PID_{axis}_D", 0.005, 0.0, 5.0, doc="rate D (on measurement)"),
                ParamSpec(f"PID_{axis}_FF", 0.0, 0.0, 10.0, doc="rate feedforward")]
    return out


CONTROLLERS = ("pid", "neural")  # CTRL_SEL values

SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("CTRL_SEL", 0, 0, len(CONTROLLERS) - 1, INT32, "rate controller: 0 PID, 1 neural policy"),
    *_gains(),
    ParamSpec("IMU_GYRO_CUTOFF", 0.0, 0.0, 1000.0, doc="PID gyro lowpass, Hz (0 off)"),
    ParamSpec("IMU_DGYRO_CUTOFF", 100.0, 0.0, 1000.0, doc="PID D-term lowpass, Hz (0 off)"),
    *_rate_curves(),
    ParamSpec("STAB_ANGLE_MAX", 35.0, 5.0, 80.0, doc="STABILIZED: full-stick tilt, deg"),
    ParamSpec("STAB_ANGLE_P", 6.0, 0.5, 20.0, doc="STABILIZED and failsafe: angle P, rad/s per rad"),
    ParamSpec("MPC_THR_HOVER", 0.745, 0.1, 0.9, doc="hover throttle 0..1 (failsafe feedforward)"),
    ParamSpec("COM_OF_LOSS_T", 0.5, 0.05, 60.0, doc="offboard setpoint loss timeout, s"),
    ParamSpec("COM_RC_LOSS_T", 0.5, 0.05, 60.0, doc="manual-control (stick) loss timeout, s"),
    ParamSpec("FS_HOLD_T", 1.0, 0.0, 30.0, doc="failsafe: hold level and vertical speed 0 for this long, s"),
    ParamSpec("FS_DESC_SPD", 0.7, 0.1, 3.0, doc="failsafe: descent speed, m/s"),
    ParamSpec("FS_DESC_MAX_T", 20.0, 1.0, 120.0, doc="failsafe: disarm after descending this long, s"),
    ParamSpec("SYS_FAILURE_EN", 0, 0, 1, INT32, "accept MAV_CMD_INJECT_FAILURE (1), as PX4; refused at 0"),
)


def int_from_bytewise(value: float) -> int:
    """PX4 sends INT32 parameters as the int's bytes in the float field."""
    return struct.unpack("<i", struct.pack("<f", value))[0]


def bytewise_from_int(value: int) -> float:
    return struct.unpack("<f", struct.pack("<i", int(value)))[0]


class ParamTable:
    """Ordered parameters with values; `set` validates, `save`/`load` persist."""

    def __init__(self, specs: Iterable[ParamSpec] = SPECS) -> None:
        self.specs = {s.name: s for s in specs}
        self.names = list(self.specs)
        self.values: dict[str, float] = {s.name: s.default for s in self.specs.values()}

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, name: str) -> float:
        return self.values[name]

    def index(self, name: str) -> int:
        return self.names.index(name)

    def set_default(self, name: str, value: float) -> None:
        """Change a default (e.g. from the loaded PID preset) and the value if still at the old one."""
        spec = self.specs[name]
        value = min(max(float(value), spec.lo), spec.hi)
        if self.values[name] == spec.default:
            self.values[name] = value
        self.specs[name] = replace(spec, default=value)

    def set(self, name: str, value: float) -> str:
        """Set a value; '' on success, else the reason it was refused (and nothing changes)."""
        spec = self.specs.get(name)
        if spec is None:
            return f"unknown parameter {name!r}"
        problem = spec.check(value)
        if not problem:
            self.values[name] = int(value) if spec.kind == INT32 else float(value)
        return problem

    def decode_wire(self, name: str, value: float, kind: int) -> float:
        """A PARAM_SET value as meant: INT32 bytewise (PX4), or a plain float some clients send."""
        spec = self.specs.get(name)
        if spec is None or spec.kind != INT32:
            return value
        try:
            as_int = int_from_bytewise(value)
        except (OverflowError, struct.error):
            return value
        return as_int if spec.lo <= as_int <= spec.hi else value

    def encode_wire(self, name: str) -> float:
        spec = self.specs[name]
        return bytewise_from_int(self.values[name]) if spec.kind == INT32 else float(self.values[name])

    def save(self, path: str | Path) -> None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
        try:
            with os.fdopen(fd, "w") as f:
                json.dump(self.values, f, indent=1, sort_keys=True)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)

    def load(self, path: str | Path) -> list[str]:
        """Apply a saved table; returns the entries refused (unknown or invalid), which are skipped."""
        path = Path(path)
        if not path.exists():
            return []
        try:
            size = path.stat().st_size
            if size > MAX_FILE_BYTES:
                return [f"{path}: too large for a parameter table ({size:,} bytes); using defaults"]
            raw = json.loads(path.read_text())
        except (OSError, ValueError, RecursionError) as exc:  # RecursionError: deeply nested JSON
            return [f"{path}: unreadable ({str(exc)[:80]}); using defaults"]
        if not isinstance(raw, dict):
            return [f"{path}: not a parameter table; using defaults"]
        return [p for name, value in raw.items() if (p := self.set(str(name)[:NAME_MAX + 1], value))]


def load_warning(path: str | Path, problems: list[str]) -> str:
    """The one line a user sees about a parameter file that was not applied in full."""
    if not problems:
        return ""
    if len(problems) == 1 and problems[0].startswith(str(path)):
        return f"params: {problems[0]}; the file is left as it is"
    shown = "; ".join(problems[:3]) + ("; …" if len(problems) > 3 else "")
    return (f"params: {path}: {len(problems)} entries skipped, defaults used for them ({shown}); "
            "the file is left as it is")
