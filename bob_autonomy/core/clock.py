"""Injected time: wall time on a vessel, simulated time in lockstep runs."""

from __future__ import annotations

import time
from typing import Protocol


class Clock(Protocol):
    """A source of time in seconds."""

    def now(self) -> float:
        """Current time, s."""
        ...


class WallClock:
    """Monotonic wall-clock time, s (on a vessel)."""

    def now(self) -> float:
        return time.monotonic()


class ManualClock:
    """Time that moves only when told to (simulation and tests), s."""

    def __init__(self, start_s: float = 0.0) -> None:
        self._t = start_s

    def now(self) -> float:
        return self._t

    def advance(self, dt_s: float) -> None:
        if dt_s < 0:
            raise ValueError(f"time cannot go backwards (dt_s={dt_s})")
        self._t += dt_s

    def set(self, t_s: float) -> None:
        if t_s < self._t:
            raise ValueError(f"time cannot go backwards ({t_s} < {self._t})")
        self._t = t_s


class ScaledWallClock:
    """Wall time run `scale` times faster, s from construction (a simulation sped up; scale 1 on a vessel)."""

    def __init__(self, scale: float = 1.0, start_s: float = 0.0) -> None:
        if not scale > 0:
            raise ValueError(f"the time scale must be positive, got {scale!r}")
        self.scale, self._start_s, self._t0 = float(scale), float(start_s), time.monotonic()

    def now(self) -> float:
        return self._start_s + (time.monotonic() - self._t0) * self.scale

    def wall_seconds(self, clock_s: float) -> float:
        """How many wall seconds `clock_s` of this clock's seconds last."""
        return clock_s / self.scale
