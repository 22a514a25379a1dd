"""Telemetry logs (.tlog) as MAVProxy writes them, for pymavlink's log tools (mavlogdump.py, mavlink_connection).

Each MAVLink frame is preceded by the time it passed, as a big-endian uint64 of
microseconds since the Unix epoch. Frames are written whole, one by one, in the
order they passed in either direction.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

_STAMP = struct.Struct(">Q")


class TlogWriter:
    """Appends frames to a .tlog file; `wall_clock` (s since the epoch) stamps them. Thread-safe."""

    def __init__(self, path: str | Path, wall_clock: Callable[[], float] = time.time) -> None:
        self.path = Path(path)
        self.wall_clock = wall_clock
        self._file: BinaryIO = open(self.path, "ab")  # noqa: SIM115 - held open for the life of the writer
        self._lock = threading.Lock()
        self.frames = 0

    def write_frame(self, frame: bytes) -> None:
        """Log one complete MAVLink frame."""
        with self._lock:
            self._file.write(_STAMP.pack(int(self.wall_clock() * 1e6)) + bytes(frame))
            self.frames += 1

    def write_message(self, message) -> None:
        """Log a decoded pymavlink message (its original bytes)."""
        self.write_frame(message.get_msgbuf())

    def flush(self) -> None:
        with self._lock:
            self._file.flush()

    def close(self) -> None:
        with self._lock:
            self._file.close()
