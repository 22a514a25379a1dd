"""A serial cable between two programs that each open a serial port by its path: two pseudo-terminals joined by
a relay, as a null-modem cable (or a companion computer's USB-serial adapter wired to an autopilot's TELEM port)
joins two UARTs.

The relay counts the bytes each way with their times (the link's load), can spoil bytes on the wire (dropped or
with one bit flipped, each with its own probability per byte, from a seeded generator: a marginal cable or
radio), and can unplug and plug in again the companion's end (its path gone, then a new device behind it). When
the two ends set different baud rates, every byte arrives as noise, as a UART reading at the wrong rate sees it.
"""

from __future__ import annotations

import errno
import fcntl
import os
import select
import struct
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class WireCounts:
    """What one direction of the cable carried: chunks as (wall time s, bytes), and the bytes it spoiled."""

    chunks: list[tuple[float, int]] = field(default_factory=list)
    dropped: int = 0
    flipped: int = 0
    lost: int = 0  # bytes the far end could not take (unplugged, or nobody reading it and its buffer full)
    misread: int = 0  # bytes read as noise at the far end, set to another baud rate

    def bytes_per_s(self, start_s: float, end_s: float) -> float:
        """Mean load between two wall times (time.monotonic()), bytes per second."""
        carried = sum(n for t, n in self.chunks if start_s <= t < end_s)
        return carried / max(end_s - start_s, 1e-9)


TCGETS2 = 0x802C542A  # Linux ioctl: struct termios2, whose c_ispeed and c_ospeed are the rates in baud
_TERMIOS2 = struct.Struct("<4IB19sII")


def baud_of(fd: int) -> int:
    """The output baud rate a terminal is set to (any rate: ArduPilot sets its UART's with BOTHER)."""
    raw = fcntl.ioctl(fd, TCGETS2, bytes(_TERMIOS2.size))
    return _TERMIOS2.unpack(raw)[-1]


class _PtyEnd:
    """One pseudo-terminal: its master (the cable's side) and its slave, held open so that the master never reads
    EIO while the program at the path is between opens; the path is a symlink to the slave."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        tty.setraw(self.master)
        os.set_blocking(self.master, False)
        os.symlink(os.ttyname(self.slave), path)

    def close(self) -> None:
        os.unlink(self.path)
        os.close(self.master)
        os.close(self.slave)


class SerialCable:
    """Two serial ports joined: open `autopilot_path` on one side and `companion_path` on the other. Use as a
    context manager. drop, flip: probability per byte of losing it or flipping one of its bits, in each direction;
    seed: the noise's generator."""

    def __init__(self, directory: Path, *, drop: float = 0.0, flip: float = 0.0, seed: int = 1) -> None:
        self.autopilot_path = directory / "autopilot-telem2"
        self.companion_path = directory / "companion-usb-serial"
        self.drop, self.flip = drop, flip
        self._rng = np.random.default_rng(seed)
        self._ends = {"autopilot": _PtyEnd(self.autopilot_path), "companion": _PtyEnd(self.companion_path)}
        self.to_companion, self.to_autopilot = WireCounts(), WireCounts()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._relay, daemon=True)

    def __enter__(self) -> SerialCable:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        with self._lock:
            for end in self._ends.values():
                if end is not None:
                    end.close()

    def unplug_companion(self) -> None:
        """The companion's adapter pulled out: its device and path are gone under whoever had it open."""
        with self._lock:
            self._ends["companion"].close()
            self._ends["companion"] = None

    def replug_companion(self) -> None:
        """The adapter plugged in again: a new device behind the same path."""
        with self._lock:
            self._ends["companion"] = _PtyEnd(self.companion_path)

    def _spoil(self, data: bytes, counts: WireCounts) -> bytes:
        if not (self.drop or self.flip):
            return data
        n = len(data)
        raw = np.frombuffer(data, dtype=np.uint8).copy()
        flips = self._rng.random(n) < self.flip
        raw[flips] ^= (1 << self._rng.integers(0, 8, int(flips.sum()))).astype(np.uint8)
        kept = self._rng.random(n) >= self.drop
        counts.flipped += int(flips.sum())
        counts.dropped += int(n - kept.sum())
        return raw[kept].tobytes()

    def _relay(self) -> None:
        routes = (("autopilot", "companion", self.to_companion), ("companion", "autopilot", self.to_autopilot))
        while not self._stop.is_set():
            with self._lock:
                masters = {name: end.master for name, end in self._ends.items() if end is not None}
            ready, _, _ = select.select(list(masters.values()), [], [], 0.05)
            for source, sink, counts in routes:
                fd = masters.get(source)
                if fd not in ready:
                    continue
                with self._lock:
                    if self._ends[source] is None or self._ends[source].master != fd:
                        continue  # unplugged meanwhile
                    try:
                        data = os.read(fd, 4096)
                    except OSError as e:
                        if e.errno in (errno.EIO, errno.EAGAIN):
                            continue
                        raise
                    counts.chunks.append((time.monotonic(), len(data)))
                    data = self._spoil(data, counts)
                    far = self._ends[sink]
                    if far is None:
                        counts.lost += len(data)
                        continue
                    if baud_of(self._ends[source].slave) != baud_of(far.slave):
                        data = self._rng.integers(0, 256, len(data), dtype=np.uint8).tobytes()  # framing errors
                        counts.misread += len(data)
                    try:
                        os.write(far.master, data)
                    except BlockingIOError:
                        counts.lost += len(data)
