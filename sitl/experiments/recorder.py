"""Ground truth recorded during a run, and the trajectory.csv written from it."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from sitl.experiments.step_watch import StepWatch
from sitl.world.world import FloatArray

TRAJECTORY_COLUMNS = (
    "t", "agent", "body", "behavior", "x", "y", "heading", "vx", "vy",
    "wind_x", "wind_y", "current_x", "current_y", "est_x", "est_y", "est_heading",
)  # fmt: skip


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
    wind: FloatArray | None = None
    current: FloatArray | None = None
    estimate: FloatArray | None = None  # (k, 3): believed x, y (m) and heading (rad)


@dataclass
class Recorder:
    """Keeps frames at a fixed period of simulated time, and what `watch` needs of every step (the "ever" and
    "never" criteria: sitl.experiments.step_watch)."""

    period_s: float
    body_names: list[str]
    frames: list[Frame] = field(default_factory=list)
    _next_s: float = 0.0
    watch: StepWatch = field(default_factory=StepWatch)

    def due(self, t: float) -> bool:
        return t + 1e-9 >= self._next_s

    def observe_step(self, t: float, active: NDArray[np.bool_], positions: FloatArray) -> None:
        """Every step: which agents are active (N,) and all true positions (N, 2) m, for the watch (nothing is
        read when it watches nothing)."""
        if self.watch.watching:
            agents = active.nonzero()[0]
            self.watch.observe(t, agents, positions[agents])

    def record(self, frame: Frame) -> None:
        self.frames.append(frame)
        self._next_s += self.period_s

    def write_csv(self, path: Path) -> None:
        """trajectory.csv: one row per agent per frame; metres, radians from east CCW, m/s.

        Truth (x, y, heading, vx, vy), the wind and current at the agent (m/s),
        and what the agent believed of its pose (est_x, est_y, est_heading).
        """
        with open(path, "w", encoding="utf-8", newline="\n") as out:
            out.write(",".join(TRAJECTORY_COLUMNS) + "\n")
            for f in self.frames:
                k = f.agents.size
                wind = f.wind if f.wind is not None else np.zeros((k, 2))
                current = f.current if f.current is not None else np.zeros((k, 2))
                estimate = f.estimate if f.estimate is not None else np.full((k, 3), np.nan)
                rows = [
                    f"{f.t:.3f},{a},{self.body_names[a]},{f.behavior[a]},{x:.4f},{y:.4f},{h:.5f},{vx:.4f},{vy:.4f},"
                    f"{wx:.3f},{wy:.3f},{cx:.3f},{cy:.3f},{ex:.4f},{ey:.4f},{eh:.5f}\n"
                    for a, (x, y), h, (vx, vy), (wx, wy), (cx, cy), (ex, ey, eh) in zip(
                        f.agents.tolist(),
                        f.position.tolist(),
                        f.heading.tolist(),
                        f.velocity.tolist(),
                        wind.tolist(),
                        current.tolist(),
                        estimate.tolist(),
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
