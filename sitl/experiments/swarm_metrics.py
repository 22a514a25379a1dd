"""Metrics of the buoy experiments (DESIGN.md experiments 4 to 6): aggregation, leader-follower, avoidance."""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, QhullError, cKDTree

from sitl.experiments.recorder import Recorder
from sitl.experiments.station_metrics import time_averaged, wander_m
from sitl.fleets.fleet import LockstepFleet
from sitl.world.world import FloatArray, point_segment_offsets, points_in_polygon


def hull_area_m2(points: FloatArray) -> float:
    """Area of the convex hull of (N, 2) points, m^2 (0 when degenerate)."""
    if len(points) < 3:
        return 0.0
    try:
        return float(ConvexHull(points).volume)
    except QhullError:
        return 0.0


def nearest_neighbor_m(points: FloatArray) -> FloatArray:
    """(N,) distance from each point to its nearest other point, m."""
    if len(points) < 2:
        return np.full(len(points), np.inf)
    return cKDTree(points).query(points, k=2)[0][:, 1]


def _events(fleet: LockstepFleet, action: str) -> list[dict]:
    return [e for e in fleet.events_log if e["action"] == action]


def _series(times: FloatArray, values: FloatArray, digits: int = 3) -> dict:
    return {"t_s": times.tolist(), "value": np.round(values, digits).tolist()}


def _finish(result: dict) -> dict:
    result["passed"] = bool(all(result["criteria"].values()))
    return result


def _within_factor(value: float | None, target: float, factor: float) -> bool:
    return value is not None and target / factor <= value <= target * factor


def aggregation_metrics(fleet: LockstepFleet, rec: Recorder, p: dict[str, float]) -> dict:
    """Convex-hull area against time around the p0 switches: aggregation, then spreading.

    The first behaviour switch is the aggregation (p0 down), the second the
    spreading (p0 up). Aggregation time: from the switch until the area first
    comes within 10 % of its smallest value before the spreading.
    average_window_s > 0 (boats that cannot stop in place): the hull of each
    agent's mean position over that trailing window (sitl.experiments.station_metrics); the
    instantaneous smallest area and how far the agents wander about their mean
    in the 5 minutes before the spreading (RMS, m) are reported too.
    """
    factor = p.get("factor", 2.0)
    window = float(p.get("average_window_s", 0.0))
    instant, rec = rec, time_averaged(rec, window)
    start_target, end_target = p.get("start_area_m2", 125_000.0), p.get("end_area_m2", 1_250.0)
    time_target = p.get("aggregation_time_s", 480.0)
    times = rec.times()
    area = np.array([hull_area_m2(f.position) for f in rec.frames])
    switches = sorted({e["t_s"] for e in _events(fleet, "set-behavior")})
    t_in = switches[0] if switches else 0.0
    t_out = switches[1] if len(switches) > 1 else times[-1] + 1.0
    k_in = int(np.searchsorted(times, t_in))
    during = (times >= t_in) & (times < t_out)
    smallest = float(area[during].min()) if during.any() else None
    reached = np.flatnonzero(during & (area <= 1.1 * smallest)) if smallest else np.zeros(0, int)
    t_agg = float(times[reached[0]] - t_in) if reached.size else None
    result: dict = {
        "agents": int(fleet.n),
        "area_before_m2": float(area[min(k_in, area.size - 1)]),
        "area_aggregated_m2": smallest,
        "aggregation_time_s": t_agg,
        "area_final_m2": float(area[-1]),
        "hull_area_m2": _series(times, area, 1),
    }
    criteria = {
        f"start_area_within_x{factor:g}_of_{start_target:g}": _within_factor(
            result["area_before_m2"], start_target, factor
        ),
        f"aggregated_area_within_x{factor:g}_of_{end_target:g}": _within_factor(smallest, end_target, factor),
        f"aggregation_time_within_x{factor:g}_of_{time_target:g}_s": _within_factor(t_agg, time_target, factor),
    }
    if len(switches) > 1:
        criteria["spreads_again"] = bool(smallest and area[-1] >= 10.0 * smallest)
    if window > 0:
        raw = np.array([hull_area_m2(f.position) for f in instant.frames])
        _, wander = wander_m(instant, window)
        result["average_window_s"] = window
        result["area_aggregated_instant_m2"] = float(raw[during].min()) if during.any() else None
        settled = during & (times >= t_out - 300.0)  # the last 5 minutes before the spreading
        rms = [w.mean() for w, keep in zip(wander, settled, strict=True) if keep and w.size]
        result["wander_rms_m_settled"] = float(np.mean(rms)) if rms else None
    result["criteria"] = criteria
    return _finish(result)


def closest_approach(rec: Recorder) -> dict:
    """closest_approach_m: the least distance between two agents over the run, at every step and between steps
    (the recorder's watch: sitl.experiments.step_watch), with which two and when (closest_approach_agents,
    _t_s); from the logged frames alone for a recording made without it."""
    watched = rec.watch.closest
    if watched is None:
        return {"closest_approach_m": float(min(nearest_neighbor_m(f.position).min() for f in rec.frames))}
    if watched.closest is None:
        return {"closest_approach_m": float("inf")}
    c = watched.closest
    return {
        "closest_approach_m": c.distance_m,
        "closest_approach_agents": list(c.agents),
        "closest_approach_t_s": c.t_s,
    }


