"""An animation of a run: what a person watching the experiment would see, in simulated time.

Drawn from the run's recording (ground truth at every logged frame): each active agent as an arrow
along its heading, coloured by its behaviour; the radio links (pairs within the network's range,
`network.range_m`: who can hear whom; the lossy channel's individual drops are not drawn); walls
and lights (a light turns red once seen); the goal of an avoidance experiment and the leader of a
leader-follower or heading-consensus one; the convex hull and its area for aggregation; the
covered band around each robot for perimeter defence; the simulated time on screen.

Written with matplotlib's animation writers: MP4 through ffmpeg when it is installed, else an
animated GIF through Pillow (a dependency of matplotlib). At most `max_frames` frames (the
recording is thinned evenly), `fps` frames per second of video.
"""

from __future__ import annotations

import contextlib
import math
import os
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib import animation
from matplotlib.collections import LineCollection, PatchCollection
from matplotlib.patches import Circle, Polygon
from scipy.spatial import ConvexHull, QhullError, cKDTree

from sitl.experiments.recorder import Recorder
from sitl.fleets.fleet import LockstepFleet

MAX_FRAMES = 300
FPS = 10
MAX_LINKS = 5000  # more pairs in range than this are not drawn (a dense swarm would be one grey blot)


def animation_format() -> str:
    """'mp4' when matplotlib finds ffmpeg, else 'gif'."""
    return "mp4" if animation.writers.is_available("ffmpeg") else "gif"


def _extent(fleet: LockstepFleet, rec: Recorder) -> tuple[float, float, float, float]:
    """x0, x1, y0, y1 (m) around every recorded position, wall and light, with a margin."""
    points = [f.position for f in rec.frames if f.position.size]
    if fleet.world.walls.size:
        points.append(fleet.world.walls.reshape(-1, 2))
    if fleet.world.light_positions.size:
        points.append(fleet.world.light_positions)
    goal = _goal(fleet)
    if goal is not None:
        points.append(goal[None, :])
    xy = np.concatenate(points) if points else np.zeros((1, 2))
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    margin = 0.06 * max(float(np.max(hi - lo)), 1.0)
    return lo[0] - margin, hi[0] + margin, lo[1] - margin, hi[1] + margin


def _goal(fleet: LockstepFleet) -> np.ndarray | None:
    params = fleet.scenario.metrics.params
    if "goal_x_m" in params and "goal_y_m" in params:
        return np.array([float(params["goal_x_m"]), float(params["goal_y_m"])])
    return None


def _leader(fleet: LockstepFleet) -> int | None:
    params, kind = fleet.scenario.metrics.params, fleet.scenario.metrics.kind
    if kind == "leader-follower":
        return int(params.get("leader", 0))
    if kind == "avoidance":
        return int(params.get("mover", 0))
    if kind == "heading-consensus":
        leaders = [e.agents[0] for e in fleet.scenario.events if e.action == "set-behavior" and e.agents]
        return int(leaders[0]) if leaders else None
    return None


def write_animation(fleet: LockstepFleet, rec: Recorder, out_dir: Path, max_frames: int = MAX_FRAMES,
                    fps: int = FPS) -> Path:  # fmt: skip
    """Write `animation.mp4` (ffmpeg) or `animation.gif` into `out_dir`; return its path.

    Written to a hidden file first and renamed into place, so that the file is whole or absent.
    """
    if not rec.frames:
        raise ValueError("the run recorded no frame: nothing to animate")
    step = max(1, math.ceil(len(rec.frames) / max_frames))
    frames = rec.frames[::step]
    if frames[-1] is not rec.frames[-1]:
        frames.append(rec.frames[-1])
    kind = animation_format()
    path = Path(out_dir) / f"animation.{kind}"
    staging = path.with_name(f".animation.partial.{kind}")
    scene = _Scene(fleet, rec)
    movie = animation.FuncAnimation(scene.fig, scene.draw, frames=frames, blit=False, cache_frame_data=False)
    writer = animation.FFMpegWriter(fps=fps) if kind == "mp4" else animation.PillowWriter(fps=fps)
    try:
        movie.save(str(staging), writer=writer, dpi=scene.dpi)
        os.replace(staging, path)
    finally:
        plt.close(scene.fig)
        with contextlib.suppress(FileNotFoundError):
            staging.unlink()
    return path


