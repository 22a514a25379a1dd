"""Geometry of sitl/world/world.py against values worked out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from sitl.world.world import (
    World,
    point_segment_offsets,
    points_in_polygon,
    polygon_segments,
    ray_segment_distance,
    segments_cross,
)


def seg(*pairs: tuple[tuple[float, float], tuple[float, float]]) -> np.ndarray:
    """(W, 2, 2) segments from ((x0, y0), (x1, y1)) pairs, m."""
    return np.array(pairs, dtype=float).reshape(-1, 2, 2)


def square_room(side: float = 2.0) -> World:
    vertices = np.array([[0.0, 0.0], [side, 0.0], [side, side], [0.0, side]])
    return World(walls=polygon_segments(vertices), rooms=[vertices])


# ---------------------------------------------------------------- polygon_segments


def test_polygon_segments_close_the_polygon() -> None:
    segments = polygon_segments(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]))
    assert segments.shape == (3, 2, 2)
    # The last edge runs from the last vertex back to the first.
    assert_allclose(segments[2], [[0.0, 1.0], [0.0, 0.0]])


# ---------------------------------------------------------------- ray_segment_distance


def test_ray_hits_wall_at_known_distance() -> None:
    # Ray from (0, 0) along +x; wall x = 3 from y = -1 to 1: hit at t = 3.
    d = ray_segment_distance(np.array([[0.0, 0.0]]), np.array([[1.0, 0.0]]), seg(((3.0, -1.0), (3.0, 1.0))))
    assert d.shape == (1,)
    assert d[0] == pytest.approx(3.0, abs=1e-12)


def test_oblique_ray_distance() -> None:
    # Ray from (1, 1) at 45 degrees; wall x = 4 (y from 0 to 10): hit at (4, 4), distance 3 * sqrt(2).
    u = np.array([[math.sqrt(0.5), math.sqrt(0.5)]])
    d = ray_segment_distance(np.array([[1.0, 1.0]]), u, seg(((4.0, 0.0), (4.0, 10.0))))
    assert d[0] == pytest.approx(3.0 * math.sqrt(2.0), abs=1e-12)


def test_ray_missing_the_segment_is_inf() -> None:
    origins, directions = np.array([[0.0, 0.0]]), np.array([[1.0, 0.0]])
    # The wall x = 3 spans y in [1, 2]: the ray along y = 0 passes below it.
    assert ray_segment_distance(origins, directions, seg(((3.0, 1.0), (3.0, 2.0))))[0] == np.inf
    # A wall behind the origin (x = -3) is not hit either.
    assert ray_segment_distance(origins, directions, seg(((-3.0, -1.0), (-3.0, 1.0))))[0] == np.inf


def test_parallel_and_collinear_rays_do_not_hit() -> None:
    origins, directions = np.array([[0.0, 0.0]]), np.array([[1.0, 0.0]])
    assert ray_segment_distance(origins, directions, seg(((0.0, 1.0), (5.0, 1.0))))[0] == np.inf
    assert ray_segment_distance(origins, directions, seg(((1.0, 0.0), (5.0, 0.0))))[0] == np.inf


def test_ray_hits_segment_endpoint() -> None:
    # Segment from (3, 0) to (3, 2): the ray along y = 0 touches its first endpoint (u = 0).
    d = ray_segment_distance(np.array([[0.0, 0.0]]), np.array([[1.0, 0.0]]), seg(((3.0, 0.0), (3.0, 2.0))))
    assert d[0] == pytest.approx(3.0)


def test_nearest_of_several_walls_per_ray() -> None:
    walls = seg(((5.0, -1.0), (5.0, 1.0)), ((2.0, -1.0), (2.0, 1.0)), ((-1.0, -4.0), (1.0, -4.0)))
    origins = np.zeros((3, 2))
    directions = np.array([[1.0, 0.0], [0.0, -1.0], [0.0, 1.0]])
    # +x: walls at 5 and 2 -> 2; -y: wall y = -4 -> 4; +y: nothing -> inf.
    assert_allclose(ray_segment_distance(origins, directions, walls), [2.0, 4.0, np.inf])


def test_no_walls_or_no_rays() -> None:
    assert_allclose(ray_segment_distance(np.zeros((2, 2)), np.array([[1.0, 0.0]] * 2), np.zeros((0, 2, 2))), np.inf)
    assert ray_segment_distance(np.zeros((0, 2)), np.zeros((0, 2)), seg(((1.0, 0.0), (1.0, 1.0)))).shape == (0,)


# ---------------------------------------------------------------- segments_cross


def test_segments_cross() -> None:
    wall = seg(((1.0, -1.0), (1.0, 1.0)))
    p = np.zeros((4, 2))
    q = np.array([[2.0, 0.0], [0.5, 0.0], [1.0, 0.0], [0.0, 3.0]])
    # p->q of length 2 crosses x = 1; length 0.5 stops short; ending exactly on the wall counts; along +y never.
    assert segments_cross(p, q, wall).tolist() == [True, False, True, False]


def test_segments_cross_outside_the_wall_span() -> None:
    # From (0, 2) to (2, 2): passes above the wall that ends at y = 1.
    assert not segments_cross(np.array([[0.0, 2.0]]), np.array([[2.0, 2.0]]), seg(((1.0, -1.0), (1.0, 1.0))))[0]


def test_segments_cross_without_walls() -> None:
    assert segments_cross(np.zeros((2, 2)), np.ones((2, 2)), np.zeros((0, 2, 2))).tolist() == [False, False]


# ---------------------------------------------------------------- point_segment_offsets


def test_point_segment_offsets() -> None:
    segments = seg(((0.0, 0.0), (4.0, 0.0)), ((0.0, 0.0), (0.0, 4.0)))
    points = np.array([[1.0, 2.0], [-1.0, -1.0], [6.0, 0.0]])
    off = point_segment_offsets(points, segments)
    assert off.shape == (3, 2, 2)
    # (1, 2): foot on the x axis (1, 0) -> (0, -2); foot on the y axis (0, 2) -> (-1, 0).
    assert_allclose(off[0], [[0.0, -2.0], [-1.0, 0.0]], atol=1e-12)
    # (-1, -1): both segments' closest point is their common endpoint (0, 0) -> (1, 1).
    assert_allclose(off[1], [[1.0, 1.0], [1.0, 1.0]], atol=1e-12)
    # (6, 0): end (4, 0) of the first -> (-2, 0); origin of the second -> (-6, 0).
    assert_allclose(off[2], [[-2.0, 0.0], [-6.0, 0.0]], atol=1e-12)


def test_point_offset_to_degenerate_segment() -> None:
    # A zero-length segment at (1, 1) behaves as a point.
    assert_allclose(point_segment_offsets(np.array([[0.0, 0.0]]), seg(((1.0, 1.0), (1.0, 1.0))))[0, 0], [1.0, 1.0])


# ---------------------------------------------------------------- points_in_polygon


def test_points_in_convex_polygon() -> None:
    square = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]])
    points = np.array([[1.0, 1.0], [0.1, 1.9], [3.0, 1.0], [-0.1, 1.0], [1.0, 2.5], [1.0, -0.5]])
    assert points_in_polygon(points, square).tolist() == [True, True, False, False, False, False]


def test_points_in_concave_polygon() -> None:
    # An L: the 4 x 4 square minus the notch [1, 4] x [1, 4].
    ell = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 1.0], [1.0, 1.0], [1.0, 4.0], [0.0, 4.0]])
    points = np.array([[0.5, 0.5], [3.5, 0.5], [0.5, 3.5], [3.0, 3.0], [1.5, 1.5], [5.0, 0.5], [0.5, 5.0]])
    assert points_in_polygon(points, ell).tolist() == [True, True, True, False, False, False, False]


def test_points_in_triangle_orientation_independent() -> None:
    tri = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 4.0]])
    points = np.array([[1.0, 1.0], [2.5, 2.5], [1.9, 1.9]])
    # x + y < 4 inside: 2 < 4 yes, 5 no, 3.8 yes.
    expected = [True, False, True]
    assert points_in_polygon(points, tri).tolist() == expected
    assert points_in_polygon(points, tri[::-1].copy()).tolist() == expected


def test_inside_rooms() -> None:
    world = square_room(2.0)
    assert world.inside_rooms(np.array([[1.0, 1.0], [3.0, 1.0]])).tolist() == [True, False]
    assert World().inside_rooms(np.array([[1e6, -1e6]])).tolist() == [True]


# ---------------------------------------------------------------- push_out_of_walls


def test_push_out_of_one_wall() -> None:
    world = square_room(2.0)
    positions = np.array([[1.0, 0.05], [1.0, 1.0], [1.96, 1.0]])
    radius = np.full(3, 0.08)
    pushed, contact = world.push_out_of_walls(positions, radius)
    # 0.05 m above y = 0 -> moved straight up to 0.08; the centre robot stays; 0.04 m from x = 2 -> x = 1.92.
    assert_allclose(pushed, [[1.0, 0.08], [1.0, 1.0], [1.92, 1.0]], atol=1e-12)
    assert contact.tolist() == [True, False, True]
    # The input is not modified in place.
    assert_allclose(positions[0], [1.0, 0.05])


def test_push_out_of_a_corner() -> None:
    world = square_room(2.0)
    # 0.05 from x = 0 and 0.03 from y = 0, radius 0.08: both walls push, ending at (0.08, 0.08).
    pushed, contact = world.push_out_of_walls(np.array([[0.05, 0.03], [1.97, 1.95]]), np.full(2, 0.08))
    assert_allclose(pushed, [[0.08, 0.08], [1.92, 1.92]], atol=1e-12)
    assert contact.tolist() == [True, True]


def test_push_radius_per_robot() -> None:
    world = square_room(2.0)
    # Same spot 0.2 m from y = 0: a buoy (0.3 m) is pushed to 0.3, an eBot (0.08 m) is not touched.
    pushed, contact = world.push_out_of_walls(np.array([[1.0, 0.2], [1.0, 0.2]]), np.array([0.3, 0.08]))
    assert_allclose(pushed, [[1.0, 0.3], [1.0, 0.2]], atol=1e-12)
    assert contact.tolist() == [True, False]


def test_push_away_from_wall_end() -> None:
    # A free wall from (0, 0) to (2, 0); a robot 0.05 m beyond its end is pushed radially to 0.08.
    world = World(walls=seg(((0.0, 0.0), (2.0, 0.0))))
    pushed, contact = world.push_out_of_walls(np.array([[2.03, 0.04]]), np.array([0.08]))
    # |(0.03, 0.04)| = 0.05 -> scaled to 0.08: (2 + 0.048, 0.064).
    assert_allclose(pushed, [[2.048, 0.064]], atol=1e-12)
    assert contact.tolist() == [True]


def test_push_without_walls_is_identity() -> None:
    positions = np.array([[0.0, 0.0]])
    pushed, contact = World().push_out_of_walls(positions, np.array([0.3]))
    assert_allclose(pushed, positions)
    assert contact.tolist() == [False]


# ---------------------------------------------------------------- light_readings


def light_world(walls: np.ndarray | None = None) -> World:
    return World(
        walls=np.zeros((0, 2, 2)) if walls is None else walls,
        light_positions=np.array([[0.0, 0.0]]),
        light_power_w=np.array([20.0]),
        light_height_m=0.3,
    )


def test_light_inverse_square_with_height_and_cardioid_gain() -> None:
    world = light_world()
    # Sensor at (0.4, 0): d^2 = 0.16 + 0.3^2 = 0.25; E = 20 / (4 pi 0.25) = 20 / pi W/m^2.
    full = 20.0 / math.pi
    # Sensor axes: at the source (pi) gain 1; away (0) gain 0; sideways (pi/2) gain (1 + cos(pi/2)) / 2 = 0.5;
    # 60 degrees off (2 pi / 3) gain (1 + 0.5) / 2 = 0.75.
    angles = np.array([[math.pi, 0.0, math.pi / 2, 2 * math.pi / 3]])
    readings = world.light_readings(np.array([[0.4, 0.0]]), angles)
    assert readings.shape == (1, 4)
    assert_allclose(readings[0], [full, 0.0, 0.5 * full, 0.75 * full], atol=1e-12)


def test_light_falls_with_distance() -> None:
    world = light_world()
    # At (0, 1.2) pointing at the source (-pi/2): d^2 = 1.44 + 0.09 = 1.53; E = 20 / (4 pi 1.53).
    readings = world.light_readings(np.array([[0.0, 1.2], [0.0, 0.4]]), np.array([[-math.pi / 2], [-math.pi / 2]]))
    assert readings[0, 0] == pytest.approx(20.0 / (4 * math.pi * 1.53), rel=1e-12)
    assert readings[1, 0] == pytest.approx(20.0 / math.pi, rel=1e-12)


def test_two_sources_add() -> None:
    world = World(light_positions=np.array([[-1.0, 0.0], [1.0, 0.0]]), light_power_w=np.array([10.0, 30.0]))
    # At the origin, sensor pointing up (pi/2): both sources sideways, gain 0.5 each; d^2 = 1 + 0.09.
    expected = 0.5 * (10.0 + 30.0) / (4 * math.pi * 1.09)
    assert world.light_readings(np.zeros((1, 2)), np.array([[math.pi / 2]]))[0, 0] == pytest.approx(expected)


def test_wall_between_source_and_sensor_blocks_light() -> None:
    blocked = light_world(seg(((0.2, -1.0), (0.2, 1.0))))
    beside = light_world(seg(((0.2, 0.5), (0.2, 1.0))))
    positions, angles = np.array([[0.4, 0.0]]), np.array([[math.pi]])
    assert blocked.light_readings(positions, angles)[0, 0] == 0.0
    assert beside.light_readings(positions, angles)[0, 0] == pytest.approx(20.0 / math.pi)


def test_no_lights_reads_zero() -> None:
    assert_allclose(World().light_readings(np.zeros((2, 2)), np.zeros((2, 2))), 0.0)
