"""A .tlog: every MAVLink frame in and out, each prefixed by its wall time in µs (big-endian
uint64), the format MAVProxy writes and MAVExplorer / mavlogdump.py read."""

from __future__ import annotations

import struct
import time
from pathlib import Path

_STAMP = struct.Struct(">Q")


class TlogWriter:
    def __init__(self, path: str | Path | int) -> None:
        """`path`: a file to create, or the descriptor of one opened for writing."""
        if not isinstance(path, int):
            Path(path).parent.mkdir(parents=True, exist_ok=True)
        self._f = open(path, "wb", buffering=1 << 16)
        self.frames = 0

    def write(self, frame: bytes) -> None:
        self._f.write(_STAMP.pack(int(time.time() * 1e6)) + frame)
        self.frames += 1

    def flush(self) -> None:
        self._f.flush()

    def close(self) -> None:
        self._f.close()
