"""The simulated world: walls (from rooms and free segments) and light sources.

Geometry is vectorized over rays, robots and wall segments: rooms have tens of
segments, open water none, so the cost stays proportional to the robots that
actually sense something.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def polygon_segments(vertices: FloatArray) -> FloatArray:
    """(V, 2) closed polygon vertices (m) to its (V, 2, 2) edge segments."""
    vertices = np.asarray(vertices, dtype=float)
    return np.stack((vertices, np.roll(vertices, -1, axis=0)), axis=1)


def points_in_polygon(points: FloatArray, vertices: FloatArray) -> NDArray[np.bool_]:
    """Even-odd rule: which of the (P, 2) points lie inside the polygon (V, 2)."""
    x, y = points[:, 0:1], points[:, 1:2]
    x0, y0 = vertices[:, 0], vertices[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    crosses = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return np.count_nonzero(crosses & (x < x_at), axis=1) % 2 == 1


def ray_segment_distance(origins: FloatArray, directions: FloatArray, segments: FloatArray) -> FloatArray:
    """(R,) distance along unit rays to the nearest of the (W, 2, 2) segments (inf if none)."""
    if segments.shape[0] == 0 or origins.shape[0] == 0:
        return np.full(origins.shape[0], np.inf)
    a = segments[:, 0][None]  # (1, W, 2)
    e = (segments[:, 1] - segments[:, 0])[None]
    o = origins[:, None]  # (R, 1, 2)
    d = directions[:, None]
    denom = d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]
    ao = a - o
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (ao[..., 0] * e[..., 1] - ao[..., 1] * e[..., 0]) / denom
        u = (ao[..., 0] * d[..., 1] - ao[..., 1] * d[..., 0]) / denom
    hit = (np.abs(denom) > 1e-12) & (t >= 0.0) & (u >= 0.0) & (u <= 1.0)
    return np.where(hit, t, np.inf).min(axis=1)


def segments_cross(p: FloatArray, q: FloatArray, segments: FloatArray) -> NDArray[np.bool_]:
    """(P,) whether the segment p->q (each (P, 2)) crosses any of the walls (W, 2, 2)."""
    if segments.shape[0] == 0 or p.shape[0] == 0:
        return np.zeros(p.shape[0], dtype=bool)
    step = q - p
    length = np.hypot(step[:, 0], step[:, 1])
    direction = step / np.maximum(length, 1e-12)[:, None]
    return ray_segment_distance(p, direction, segments) <= length


def point_segment_offsets(points: FloatArray, segments: FloatArray) -> FloatArray:
    """(P, W, 2) vector from each point to the closest point of each segment, m."""
    a = segments[:, 0][None]
    e = (segments[:, 1] - segments[:, 0])[None]
    rel = points[:, None] - a
    t = np.clip(np.einsum("pwc,pwc->pw", rel, e) / np.maximum(np.einsum("pwc,pwc->pw", e, e), 1e-12), 0, 1)
    return a + t[..., None] * e - points[:, None]


@dataclass
class World:
    """Walls as segments (W, 2, 2) in m; light sources with power (W) and height (m)."""

    walls: FloatArray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    rooms: list[FloatArray] = field(default_factory=list)
    light_positions: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))
    light_power_w: FloatArray = field(default_factory=lambda: np.zeros(0))
    light_height_m: float = 0.3

    def push_out_of_walls(self, positions: FloatArray, radius: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
        """Move robot centres (P, 2) to at least `radius` (P,) m from every wall; report contacts."""
        if self.walls.shape[0] == 0:
            return positions, np.zeros(positions.shape[0], dtype=bool)
        positions = positions.copy()
        contact = np.zeros(positions.shape[0], dtype=bool)
        for _ in range(2):  # corners need a second pass
            off = point_segment_offsets(positions, self.walls)
            dist = np.hypot(off[..., 0], off[..., 1])
            nearest = dist.argmin(axis=1)
            rows = np.arange(positions.shape[0])
            d = dist[rows, nearest]
            inside = d < radius
            if not np.any(inside):
                break
            contact |= inside
            away = -off[rows, nearest] / np.maximum(d, 1e-12)[:, None]
            positions[inside] += away[inside] * (radius[inside] - d[inside])[:, None]
        return positions, contact

    def light_readings(self, positions: FloatArray, sensor_angles: FloatArray) -> FloatArray:
        """(P, S) irradiance (W/m^2) on sensors pointing at world angles (P, S) rad.

        Each source is isotropic, `light_height_m` above the sensors; a sensor's
        gain is the cardioid (1 + cos(angle off its axis)) / 2; walls block light.
        """
        readings = np.zeros(sensor_angles.shape)
        for source, power in zip(self.light_positions, self.light_power_w, strict=True):
            rel = source[None] - positions
            d2 = np.einsum("pc,pc->p", rel, rel)
            irradiance = power / (4.0 * np.pi * (d2 + self.light_height_m**2))
            visible = ~segments_cross(positions, np.broadcast_to(source, positions.shape), self.walls)
            bearing = np.arctan2(rel[:, 1], rel[:, 0])
            gain = 0.5 * (1.0 + np.cos(sensor_angles - bearing[:, None]))
            readings += (irradiance * visible)[:, None] * gain
        return readings

    def inside_rooms(self, positions: FloatArray) -> NDArray[np.bool_]:
        """(P,) whether each position is inside some room (all true with no rooms)."""
        if not self.rooms:
            return np.ones(positions.shape[0], dtype=bool)
        inside = np.zeros(positions.shape[0], dtype=bool)
        for room in self.rooms:
            inside |= points_in_polygon(positions, room)
        return inside
