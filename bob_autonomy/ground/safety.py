"""Geofence geometry in the local frame (m): is a point inside, and how to keep a velocity command inside.

The fence is a simple polygon of (x, y) vertices in metres (the uploaded
latitude/longitude polygon converted with the swarm's LocalFrame). A vessel
inside has the outward part of its desired velocity removed near each edge it
would cross within `lookahead_s`; a vessel outside is sent back to the nearest
point a margin inside the fence.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def inside_polygon(point: FloatArray, polygon: FloatArray) -> bool:
    """Whether the point (2,) m is inside the polygon (k, 2) m (even-odd rule)."""
    x, y = float(point[0]), float(point[1])
    a, b = polygon, np.roll(polygon, -1, axis=0)
    crosses = (a[:, 1] > y) != (b[:, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    return bool(np.count_nonzero(crosses & (x < x_at)) % 2)


def _closest_on_edges(point: FloatArray, polygon: FloatArray) -> tuple[FloatArray, FloatArray]:
    """For each edge: the closest point on it to `point` (k, 2), and the distance (k,), m."""
    a, b = polygon, np.roll(polygon, -1, axis=0)
    edge = b - a
    length2 = np.maximum(np.einsum("ij,ij->i", edge, edge), 1e-12)
    s = np.clip(np.einsum("ij,ij->i", point - a, edge) / length2, 0.0, 1.0)
    closest = a + s[:, None] * edge
    return closest, np.hypot(*(point - closest).T)


def _inward_normals(polygon: FloatArray) -> FloatArray:
    """(k, 2) unit normals of the edges pointing into the polygon (either vertex order)."""
    edge = np.roll(polygon, -1, axis=0) - polygon
    normal = np.column_stack((-edge[:, 1], edge[:, 0]))
    normal /= np.maximum(np.hypot(*normal.T), 1e-12)[:, None]
    area2 = float(np.sum(polygon[:, 0] * np.roll(polygon[:, 1], -1) - np.roll(polygon[:, 0], -1) * polygon[:, 1]))
    return normal if area2 > 0 else -normal  # counter-clockwise: the left normal points in


def limit_to_fence(
    position: FloatArray, velocity: FloatArray, polygon: FloatArray, lookahead_s: float = 5.0
) -> FloatArray:
    """The velocity (2,) m/s without its outward part across every edge closer than `lookahead_s` of travel."""
    v = np.asarray(velocity, dtype=float).copy()
    speed = float(np.hypot(*v))
    if speed == 0.0:
        return v
    _closest, distance = _closest_on_edges(position, polygon)
    normals = _inward_normals(polygon)
    for k in np.argsort(distance):
        if distance[k] > speed * lookahead_s:
            break
        outward = -float(v @ normals[k])
        if outward > 0.0:
            v += outward * normals[k]
    return v


def return_inside(position: FloatArray, polygon: FloatArray, speed_mps: float, margin_m: float = 5.0) -> FloatArray:
    """Velocity (2,) m/s at `speed_mps` towards the point `margin_m` inside the fence nearest `position`."""
    closest, distance = _closest_on_edges(position, polygon)
    k = int(np.argmin(distance))
    target = closest[k] + margin_m * _inward_normals(polygon)[k]
    return towards(position, target, speed_mps)


def towards(position: FloatArray, target: FloatArray, speed_mps: float, slow_radius_m: float = 5.0) -> FloatArray:
    """Velocity (2,) m/s towards `target`, `speed_mps` far away, slowing linearly inside `slow_radius_m`."""
    offset = np.asarray(target, dtype=float) - np.asarray(position, dtype=float)
    distance = float(np.hypot(*offset))
    if distance < 1e-9:
        return np.zeros(2)
    return offset / distance * speed_mps * min(1.0, distance / slow_radius_m)
