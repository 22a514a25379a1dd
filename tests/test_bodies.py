"""KinematicBodies (sitl/vehicles/bodies.py): speed, acceleration and wheel limits, walls, range finders, light."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from sitl.vehicles.bodies import (
    BUOY,
    EBOT,
    EBOT_LIGHT_ANGLES_RAD,
    EBOT_SONAR_ANGLES_RAD,
    SONAR_CONE_OFFSETS_RAD,
    KinematicBodies,
)
from sitl.world.world import World, polygon_segments

DT = 0.1
WHEEL_BASE = 0.1  # m, eBot
EBOT_WHEEL_MAX = 0.20  # m/s
BUOY_MAX_SPEED = 1.0  # m/s
BUOY_MAX_ACCEL = 0.5  # m/s^2
EBOT_RADIUS, BUOY_RADIUS = 0.08, 0.3
OPEN = World()


def bodies(kinds: list[int], positions: list[list[float]], headings: list[float]) -> KinematicBodies:
    return KinematicBodies(np.array(kinds), np.array(positions, dtype=float), np.array(headings, dtype=float))


def room(side: float = 2.0) -> World:
    vertices = np.array([[0.0, 0.0], [side, 0.0], [side, side], [0.0, side]])
    return World(walls=polygon_segments(vertices), rooms=[vertices])


def wrap(a: np.ndarray | float) -> np.ndarray:
    return np.mod(np.asarray(a) + np.pi, 2 * np.pi) - np.pi


# ---------------------------------------------------------------- buoy


def test_buoy_accelerates_at_the_limit_up_to_top_speed() -> None:
    b = bodies([BUOY], [[0.0, 0.0]], [0.0])
    speeds, x = [], []
    for _ in range(30):
        b.apply(np.array([[5.0, 0.0]]), np.array([math.nan]), DT, OPEN)
        speeds.append(float(np.hypot(*b.velocity[0])))
        x.append(float(b.position[0, 0]))
    # dv per step = 0.5 m/s^2 * 0.1 s = 0.05 m/s: 0.05, 0.10, ... 1.0 after 20 steps, then held at 1.0.
    assert_allclose(speeds[:20], 0.05 * np.arange(1, 21), atol=1e-12)
    assert_allclose(speeds[20:], 1.0, atol=1e-12)
    # Distance after 20 steps: 0.1 * 0.05 * (1 + ... + 20) = 0.005 * 210 = 1.05 m; then 0.1 m per step.
    assert x[19] == pytest.approx(1.05, abs=1e-12)
    assert x[29] == pytest.approx(1.05 + 10 * 0.1, abs=1e-12)
    assert abs(b.velocity[0, 1]) < 1e-15


def test_buoy_never_exceeds_speed_or_acceleration_limit() -> None:
    rng = np.random.default_rng(1)
    n = 12
    b = bodies([BUOY] * n, rng.uniform(-5, 5, (n, 2)).tolist(), rng.uniform(-3, 3, n).tolist())
    for step in range(80):
        # A new random wish (up to 3 m/s, any direction) every 10 steps, including full reversals.
        if step % 10 == 0:
            wish = rng.uniform(-3.0, 3.0, (n, 2))
        before_p, before_v, before_h = b.position.copy(), b.velocity.copy(), b.heading.copy()
        b.apply(wish, np.full(n, math.nan), DT, OPEN)
        assert np.all(np.hypot(*b.velocity.T) <= BUOY_MAX_SPEED + 1e-12)
        assert np.all(np.hypot(*(b.velocity - before_v).T) <= BUOY_MAX_ACCEL * DT + 1e-12)
        # Turn rate 1.5 rad/s: at most 0.15 rad per step.
        assert np.all(np.abs(wrap(b.heading - before_h)) <= 1.5 * DT + 1e-12)
        # No walls: the body moves by exactly velocity * dt.
        assert_allclose(b.position - before_p, b.velocity * DT, atol=1e-12)


def test_buoy_decelerates_at_the_limit() -> None:
    b = bodies([BUOY], [[0.0, 0.0]], [0.0])
    for _ in range(20):
        b.apply(np.array([[1.0, 0.0]]), np.array([math.nan]), DT, OPEN)
    assert b.velocity[0, 0] == pytest.approx(1.0)
    b.apply(np.zeros((1, 2)), np.array([math.nan]), DT, OPEN)
    # Braking is limited too: 1.0 - 0.05 = 0.95 m/s.
    assert b.velocity[0, 0] == pytest.approx(0.95, abs=1e-12)


def test_buoy_turns_to_wished_heading_at_turn_rate() -> None:
    b = bodies([BUOY], [[0.0, 0.0]], [0.0])
    headings = []
    for _ in range(8):
        b.apply(np.zeros((1, 2)), np.array([1.0]), DT, OPEN)
        headings.append(float(b.heading[0]))
    # 0.15 rad per step: 0.15 ... 0.90 after 6 steps, then the remaining 0.10 and stop at 1.0.
    assert_allclose(headings, [0.15, 0.30, 0.45, 0.60, 0.75, 0.90, 1.0, 1.0], atol=1e-12)
    assert_allclose(b.position, [[0.0, 0.0]])


def test_buoy_faces_its_velocity_without_heading_wish() -> None:
    b = bodies([BUOY], [[0.0, 0.0]], [0.0])
    for _ in range(40):
        b.apply(np.array([[0.0, 1.0]]), np.array([math.nan]), DT, OPEN)
    assert b.heading[0] == pytest.approx(math.pi / 2, abs=1e-12)


# ---------------------------------------------------------------- eBot


def wheel_speeds(h_before: np.ndarray, b: KinematicBodies) -> tuple[np.ndarray, np.ndarray]:
    """Left and right wheel speeds (m/s) that produced the last step of a differential-drive body.

    turn = heading change; the body moved along mid = h + turn / 2 at forward speed v . (cos mid, sin mid);
    omega = turn / dt; wheels = forward -+ omega * wheel_base / 2.
    """
    turn = wrap(b.heading - h_before)
    mid = h_before + 0.5 * turn
    axis = np.column_stack((np.cos(mid), np.sin(mid)))
    forward = np.einsum("ij,ij->i", b.velocity, axis)
    # A differential drive cannot slide sideways.
    sideways = b.velocity[:, 0] * axis[:, 1] - b.velocity[:, 1] * axis[:, 0]
    assert_allclose(sideways, 0.0, atol=1e-12)
    omega = turn / DT
    return forward - 0.5 * WHEEL_BASE * omega, forward + 0.5 * WHEEL_BASE * omega


def test_ebot_straight_at_top_speed() -> None:
    b = bodies([EBOT], [[0.0, 0.0]], [0.0])
    b.apply(np.array([[1.0, 0.0]]), np.array([math.nan]), DT, OPEN)
    # Both wheels at 0.2 m/s: 0.02 m in 0.1 s; a 1 m/s wish is capped.
    assert_allclose(b.velocity, [[0.2, 0.0]], atol=1e-15)
    assert_allclose(b.position, [[0.02, 0.0]], atol=1e-15)
    assert b.heading[0] == 0.0


def test_ebot_small_turn_matches_hand_computation() -> None:
    b = bodies([EBOT], [[0.0, 0.0]], [0.0])
    b.apply(np.array([[0.2 * math.cos(0.1), 0.2 * math.sin(0.1)]]), np.array([math.nan]), DT, OPEN)
    # error 0.1 rad: forward 0.2 cos 0.1, omega 4 * 0.1 = 0.4; wheels forward -+ 0.02;
    # the right wheel 0.2 cos 0.1 + 0.02 > 0.2, so both scale by 0.2 / right.
    forward = 0.2 * math.cos(0.1)
    left, right = forward - 0.02, forward + 0.02
    scale = 0.2 / right
    left, right = left * scale, right * scale
    turn = (right - left) / WHEEL_BASE * DT
    speed = 0.5 * (left + right)
    assert b.heading[0] == pytest.approx(turn, abs=1e-12)
    assert_allclose(b.velocity[0], speed * np.array([math.cos(turn / 2), math.sin(turn / 2)]), atol=1e-12)


def test_ebot_wheels_never_exceed_limit() -> None:
    rng = np.random.default_rng(2)
    n = 25
    b = bodies([EBOT] * n, rng.uniform(-5, 5, (n, 2)).tolist(), rng.uniform(-3, 3, n).tolist())
    top = 0.0
    for step in range(60):
        if step % 6 == 0:
            wish_v = rng.uniform(-1.0, 1.0, (n, 2))
            wish_h = np.where(rng.random(n) < 0.5, math.nan, rng.uniform(-math.pi, math.pi, n))
        h_before = b.heading.copy()
        b.apply(wish_v, wish_h, DT, OPEN)
        left, right = wheel_speeds(h_before, b)
        top = max(top, np.abs(left).max(), np.abs(right).max())
        assert np.all(np.abs(left) <= EBOT_WHEEL_MAX + 1e-12)
        assert np.all(np.abs(right) <= EBOT_WHEEL_MAX + 1e-12)
    # The limit is reached, not just respected trivially.
    assert top == pytest.approx(EBOT_WHEEL_MAX, abs=1e-9)


def test_ebot_turns_in_place_for_a_heading_behind_it() -> None:
    b = bodies([EBOT], [[1.0, 1.0]], [0.0])
    h_before = b.heading.copy()
    b.apply(np.array([[-0.1, 0.0]]), np.array([math.nan]), DT, OPEN)
    # error = pi: forward = 0.1 * max(cos pi, 0) = 0; wheels -+0.2 m/s -> omega 0.4 / 0.1 = 4 rad/s, 0.4 rad.
    assert_allclose(b.position, [[1.0, 1.0]], atol=1e-15)
    assert_allclose(b.velocity, 0.0, atol=1e-15)
    assert abs(b.heading[0]) == pytest.approx(0.4, abs=1e-12)
    left, right = wheel_speeds(h_before, b)
    assert_allclose(sorted([left[0], right[0]]), [-0.2, 0.2], atol=1e-12)


def test_ebot_explicit_heading_wish_turns_towards_it() -> None:
    b = bodies([EBOT], [[0.0, 0.0]], [0.0])
    for _ in range(10):
        b.apply(np.zeros((1, 2)), np.array([math.pi / 2]), DT, OPEN)
    # omega = 4 * error, wheels -+omega * 0.05 capped at 0.2 m/s (|omega| <= 4 rad/s, 0.4 rad per step):
    # errors pi/2 -> pi/2 - 0.4 -> pi/2 - 0.8 = 0.7708 (4 * 0.7708 * 0.05 = 0.154 < 0.2: no cap from here),
    # then each step turns 0.4 * error, leaving 0.6 * error: after 8 more steps (pi/2 - 0.8) * 0.6^8.
    assert math.pi / 2 - b.heading[0] == pytest.approx((math.pi / 2 - 0.8) * 0.6**8, abs=1e-12)
    assert_allclose(b.position, 0.0, atol=1e-15)


def test_ebot_driven_into_wall_stays_inside_and_counts_contacts() -> None:
    world = room(2.0)
    b = bodies([EBOT], [[1.85, 1.0]], [0.0])
    xs, contacts = [], []
    for _ in range(10):
        b.apply(np.array([[0.2, 0.0]]), np.array([math.nan]), DT, world)
        xs.append(float(b.position[0, 0]))
        contacts.append(b.wall_contacts)
    # 0.02 m per step: 1.87, 1.89, 1.91, then 1.93 > 2 - 0.08 is pushed back to 1.92 (contact) every step.
    assert_allclose(xs, [1.87, 1.89, 1.91] + [1.92] * 7, atol=1e-12)
    assert contacts == [0, 0, 0, 1, 2, 3, 4, 5, 6, 7]
    # The velocity is what actually happened: (1.92 - 1.91) / 0.1 = 0.1 m/s, then 0.
    assert b.velocity[0, 0] == pytest.approx(0.0, abs=1e-12)
    assert bool(world.inside_rooms(b.position)[0])


def test_ebot_driven_into_corner() -> None:
    world = room(2.0)
    b = bodies([EBOT], [[1.85, 1.85]], [math.pi / 4])
    for _ in range(10):
        b.apply(np.array([[0.2, 0.2]]), np.array([math.nan]), DT, world)
        assert np.all(b.position <= 2.0 - EBOT_RADIUS + 1e-12)
    assert_allclose(b.position, [[1.92, 1.92]], atol=1e-12)
    assert b.wall_contacts > 0


def test_inactive_robots_do_not_move_or_count() -> None:
    world = room(2.0)
    b = bodies([EBOT, BUOY], [[1.85, 1.0], [1.0, 1.0]], [0.0, 0.0])
    b.active[:] = False
    for _ in range(10):
        b.apply(np.array([[0.2, 0.0], [1.0, 0.0]]), np.array([math.nan, 1.0]), DT, world)
    assert_allclose(b.position, [[1.85, 1.0], [1.0, 1.0]])
    assert_allclose(b.heading, [0.0, 0.0])
    assert_allclose(b.velocity, 0.0)
    assert b.wall_contacts == 0


def test_inactive_robot_near_wall_does_not_move() -> None:
    world = room(2.0)
    b = bodies([EBOT], [[1.0, 0.05]], [0.0])  # 0.05 m from y = 0 (radius 0.08), e.g. placed there at the start
    b.active[:] = False
    b.apply(np.zeros((1, 2)), np.array([math.nan]), DT, world)
    assert_allclose(b.position, [[1.0, 0.05]])
    assert_allclose(b.velocity, 0.0)


# ---------------------------------------------------------------- range finders


def sonar(k_axis: int) -> float:
    """World angle (rad) of sonar k for an eBot with heading 0."""
    return float(EBOT_SONAR_ANGLES_RAD[k_axis])


def test_sonar_layout() -> None:
    # Six sonars 60 degrees apart, the first straight ahead.
    assert_allclose(np.degrees(EBOT_SONAR_ANGLES_RAD), [0, 60, 120, 180, -120, -60])


def test_wall_straight_ahead() -> None:
    world = World(walls=np.array([[[1.0, -5.0], [1.0, 5.0]]]))
    b = bodies([EBOT], [[0.0, 0.0]], [0.0])
    hits = b.range_finders(np.array([0]), world)
    assert hits.shape == (1, 6, 2)
    # Straight ahead at 1.0 m: offset (1, 0). Sonars 120, 180, -120 face away from the wall: nothing.
    assert_allclose(hits[0, 0], [1.0, 0.0], atol=1e-12)
    assert np.all(np.isnan(hits[0, [2, 3, 4]]))


def test_wall_ahead_of_a_turned_robot() -> None:
    # Heading pi/2 (north), wall y = 1.5 + 1.0: offset (0, 1) in the world frame.
    world = World(walls=np.array([[[-5.0, 2.5], [5.0, 2.5]]]))
    b = bodies([EBOT], [[0.3, 1.5]], [math.pi / 2])
    assert_allclose(b.range_finders(np.array([0]), world)[0, 0], [0.0, 1.0], atol=1e-12)


def test_wall_beyond_range_is_nan() -> None:
    # 1.6 m ahead > 1.5 m range; the +-60 degree sonars see it at >= 1.6 / cos(30 deg) = 1.85 m at the nearest.
    world = World(walls=np.array([[[1.6, -5.0], [1.6, 5.0]]]))
    b = bodies([EBOT], [[0.0, 0.0]], [0.0])
    assert np.all(np.isnan(b.range_finders(np.array([0]), world)))


def test_other_robot_on_a_sonar_axis() -> None:
    # Robot 1 at 0.5 m along the 60 degree sonar of robot 0: echo at 0.5 - 0.08 = 0.42 m.
    angle = sonar(1)
    other = 0.5 * np.array([math.cos(angle), math.sin(angle)])
    # Robot 1 faces robot 0 (heading 60 + 180 = 240 deg): its straight-ahead sonar sees it at 0.42 m too.
    b = bodies([EBOT, EBOT], [[0.0, 0.0], other.tolist()], [0.0, angle + math.pi])
    hits = b.range_finders(np.array([0, 1]), OPEN)
    assert hits.shape == (2, 6, 2)
    assert_allclose(hits[0, 1], 0.42 * np.array([math.cos(angle), math.sin(angle)]), atol=1e-12)
    assert_allclose(hits[1, 0], -0.42 * np.array([math.cos(angle), math.sin(angle)]), atol=1e-12)
    # The disc (0.08 m at 0.5 m, 9.2 degrees) is 30+ degrees off every other sonar's rays: nothing else.
    assert np.all(np.isnan(np.delete(hits[0], 1, axis=0)))
    assert np.all(np.isnan(np.delete(hits[1], 0, axis=0)))


def test_sonar_cone_reports_nearest_echo_on_its_axis() -> None:
    # Cones of about +-30 degrees sampled at +-27, +-13.5 and 0: neighbouring sonars share no ray.
    assert_allclose(np.degrees(SONAR_CONE_OFFSETS_RAD), [-27.0, -13.5, 0.0, 13.5, 27.0])
    # A robot 0.5 m straight to the left (90 deg) is 3 degrees off the 87 degree edge ray of the 60 degree
    # sonar and the 93 degree edge ray of the 120 degree one: miss distance 0.5 sin 3 = 0.0262 m < 0.08 m,
    # echo at 0.5 cos 3 - sqrt(0.08^2 - 0.0262^2) = 0.4237 m, reported along each sonar's own axis.
    b = bodies([EBOT, EBOT], [[0.0, 0.0], [0.0, 0.5]], [0.0, 0.0])
    hits = b.range_finders(np.array([0]), OPEN)[0]
    miss = 0.5 * math.sin(math.radians(3.0))
    echo = 0.5 * math.cos(math.radians(3.0)) - math.sqrt(0.08**2 - miss**2)
    for k in (1, 2):
        assert_allclose(hits[k], echo * np.array([math.cos(sonar(k)), math.sin(sonar(k))]), atol=1e-12)
    assert np.all(np.isnan(hits[[0, 3, 4, 5]]))
    # The wall x = 1 seen by the 60 degree sonar: nearest along its 33 degree edge ray, 1 / cos 33 = 1.1924 m.
    world = World(walls=np.array([[[1.0, -5.0], [1.0, 5.0]]]))
    hits = bodies([EBOT], [[0.0, 0.0]], [0.0]).range_finders(np.array([0]), world)[0]
    d = 1.0 / math.cos(math.radians(33.0))
    assert_allclose(hits[1], d * np.array([math.cos(sonar(1)), math.sin(sonar(1))]), atol=1e-12)
    assert_allclose(hits[5], d * np.array([math.cos(sonar(5)), math.sin(sonar(5))]), atol=1e-12)


def test_buoy_seen_at_its_radius() -> None:
    # A buoy (radius 0.3 m) 1.0 m ahead: echo at 0.7 m.
    b = bodies([EBOT, BUOY], [[0.0, 0.0], [1.0, 0.0]], [0.0, 0.0])
    assert_allclose(b.range_finders(np.array([0]), OPEN)[0, 0], [0.7, 0.0], atol=1e-12)


def test_robot_range_limit_applies_to_its_surface() -> None:
    # Centre 1.55 m ahead: surface at 1.47 m <= 1.5 m, seen. Centre 1.7 m: surface 1.62 m, NaN.
    near = bodies([EBOT, EBOT], [[0.0, 0.0], [1.55, 0.0]], [0.0, 0.0])
    far = bodies([EBOT, EBOT], [[0.0, 0.0], [1.7, 0.0]], [0.0, 0.0])
    assert_allclose(near.range_finders(np.array([0]), OPEN)[0, 0], [1.47, 0.0], atol=1e-12)
    assert np.all(np.isnan(far.range_finders(np.array([0]), OPEN)))


def test_nearest_echo_wins_robot_before_wall() -> None:
    world = World(walls=np.array([[[1.0, -5.0], [1.0, 5.0]]]))
    b = bodies([EBOT, EBOT], [[0.0, 0.0], [0.5, 0.0]], [0.0, 0.0])
    # Robot surface at 0.42 m in front of the wall at 1.0 m.
    assert_allclose(b.range_finders(np.array([0]), world)[0, 0], [0.42, 0.0], atol=1e-12)


def test_inactive_robots_are_invisible() -> None:
    b = bodies([EBOT, EBOT], [[0.0, 0.0], [0.5, 0.0]], [0.0, 0.0])
    assert np.isfinite(b.range_finders(np.array([0]), OPEN)[0, 0]).all()
    b.active[1] = False
    assert np.all(np.isnan(b.range_finders(np.array([0]), OPEN)))


def test_no_self_echo_when_alone() -> None:
    b = bodies([EBOT], [[0.0, 0.0]], [0.0])
    assert np.all(np.isnan(b.range_finders(np.array([0]), OPEN)))


# ---------------------------------------------------------------- light sensors


def test_light_sensor_layout() -> None:
    assert_allclose(np.degrees(EBOT_LIGHT_ANGLES_RAD), [45.0, -45.0])  # left, right


def test_light_sensors_left_and_right() -> None:
    world = World(light_positions=np.array([[0.0, 0.0]]), light_power_w=np.array([20.0]), light_height_m=0.3)
    # Both at (0.4, 0): irradiance 20 / (4 pi (0.16 + 0.09)) = 20 / pi.
    full = 20.0 / math.pi
    b = bodies([EBOT, EBOT], [[0.4, 0.0], [0.4, 0.0]], [math.pi, math.pi / 2])
    readings = b.light_sensors(np.array([0, 1]), world)
    # Facing the source: each sensor is 45 degrees off, gain (1 + cos 45) / 2.
    g45, g135 = (1 + math.cos(math.pi / 4)) / 2, (1 + math.cos(3 * math.pi / 4)) / 2
    assert_allclose(readings[0], [g45 * full, g45 * full], rtol=1e-12)
    # Facing north with the source to the west (on the left): left 45 degrees off, right 135 degrees off.
    assert_allclose(readings[1], [g45 * full, g135 * full], rtol=1e-12)
