"""Ground truth recorded during a run, and the trajectory.csv written from it."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from sitl.world import FloatArray

TRAJECTORY_COLUMNS = ("t", "agent", "body", "behavior", "x", "y", "heading", "vx", "vy")


@dataclass
class Frame:
    """One logged instant: time (s) and the state of the active agents."""

    t: float
    agents: NDArray[np.intp]
    position: FloatArray
    heading: FloatArray
    velocity: FloatArray
    behavior: list[str]
    light_seen: bool = False


@dataclass
class Recorder:
    """Keeps frames at a fixed period of simulated time."""

    period_s: float
    body_names: list[str]
    frames: list[Frame] = field(default_factory=list)
    _next_s: float = 0.0

    def due(self, t: float) -> bool:
        return t + 1e-9 >= self._next_s

    def record(self, frame: Frame) -> None:
        self.frames.append(frame)
        self._next_s += self.period_s

    def write_csv(self, path: Path) -> None:
        """trajectory.csv: one row per agent per frame; metres, radians from east CCW, m/s."""
        with open(path, "w", encoding="utf-8", newline="\n") as out:
            out.write(",".join(TRAJECTORY_COLUMNS) + "\n")
            for f in self.frames:
                rows = [
                    f"{f.t:.3f},{a},{self.body_names[a]},{b},{x:.4f},{y:.4f},{h:.5f},{vx:.4f},{vy:.4f}\n"
                    for a, b, (x, y), h, (vx, vy) in zip(
                        f.agents.tolist(),
                        [f.behavior[a] for a in f.agents.tolist()],
                        f.position.tolist(),
                        f.heading.tolist(),
                        f.velocity.tolist(),
                        strict=True,
                    )
                ]
                out.writelines(rows)

    def times(self) -> FloatArray:
        return np.array([f.t for f in self.frames])

    def agent_series(self, agent: int, attribute: str) -> tuple[FloatArray, FloatArray]:
        """(times s, values) of one agent's `position`, `heading` or `velocity` over the frames it was active."""
        times, values = [], []
        for f in self.frames:
            row = np.searchsorted(f.agents, agent)
            if row < f.agents.size and f.agents[row] == agent:
                times.append(f.t)
                values.append(getattr(f, attribute)[row])
        return np.array(times), np.array(values)