def leader_follower_metrics(fleet: LockstepFleet, rec: Recorder, p: dict[str, float]) -> dict:
    """The group follows a driven leader: arrival, spacing, closest approach, the weak buoy's lag."""
    leader = int(p.get("leader", 0))
    arrive_within = p.get("arrival_radius_m", 30.0)
    min_separation = p.get("min_separation_m", 1.0)
    times = rec.times()
    _, leader_xy = rec.agent_series(leader, "position")
    final_goal = leader_xy[-1]
    path_length = float(np.hypot(*np.diff(leader_xy, axis=0).T).sum())
    farthest = np.array([np.hypot(*(f.position - leader_xy[k]).T).max() for k, f in enumerate(rec.frames)])
    nn_final = nearest_neighbor_m(rec.frames[-1].position)
    result: dict = {
        "agents": int(fleet.n),
        "leader": leader,
        "leader_path_m": path_length,
        **closest_approach(rec),
        "final_nn_mean_m": float(nn_final.mean()),
        "final_nn_std_m": float(nn_final.std()),
        "all_within_radius_of_leader_s": None,
        "farthest_from_leader_m": _series(times, farthest, 2),
    }
    arrived = np.flatnonzero(farthest <= arrive_within)
    leader_done = np.flatnonzero(np.hypot(*(leader_xy - final_goal).T) < 1.0)
    if arrived.size and leader_done.size:
        after = arrived[arrived >= leader_done[0]]
        result["all_within_radius_of_leader_s"] = float(times[after[0]]) if after.size else None
    weak = [int(a) for a in p.get("weak_agents", [])]
    if weak:
        lag = [float(np.hypot(*(rec.agent_series(a, "position")[1][-1] - final_goal))) for a in weak]
        result["weak_final_distance_to_leader_m"] = lag
    result["criteria"] = {
        f"leader_travelled_at_least_{p.get('min_path_m', 300.0):g}_m": path_length >= p.get("min_path_m", 300.0),
        f"no_two_closer_than_{min_separation:g}_m": result["closest_approach_m"] >= min_separation,
        f"all_within_{arrive_within:g}_m_of_leader_at_end": result["all_within_radius_of_leader_s"] is not None,
    }
    return _finish(result)


def avoidance_metrics(fleet: LockstepFleet, rec: Recorder, p: dict[str, float]) -> dict:
    """Agent `mover` reaching its goal through a swarm: did it arrive, and did it yield, go around or through?

    through: part of its path lies deeper than `through_depth_m` inside the
    swarm's convex hull (taken when it sets off; the edge of a lattice is
    ragged, so grazing it is not crossing). around: no part does. yield: the
    swarm members were displaced by more than `yield_displacement_m` while it
    passed.
    """
    mover = int(p.get("mover", 0))
    goal = np.array([p["goal_x_m"], p["goal_y_m"]])
    arrive_within = p.get("arrival_radius_m", 10.0)
    times = rec.times()
    t_go = min((e["t_s"] for e in fleet.events_log), default=0.0)
    k_go = int(np.searchsorted(times, t_go))
    start = rec.frames[k_go]
    others = start.agents != mover
    hull_points = start.position[others]
    hull = hull_points[ConvexHull(hull_points).vertices]
    t_m, path = rec.agent_series(mover, "position")
    path_after = path[t_m >= t_go]
    edges = np.stack((hull, np.roll(hull, -1, axis=0)), axis=1)
    depth = np.hypot(*point_segment_offsets(path_after, edges).transpose(2, 0, 1)).min(axis=1)
    inside = points_in_polygon(path_after, hull) & (depth > p.get("through_depth_m", 40.0))
    distance = np.hypot(*(path_after - goal).T)
    arrived = np.flatnonzero(distance <= arrive_within)
    displacement = max(
        float(np.hypot(*(f.position[f.agents != mover] - hull_points).T).max()) for f in rec.frames[k_go:]
    )
    yielded = displacement > p.get("yield_displacement_m", 20.0)
    went_through = bool(inside.any())
    result = {
        "mover": mover,
        "goal_m": goal.tolist(),
        "arrival_time_s": float(t_m[t_m >= t_go][arrived[0]]) if arrived.size else None,
        "final_distance_to_goal_m": float(distance[-1]),
        "path_fraction_inside_swarm": float(inside.mean()),
        "swarm_max_displacement_m": displacement,
        "outcome": "yield" if (yielded and went_through) else ("through" if went_through else "around"),
    }
    expected = p.get("expected")
    result["criteria"] = {"reached_goal": result["arrival_time_s"] is not None}
    if expected is not None:
        result["expected_outcome"] = expected
        result["criteria"][f"outcome_is_{expected}"] = result["outcome"] == expected
    return _finish(result)
