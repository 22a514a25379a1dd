"""Figures of a run (matplotlib, written as PNG without a display)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from sitl.experiments.recorder import Recorder
from sitl.fleets.fleet import LockstepFleet


def _draw_world(ax, fleet: LockstepFleet) -> None:
    for a, b in fleet.world.walls:
        ax.plot([a[0], b[0]], [a[1], b[1]], color="black", lw=1.5)
    for light in fleet.world.light_positions:
        ax.plot(*light, marker="*", color="gold", markeredgecolor="black", markersize=16, zorder=5)


def trajectories(fleet: LockstepFleet, rec: Recorder, path: Path) -> None:
    """Every agent's path, start (circle) and end (square)."""
    fig, ax = plt.subplots(figsize=(8, 6))
    _draw_world(ax, fleet)
    ids = sorted({int(a) for f in rec.frames for a in f.agents})
    cmap = plt.get_cmap("tab20")
    for k, agent in enumerate(ids):
        _, pts = rec.agent_series(agent, "position")
        color = cmap(k % 20)
        ax.plot(pts[:, 0], pts[:, 1], color=color, lw=0.8, alpha=0.8)
        ax.plot(*pts[0], "o", color=color, ms=4)
        removed = agent not in rec.frames[-1].agents
        ax.plot(*pts[-1], "x" if removed else "s", color=color, ms=7 if removed else 5, markeredgecolor="black")
    ax.set_aspect("equal")
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    ax.set_title(f"{fleet.scenario.name}: trajectories ({fleet.n} agents, {rec.frames[-1].t:.0f} s; x = removed)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def headings(fleet: LockstepFleet, rec: Recorder, metrics: dict, path: Path) -> None:
    """Heading of each agent against time, with a zoom on the first consensus."""
    times = rec.times()
    fig, (ax, zoom) = plt.subplots(1, 2, figsize=(12, 4.5), gridspec_kw={"width_ratios": [2, 1]})
    for agent in range(fleet.n):
        t, h = rec.agent_series(agent, "heading")
        style = {"lw": 2.5, "color": "red"} if agent == metrics.get("leader") else {"lw": 0.9}
        for axis in (ax, zoom):
            axis.plot(t, np.degrees(h), **style)
    if "leader_event_t_s" in metrics:
        ax.axvline(metrics["leader_event_t_s"], color="gray", ls="--", label="leader holds its heading")
        ax.legend(loc="best")
    zoom.set_xlim(0, min(11.0, times[-1]))
    ax.set_title("Heading consensus (leader in red)")
    zoom.set_title("t = 0 to 11 s")
    for axis in (ax, zoom):
        axis.set_xlabel("t (s)")
        axis.set_ylabel("heading (deg from east)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def series(
    metrics: dict, keys: list[tuple[str, str]], title: str, path: Path, marks: dict[str, float], log: bool = False
) -> None:
    """Time series stored in metrics (key, y label), with vertical marks at named times."""
    fig, axes = plt.subplots(len(keys), 1, figsize=(8, 3 * len(keys)), sharex=True, squeeze=False)
    for axis, (key, label) in zip(axes[:, 0], keys, strict=True):
        data = metrics[key]
        axis.plot(data["t_s"], data["value"], lw=1.5)
        axis.set_ylabel(label)
        if log:
            axis.set_yscale("log")
        for name, t in marks.items():
            if t is not None:
                axis.axvline(t, color="gray", ls="--")
                axis.annotate(name, (t, axis.get_ylim()[1]), fontsize=8, va="top", rotation=90)
    axes[-1, 0].set_xlabel("t (s)")
    axes[0, 0].set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_figures(fleet: LockstepFleet, rec: Recorder, metrics: dict, out: Path) -> list[str]:
    """All figures for the scenario's metrics kind; returns the file names."""
    names = ["trajectories.png"]
    trajectories(fleet, rec, out / names[0])
    kind = fleet.scenario.metrics.kind
    if kind == "heading-consensus":
        names.append("headings.png")
        headings(fleet, rec, metrics, out / names[-1])
    elif kind == "perimeter-defense":
        names.append("coverage.png")
        keys = [
            ("coverage", f"covered fraction (<= {metrics['cover_radius_m']} m)"),
            ("largest_gap_m", "largest gap (m)"),
        ]
        series(
            metrics,
            keys,
            "Perimeter defence: coverage of the room",
            out / names[-1],
            {"removal": metrics.get("removal_t_s")},
        )
    elif kind == "aggregation":
        names.append("hull_area.png")
        switches = sorted({e["t_s"] for e in fleet.events_log if e["action"] == "set-behavior"})
        marks = {f"switch {k + 1}": t for k, t in enumerate(switches)}
        series(metrics, [("hull_area_m2", "convex hull area (m^2)")], "Aggregation", out / names[-1], marks, log=True)
    elif kind == "exploration":
        names.append("rooms.png")
        series(
            metrics,
            [("rooms_visited", "rooms visited")],
            "Exploration of the rooms",
            out / names[-1],
            {"all visited": metrics["all_rooms_visited_s"]},
        )
    elif kind == "leader-follower":
        names.append("spread.png")
        series(
            metrics,
            [("farthest_from_leader_m", "farthest buoy from the leader (m)")],
            "Leader-follower",
            out / names[-1],
            {},
        )
    elif kind == "search-exploration":
        names.append("search.png")
        marks = {"first detection": metrics["first_detection_s"], "all arrived": metrics["all_arrived_s"]}
        series(
            metrics,
            [("farthest_from_source_m", "farthest robot from source (m)")],
            "Search and rendezvous",
            out / names[-1],
            marks,
        )
    return names