class _Scene:
    """The figure and its artists, updated frame by frame."""

    dpi = 80

    def __init__(self, fleet: LockstepFleet, rec: Recorder) -> None:
        self.fleet, self.rec = fleet, rec
        scenario = fleet.scenario
        self.kind = scenario.metrics.kind
        self.range_m = scenario.network.range_m
        self.cover_m = float(scenario.metrics.params.get("cover_radius_m", 2.5))
        self.leader = _leader(fleet)
        x0, x1, y0, y1 = _extent(fleet, rec)
        self.size = max(x1 - x0, y1 - y0)
        width = 7.0
        height = min(7.0, max(3.0, width * (y1 - y0) / max(x1 - x0, 1e-9) + 0.8))
        self.fig, self.ax = plt.subplots(figsize=(width, height))
        ax = self.ax
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel("x east (m)")
        ax.set_ylabel("y north (m)")
        walls = fleet.world.walls
        if walls.size:
            ax.add_collection(LineCollection(walls, colors="black", linewidths=1.5, zorder=2))
        self.lights = None
        if fleet.world.light_positions.size:
            lp = fleet.world.light_positions
            self.lights = ax.scatter(lp[:, 0], lp[:, 1], marker="*", s=220, c="gold", edgecolors="black", zorder=6)
        goal = _goal(fleet)
        if goal is not None:
            ax.plot(*goal, marker="X", color="green", markersize=12, zorder=6, label="goal")
        self.links = LineCollection([], colors="0.6", linewidths=0.4, alpha=0.5, zorder=1)
        ax.add_collection(self.links)
        self.cover: Any = None
        self.hull = Polygon(np.zeros((3, 2)), closed=True, fill=True, facecolor="tab:blue", alpha=0.12,
                            edgecolor="tab:blue", zorder=1)  # fmt: skip
        self.hull.set_visible(False)
        ax.add_patch(self.hull)
        self.arrows: Any = None
        self.leader_mark = ax.scatter([], [], s=120, facecolors="none", edgecolors="red", linewidths=1.5, zorder=5)
        self.clock = ax.text(0.01, 0.99, "", transform=ax.transAxes, va="top", ha="left", fontsize=10,
                             bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none"}, zorder=7)  # fmt: skip
        names = sorted({b for f in rec.frames for b in f.behavior})
        cmap = plt.get_cmap("tab10")
        self.colours = {name: cmap(k % 10) for k, name in enumerate(names)}
        for name, colour in self.colours.items():
            ax.plot([], [], marker=">", linestyle="none", color=colour, label=name)
        ax.legend(loc="lower right", fontsize="x-small", framealpha=0.8)
        ax.set_title(f"{scenario.name}: {fleet.n} agents", fontsize="medium")
        self.fig.tight_layout()

    def draw(self, frame: Any) -> list:
        ax, position = self.ax, frame.position
        tree = cKDTree(position) if len(position) else None
        pairs = np.array(sorted(tree.query_pairs(self.range_m)), dtype=int).reshape(-1, 2) if tree else np.zeros((0, 2))
        if len(pairs) <= MAX_LINKS:
            self.links.set_segments(position[pairs] if len(pairs) else [])
        else:
            self.links.set_segments([])
        arrow = 0.04 * self.size
        colours = [self.colours[frame.behavior[a]] for a in frame.agents.tolist()]
        u, v = arrow * np.cos(frame.heading), arrow * np.sin(frame.heading)
        if self.arrows is not None:
            self.arrows.remove()
        self.arrows = ax.quiver(position[:, 0], position[:, 1], u, v, color=colours, angles="xy", scale_units="xy",
                                scale=1.0, width=0.006, zorder=4)  # fmt: skip
        text = f"t = {frame.t:7.1f} s"
        if self.kind == "aggregation" and len(position) >= 3:
            try:
                hull = ConvexHull(position)
                self.hull.set_xy(position[hull.vertices])
                self.hull.set_visible(True)
                text += f"\nhull {hull.volume:,.0f} m²"
            except QhullError:
                self.hull.set_visible(False)
        if self.kind == "perimeter-defense":
            if self.cover is not None:
                self.cover.remove()
            circles = [Circle((float(x), float(y)), self.cover_m) for x, y in position]
            self.cover = ax.add_collection(
                PatchCollection(circles, facecolor="tab:green", alpha=0.12, edgecolor="none", zorder=1)
            )
        if self.leader is not None:
            row = np.flatnonzero(frame.agents == self.leader)
            self.leader_mark.set_offsets(position[row] if row.size else np.zeros((0, 2)))
        if self.lights is not None:
            self.lights.set_facecolor("red" if frame.light_seen else "gold")
        text += f"\n{len(pairs)} pairs in radio range"
        self.clock.set_text(text)
        return [self.links, self.arrows, self.clock]
