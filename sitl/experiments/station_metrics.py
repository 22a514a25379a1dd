"""Where a boat that cannot stop in place is "on average": positions averaged over a trailing time window.

A motorboat cannot hold a spot: with nothing to do it drifts, and when the drift
is stronger than its hold threshold it points into it and turns back whenever it
overshoots, so it orbits about its spot in circles of about its turning radius
(`bob_autonomy.control.motorboat_control`). A swarm metric taken from the instantaneous
positions (e.g. the convex hull area of an aggregated swarm of 45 boats, ~1,250
m2 for buoys 5 m apart) then measures the orbits as much as the formation: 45
circles of 3 m radius on the hull's edge add about a perimeter times 3 m.

`time_averaged` replaces each agent's position in every frame by its mean
position over the frames of the trailing window (t - window_s, t] in which it
was active: the centre of its orbit, the spot it holds. `wander_m` says how far
each agent strayed from that centre (RMS over the window): the size of its
orbit or drift. Metrics state which they use (`average_window_s` in a
scenario's metrics parameters); 0 keeps the instantaneous positions.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from sitl.experiments.recorder import Recorder
from sitl.world.world import FloatArray


def _windows(rec: Recorder, window_s: float):
    """For every frame: (frame, agents, (k, m, 2) positions of those agents in the window's frames, NaN where the
    agent was not active then)."""
    times = rec.times()
    for k, frame in enumerate(rec.frames):
        first = int(np.searchsorted(times, frame.t - window_s, side="right"))
        stack = np.full((k + 1 - first, frame.agents.size, 2), np.nan)
        for j, past in enumerate(rec.frames[first : k + 1]):
            rows = np.searchsorted(past.agents, frame.agents)
            rows = np.minimum(rows, max(past.agents.size - 1, 0))
            present = past.agents.size > 0
            found = (past.agents[rows] == frame.agents) if present else np.zeros(frame.agents.size, dtype=bool)
            stack[j, found] = past.position[rows[found]]
        yield frame, stack


def time_averaged(rec: Recorder, window_s: float) -> Recorder:
    """A copy of `rec` whose positions are each agent's mean over the trailing window_s s (see the module
    docstring); window_s <= 0 returns `rec` itself."""
    if window_s <= 0:
        return rec
    frames = []
    for frame, stack in _windows(rec, window_s):
        frames.append(replace(frame, position=np.nanmean(stack, axis=0)))
    return Recorder(rec.period_s, rec.body_names, frames)


def wander_m(rec: Recorder, window_s: float) -> tuple[FloatArray, list[FloatArray]]:
    """(times (frames,), per frame (agents,) RMS distance of each agent from its trailing-window mean, m)."""
    out = []
    for _frame, stack in _windows(rec, window_s):
        centre = np.nanmean(stack, axis=0)
        out.append(np.sqrt(np.nanmean(np.sum((stack - centre) ** 2, axis=2), axis=0)))
    return rec.times(), out
