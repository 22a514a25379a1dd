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
_V1, _V2 = 0xFE, 0xFD


def split_frames(data: bytes) -> list[bytes]:
    """The MAVLink 1 and 2 frames in `data`, by their start markers and length bytes (bytes outside a complete
    frame are skipped; checksums are not verified: that is the reader's job)."""
    frames: list[bytes] = []
    pos, n = 0, len(data)
    while pos < n:
        magic = data[pos]
        if magic not in (_V1, _V2) or pos + 3 > n:
            pos += 1
            continue
        length = data[pos + 1] + (8 if magic == _V1 else 12)
        if magic == _V2 and data[pos + 2] & 0x01:
            length += 13  # signature
        if pos + length > n:
            break
        frames.append(bytes(data[pos : pos + length]))
        pos += length
    return frames


class TlogWriter:
    """Appends frames to a .tlog file; `wall_clock` (s since the epoch) stamps them. Thread-safe."""

    def __init__(self, path: str | Path, wall_clock: Callable[[], float] = time.time) -> None:
        self.path = Path(path)
        self.wall_clock = wall_clock
        self._file: BinaryIO = open(self.path, "ab")  # noqa: SIM115 - held open for the life of the writer
        self._lock = threading.Lock()
        self.frames = 0

    def write_frame(self, frame: bytes, unix_time_s: float | None = None) -> None:
        """Log one complete MAVLink frame (at `unix_time_s`, default now)."""
        stamp = _STAMP.pack(round((self.wall_clock() if unix_time_s is None else unix_time_s) * 1e6))
        with self._lock:
            self._file.write(stamp + bytes(frame))
            self.frames += 1

    def write(self, data: bytes, unix_time_s: float | None = None) -> None:
        """Log every frame in `data` (a datagram or a stream chunk of whole frames), all with one time stamp."""
        for frame in split_frames(data):
            self.write_frame(frame, unix_time_s)

    def write_message(self, message) -> None:
        """Log a decoded pymavlink message (its original bytes)."""
        self.write_frame(message.get_msgbuf())

    def flush(self) -> None:
        with self._lock:
            self._file.flush()

    def close(self) -> None:
        with self._lock:
            if not self._file.closed:
                self._file.close()
