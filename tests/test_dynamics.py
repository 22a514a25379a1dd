"""Physical bodies (sitl/vehicles/dynamics.py) against force balances and closed forms worked out here.

Expected values never come from the integrator: terminal speeds and drifts are
roots of the force balance (scipy.optimize.brentq), coasting follows the closed
form of m dv/dt = -(c1 v + c2 v^2), and the eBot's motions follow from the
unicycle model by hand.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.optimize import brentq

from sitl.vehicles.dynamics import (
    BuoyDynamics,
    BuoyParams,
    DiffDriveDynamics,
    DiffDriveParams,
    equivalent_drift_mps,
    wrap_angle,
)
from sitl.world.environment import CurrentSpec, Environment, WindSpec
from sitl.world.world import World, point_segment_offsets, polygon_segments

DT = 0.1  # s
# Default buoy parameters, restated by hand: the tests derive everything from these.
MASS = 25.0 + 10.0  # kg, dry + added
C1, C2 = 5.0, 40.0  # N/(m/s), N/(m/s)^2
KA = 0.5 * 1.225 * 1.0 * 0.15  # N/(m/s)^2, 0.5 rho Cd A
FULL_THRUST = C1 * 1.0 + (C2 + KA) * 1.0**2  # N: total drag at 1 m/s in still water and air
STILL = BuoyParams(yaw_torque_std_nm=0.0)  # heading holds still unless pushed


def buoys(n: int = 1, heading: float | list[float] = 0.0, params: BuoyParams = STILL, seed: int = 0) -> BuoyDynamics:
    return BuoyDynamics(params, np.zeros((n, 2)), np.broadcast_to(heading, (n,)), np.random.default_rng(seed))


def run(b: BuoyDynamics, cmd: np.ndarray, seconds: float, **kwargs: np.ndarray) -> None:
    for _ in range(round(seconds / DT)):
        b.step(cmd, DT, **kwargs)


def speed(v: np.ndarray) -> np.ndarray:
    return np.hypot(v[:, 0], v[:, 1])


# --------------------------------------------------------------------------- buoy


def test_max_thrust_is_derived_from_the_top_speed() -> None:
    assert STILL.max_thrust_n == pytest.approx(FULL_THRUST, rel=1e-12)
    slower = BuoyParams(design_top_speed_mps=0.5)
    assert slower.max_thrust_n == pytest.approx(C1 * 0.5 + (C2 + KA) * 0.25, rel=1e-12)


@pytest.mark.parametrize("body_angle_deg", [0.0, 90.0, 180.0, -135.0, 33.0])
def test_full_thrust_in_still_water_reaches_one_metre_per_second_in_any_body_direction(body_angle_deg: float) -> None:
    heading = math.radians(20.0)
    b = buoys(heading=heading)
    a = math.radians(body_angle_deg)
    cmd = 2.0 * FULL_THRUST * np.array([[math.cos(a), math.sin(a)]])  # above the limit: clipped
    run(b, cmd, 30.0)
    v = b.velocity_mps[0]
    assert np.hypot(*v) == pytest.approx(1.0, rel=0.01)
    # World direction = body direction rotated by the true heading.
    assert_allclose(v / np.hypot(*v), [math.cos(heading + a), math.sin(heading + a)], atol=1e-6)
    assert np.hypot(*b.thrust_n[0]) == pytest.approx(FULL_THRUST, rel=1e-9)


def test_forward_thrust_with_heading_north_moves_north() -> None:
    b = buoys(heading=math.pi / 2)
    run(b, np.array([[FULL_THRUST, 0.0]]), 20.0)
    assert_allclose(b.velocity_mps[0], [0.0, 1.0], atol=0.01)
    assert b.position_m[0, 1] > 15.0
    assert abs(b.position_m[0, 0]) < 1e-6


def test_weak_battery_gives_the_lower_terminal_speed() -> None:
    b = buoys(n=2)
    limits = np.array([FULL_THRUST, 0.5 * FULL_THRUST])
    run(b, np.array([[100.0, 0.0], [100.0, 0.0]]), 30.0, max_thrust_n=limits)
    weak = brentq(lambda v: C1 * v + (C2 + KA) * v * v - 0.5 * FULL_THRUST, 0.0, 1.0)
    assert weak < 0.75
    assert_allclose(speed(b.velocity_mps), [1.0, weak], rtol=0.01)


def test_coasting_matches_the_closed_form() -> None:
    # M dv/dt = -(c1 v + c2 v^2), c2 here water + air (still air): with a = c1/M, b = c2/M,
    # 1/v = (1/v0 + b/a) e^{a t} - b/a and x = (M/c2) ln(1 + (c2 v0/c1)(1 - e^{-a t})).
    c2 = C2 + KA
    a, bq = C1 / MASS, c2 / MASS
    b = buoys(heading=0.3)
    b.velocity_mps[:] = [[0.8, -0.6]]  # 1 m/s towards -36.87 deg
    speeds, distances = [], []
    for _ in range(200):
        b.step(np.zeros((1, 2)), DT)
        speeds.append(np.hypot(*b.velocity_mps[0]))
        distances.append(np.hypot(*b.position_m[0]))
    t = DT * np.arange(1, 201)
    v_exact = 1.0 / ((1.0 + bq / a) * np.exp(a * t) - bq / a)
    x_exact = MASS / c2 * np.log(1.0 + c2 / C1 * (1.0 - np.exp(-a * t)))
    assert np.all(np.diff(speeds) < 0.0)
    assert_allclose(speeds, v_exact, rtol=0.01)
    assert_allclose(distances, x_exact, rtol=0.01)
    assert_allclose(b.velocity_mps[0] / speeds[-1], [0.8, -0.6], atol=1e-9)  # straight line


def test_acceleration_is_reported_for_the_last_step() -> None:
    b = buoys()
    acc = b.step(np.array([[FULL_THRUST, 0.0]]), DT)
    # From rest: M dv/dt = T - c1 v - (c2 + ka) v^2, v tiny; mean over 0.1 s within a few %.
    assert acc[0, 0] == pytest.approx(FULL_THRUST / MASS, rel=0.05)
    assert_allclose(b.acceleration_mps2, acc)
    assert acc[0, 1] == 0.0


def test_wind_alone_gives_the_force_balance_drift() -> None:
    wind_speed, toward = 8.0, 30.0
    env = Environment(WindSpec(wind_speed, toward), CurrentSpec(), np.random.default_rng(0))
    b = buoys(heading=1.0)
    for _ in range(600):
        b.step(np.zeros((1, 2)), DT, wind_mps=env.wind_at(b.position_m), current_mps=env.current_at(b.position_m))
    # Along the wind: air drag on the hull = water drag relative to the surface water
    # that the wind drives at 3 % of its speed.
    surface = 0.03 * wind_speed

    def balance(v: float) -> float:
        return KA * (wind_speed - v) ** 2 - (C1 * (v - surface) + C2 * (v - surface) ** 2)

    drift = brentq(balance, surface, wind_speed)
    assert 0.3 < drift < 0.6
    direction = np.radians(toward)
    assert_allclose(b.velocity_mps[0], drift * np.array([np.cos(direction), np.sin(direction)]), rtol=0.01)


def test_passive_buoy_ends_moving_with_the_current() -> None:
    b = buoys(n=3, heading=[0.0, 2.0, -2.5])
    current = np.array([[0.3, 0.0], [0.0, -0.5], [-0.2, 0.2]])
    run(b, np.zeros((3, 2)), 100.0, current_mps=current)  # ~14 time constants M / c1
    # It moves with the water, held back a little by the still air on its hull:
    # water drag on (c - v) = air drag on v, along the current.
    for v, c in zip(b.velocity_mps, current, strict=True):
        c_speed = np.hypot(*c)
        balance = brentq(
            lambda s, c_speed=c_speed: C1 * (c_speed - s) + C2 * (c_speed - s) ** 2 - KA * s * s, 0.0, c_speed
        )
        assert_allclose(v, balance * c / c_speed, rtol=1e-3, atol=1e-6)
        assert np.hypot(*v) == pytest.approx(c_speed, rel=0.01)


def test_thrust_direction_slews_at_its_limit_on_a_reversal() -> None:
    b = buoys(heading=0.7)
    run(b, np.array([[FULL_THRUST, 0.0]]), 1.0)
    start = b.thrust_n[0] / FULL_THRUST
    slew = STILL.thrust_slew_radps
    for k in range(1, 15):
        b.step(np.array([[-FULL_THRUST, 0.0]]), DT)
        turned = math.acos(np.clip(np.dot(b.thrust_n[0] / FULL_THRUST, start), -1.0, 1.0))
        assert turned == pytest.approx(min(slew * DT * k, math.pi), abs=1e-6)
        assert np.hypot(*b.thrust_n[0]) == pytest.approx(FULL_THRUST, rel=1e-9)
    reverse = np.array([-math.cos(0.7), -math.sin(0.7)])
    assert_allclose(b.thrust_n[0] / FULL_THRUST, reverse, atol=1e-9)


def test_heading_wanders_with_the_stationary_yaw_rate_of_the_torque_model() -> None:
    # I r' = -c r + tau, tau Gauss-Markov (std s, time constant tc): a first-order
    # filter (time constant T = I/c, gain 1/c) on it has Var r = (s/c)^2 tc / (tc + T).
    params = BuoyParams(yaw_torque_std_nm=0.05)
    inertia, damping, s, tc = 1.5, 2.0, 0.05, 5.0
    expected_std = s / damping * math.sqrt(tc / (tc + inertia / damping))
    n = 1000
    b = BuoyDynamics(params, np.zeros((n, 2)), np.zeros(n), np.random.default_rng(3))
    samples = []
    for k in range(1, 601):
        b.step(np.zeros((n, 2)), DT)
        if k >= 100 and k % 50 == 0:
            samples.append(b.yaw_rate_radps.copy())
    assert np.std(samples) == pytest.approx(expected_std, rel=0.08)
    assert np.std(b.heading_rad) > 0.1  # the heading has wandered
    assert np.all(b.heading_rad <= math.pi) and np.all(b.heading_rad > -math.pi)
    assert_allclose(b.velocity_mps, 0.0, atol=1e-12)  # yaw alone does not translate


def test_buoys_are_deterministic_for_a_seed() -> None:
    def final(seed: int) -> np.ndarray:
        env = Environment(WindSpec(6.0, 45.0, 0.3, 10.0), CurrentSpec(0.2, 0.0), np.random.default_rng(seed))
        b = BuoyDynamics(
            BuoyParams(), np.array([[0.0, 0.0], [5.0, 5.0]]), np.array([0.0, 1.0]), np.random.default_rng(seed)
        )
        cmd = np.array([[20.0, 5.0], [0.0, -10.0]])
        for _ in range(100):
            env.step(DT)
            b.step(cmd, DT, env.wind_at(b.position_m), env.current_at(b.position_m))
        return np.concatenate((b.position_m.ravel(), b.heading_rad, b.velocity_mps.ravel()))

    assert_allclose(final(11), final(11), rtol=0, atol=0)
    assert not np.allclose(final(11), final(12))


def test_inactive_buoys_do_not_move() -> None:
    b = BuoyDynamics(BuoyParams(), np.array([[1.0, 2.0], [3.0, 4.0]]), np.array([0.5, -0.5]), np.random.default_rng(0))
    b.active[1] = False
    cmd = np.full((2, 2), 30.0)
    run(b, cmd, 5.0, wind_mps=np.full((2, 2), 5.0), current_mps=np.full((2, 2), 0.3))
    assert_allclose(b.position_m[1], [3.0, 4.0], rtol=0, atol=0)
    assert b.heading_rad[1] == -0.5
    assert_allclose(b.velocity_mps[1], 0.0)
    assert_allclose(b.acceleration_mps2[1], 0.0)
    assert_allclose(b.thrust_n[1], 0.0)
    assert np.hypot(*b.position_m[0] - [1.0, 2.0]) > 2.0


def toward(speed: float, deg: float) -> np.ndarray:
    return speed * np.array([math.cos(math.radians(deg)), math.sin(math.radians(deg))])


@pytest.mark.parametrize(("wind_deg", "current_deg"), [(60.0, 180.0), (0.0, 0.0), (-90.0, 45.0)])
def test_unpowered_buoy_settles_at_the_equivalent_drift(wind_deg: float, current_deg: float) -> None:
    wind, current = toward(5.0, wind_deg), toward(0.1, current_deg)
    b = buoys(heading=0.7)
    run(b, np.zeros((1, 2)), 120.0, wind_mps=wind[None], current_mps=current[None])
    drift = equivalent_drift_mps(STILL, wind, current)
    assert drift.shape == (1, 2)
    assert_allclose(b.velocity_mps, drift, rtol=0, atol=1e-6)
    # By hand: water drag and windage are opposite there, so the buoy sits on the segment from the surface water
    # u to the wind w, slipping s through the water with c1 s + c2 s^2 = ka (|w - u| - s)^2.
    water = current + 0.03 * wind
    span = np.hypot(*(wind - water))
    slip = brentq(lambda s: C1 * s + C2 * s * s - KA * (span - s) ** 2, 0.0, span)
    assert_allclose(drift[0], water + slip * (wind - water) / span, rtol=1e-12, atol=1e-12)
    # It is its own equivalent drift (the force vanishes there).
    assert_allclose(equivalent_drift_mps(STILL, wind, current, drift), drift, rtol=0, atol=1e-12)


def test_equivalent_drift_makes_the_water_drag_law_exact_at_the_operating_velocity() -> None:
    # Steady under constant thrust T, at velocity v: T = D_w(v - d) with d the equivalent drift at v, so the
    # nominal model M dv/dt = T - D_w(v - d) balances exactly there.
    wind, current = np.array([toward(5.0, 30.0), toward(8.0, -120.0)]), np.array([toward(0.2, 200.0), [0.0, 0.0]])
    thrust = np.array([[8.0, -3.0], [-2.0, 5.0]])
    b = buoys(n=2)  # heading 0: body frame = world frame
    run(b, thrust, 120.0, wind_mps=wind, current_mps=current)
    v = b.velocity_mps
    relative = v - equivalent_drift_mps(STILL, wind, current, v)
    speed = np.hypot(*relative.T)
    assert_allclose((C1 + C2 * speed)[:, None] * relative, thrust, rtol=1e-6)
    # At rest, the drift a buoy holding station feels is not the one it would drift at unpowered (a few cm/s
    # apart in a 5 m/s wind): it depends on the operating velocity.
    at_rest = equivalent_drift_mps(STILL, wind[0], current[0], np.zeros(2))
    unpowered = equivalent_drift_mps(STILL, wind[0], current[0])
    assert 0.02 < np.hypot(*(at_rest - unpowered)[0]) < 0.1
    # At rest: D_w(d) = D_w(u) + ka |w| w, the push of water and wind on a still hull.
    water = current[0] + 0.03 * wind[0]
    push = (C1 + C2 * np.hypot(*water)) * water + KA * np.hypot(*wind[0]) * wind[0]
    d = at_rest[0]
    assert_allclose((C1 + C2 * np.hypot(*d)) * d, push, rtol=1e-12)


def test_wrap_angle_is_half_open_at_minus_pi() -> None:
    assert_allclose(
        wrap_angle(np.array([math.pi, -math.pi, 3 * math.pi, 0.1 - 2 * math.pi])), [math.pi, math.pi, math.pi, 0.1]
    )


# --------------------------------------------------------------------------- eBot

EBOT_RADIUS, WHEEL_BASE, VMAX = 0.08, 0.1, 0.2  # m, m, m/s
EXACT = DiffDriveParams(slip_noise=0.0)
OPEN = World()


def ebots(positions: list[list[float]], headings: list[float], params: DiffDriveParams = EXACT, seed: int = 0):
    return DiffDriveDynamics(params, np.array(positions, dtype=float), np.array(headings), np.random.default_rng(seed))


def room(side: float) -> World:
    vertices = np.array([[0.0, 0.0], [side, 0.0], [side, side], [0.0, side]])
    return World(walls=polygon_segments(vertices), rooms=[vertices])


def wall_clearance(world: World, positions: np.ndarray) -> np.ndarray:
    off = point_segment_offsets(positions, world.walls)
    return np.hypot(off[..., 0], off[..., 1]).min(axis=1)


def min_pair_distance(positions: np.ndarray) -> float:
    d = np.hypot(*(positions[:, None] - positions[None]).transpose(2, 0, 1))
    return float(d[np.triu_indices(len(positions), 1)].min())


def test_wheel_speeds_are_clipped() -> None:
    e = ebots([[0, 0], [0, 5], [0, 10]], [0.0, 0.0, 0.0])
    cmd = np.array([[1.0, 1.0], [0.5, 0.3], [-3.0, -3.0]])
    for _ in range(10):
        e.step(cmd, DT, OPEN)
        assert np.all(speed(e.velocity_mps) <= VMAX + 1e-12)
    assert_allclose(e.velocity_mps[0], [VMAX, 0.0], atol=1e-12)
    assert_allclose(e.velocity_mps[2], [-VMAX, 0.0], atol=1e-12)
    assert_allclose(e.position_m[0], [VMAX * 1.0, 0.0], atol=1e-12)


def test_turning_in_place() -> None:
    e = ebots([[1.0, 1.0]], [0.0])
    e.step(np.array([[-VMAX, VMAX]]), DT, OPEN)
    assert e.yaw_rate_radps[0] == pytest.approx(2 * VMAX / WHEEL_BASE)  # 4 rad/s
    assert e.heading_rad[0] == pytest.approx(0.4)
    assert_allclose(e.position_m[0], [1.0, 1.0], atol=1e-12)
    for _ in range(20):
        e.step(np.array([[-VMAX, VMAX]]), DT, OPEN)
    assert e.heading_rad[0] == pytest.approx(float(wrap_angle(21 * 0.4)))
    assert -math.pi < e.heading_rad[0] <= math.pi


def test_straight_driving_distance_is_speed_times_time() -> None:
    e = ebots([[0.0, 0.0]], [math.radians(120.0)])
    for _ in range(50):
        e.step(np.array([[0.15, 0.15]]), DT, OPEN)
    assert_allclose(e.position_m[0], 0.15 * 5.0 * np.array([math.cos(2 * math.pi / 3), math.sin(2 * math.pi / 3)]))


def test_driving_on_an_arc_follows_the_circle() -> None:
    # Wheels 0.1 and 0.2 m/s: v = 0.15 m/s, omega = 1 rad/s, radius 0.15 m about (0, 0.15).
    e = ebots([[0.0, 0.0]], [0.0])
    for _ in range(10):
        e.step(np.array([[0.1, 0.2]]), DT, OPEN)
    assert_allclose(e.position_m[0], [0.15 * math.sin(1.0), 0.15 - 0.15 * math.cos(1.0)], atol=1e-12)


def test_slip_noise_statistics() -> None:
    # Both wheels at v: forward speed v (1 + (sl + sr)/2), std v sigma / sqrt(2);
    # yaw rate v (sr - sl) / L, std v sigma sqrt(2) / L; independent wheels.
    sigma, v, n = 0.05, 0.1, 4000
    grid = np.stack(np.meshgrid(np.arange(80.0), np.arange(50.0)), axis=-1).reshape(-1, 2)
    e = DiffDriveDynamics(DiffDriveParams(slip_noise=sigma), grid, np.zeros(n), np.random.default_rng(5))
    e.step(np.full((n, 2), v), DT, OPEN)
    forward = e.velocity_mps[:, 0]
    assert forward.mean() == pytest.approx(v, rel=0.005)
    assert forward.std() == pytest.approx(v * sigma / math.sqrt(2.0), rel=0.05)
    assert e.yaw_rate_radps.std() == pytest.approx(v * sigma * math.sqrt(2.0) / WHEEL_BASE, rel=0.05)
    assert abs(np.corrcoef(forward, e.yaw_rate_radps)[0, 1]) < 0.05
    assert_allclose(e.wheel_travel_m, v * DT)  # encoders see the wheels, not the slip


def test_driving_into_a_wall_stops_at_the_radius_and_counts_contacts() -> None:
    world = room(2.0)
    e = ebots([[1.0, 1.0]], [0.0])
    for _ in range(100):
        e.step(np.array([[VMAX, VMAX]]), DT, world)
        assert wall_clearance(world, e.position_m)[0] >= EBOT_RADIUS - 1e-9
    assert_allclose(e.position_m[0], [2.0 - EBOT_RADIUS, 1.0], atol=1e-9)
    # Free travel 0.92 m at 2 cm per step: 46 steps, then pressed on the wall for the other 54
    # (55 if round-off lands the 46th step a hair inside the radius).
    assert 54 <= e.wall_contacts <= 55
    assert_allclose(e.velocity_mps[0], 0.0, atol=1e-9)


def test_no_robot_tunnels_or_sinks_into_walls_in_a_corner_with_slip() -> None:
    world = room(1.0)
    e = ebots([[0.5, 0.5], [0.3, 0.6]], [math.radians(40.0), math.radians(170.0)], DiffDriveParams(), seed=4)
    for _ in range(200):
        e.step(np.array([[VMAX, VMAX], [VMAX, 0.9 * VMAX]]), DT, world)
        assert np.all(wall_clearance(world, e.position_m) >= EBOT_RADIUS - 1e-9)
        assert np.all(world.inside_rooms(e.position_m))
    assert e.wall_contacts > 0


def test_too_long_a_step_is_refused() -> None:
    e = ebots([[0.0, 0.0]], [0.0])
    with pytest.raises(ValueError, match="tunnel"):
        e.step(np.array([[VMAX, VMAX]]), 0.3, OPEN)  # 1.5 * 0.2 * 0.3 = 9 cm > 8 cm


def test_head_on_robots_never_overlap_and_contacts_are_counted() -> None:
    e = ebots([[0.0, 0.0], [1.0, 0.0]], [0.0, math.pi])
    for _ in range(60):
        e.step(np.full((2, 2), VMAX), DT, OPEN)
        assert min_pair_distance(e.position_m) >= 2 * EBOT_RADIUS - 1e-3
    # Symmetric: they stand pressed together about the midpoint.
    assert_allclose(e.position_m, [[0.5 - EBOT_RADIUS, 0.0], [0.5 + EBOT_RADIUS, 0.0]], atol=1e-9)
    # Touching from the 22nd step (0.84 m gap closed at 4 cm per step) to the 60th.
    assert 38 <= e.robot_contacts <= 39


def test_a_crowd_converging_in_a_small_room_never_overlaps() -> None:
    world = room(1.2)
    rng = np.random.default_rng(9)
    xy = np.stack(np.meshgrid(np.linspace(0.15, 1.05, 5), np.linspace(0.15, 1.05, 5)), axis=-1).reshape(-1, 2)
    to_centre = np.arctan2(0.6 - xy[:, 1], 0.6 - xy[:, 0]) + rng.uniform(-0.3, 0.3, 25)
    e = DiffDriveDynamics(DiffDriveParams(), xy, to_centre, np.random.default_rng(10))
    for _ in range(150):
        e.step(np.full((25, 2), VMAX), DT, world)
        assert min_pair_distance(e.position_m) >= 2 * EBOT_RADIUS - 1e-3
        assert np.all(wall_clearance(world, e.position_m) >= EBOT_RADIUS - 1e-9)
    assert e.robot_contacts > 25


def test_wheel_travel_accumulates_the_clipped_commands() -> None:
    rng = np.random.default_rng(2)
    e = ebots([[0.0, 0.0], [3.0, 0.0]], [0.0, 1.0], DiffDriveParams(), seed=3)
    expected = np.zeros((2, 2))
    for _ in range(30):
        cmd = rng.uniform(-0.4, 0.4, (2, 2))
        e.step(cmd, DT, OPEN)
        expected += np.clip(cmd, -VMAX, VMAX) * DT
    assert_allclose(e.wheel_travel_m, expected, rtol=1e-12)


def test_inactive_ebots_neither_move_nor_collide() -> None:
    e = ebots([[0.0, 0.0], [0.3, 0.0]], [0.0, 0.0])
    e.active[1] = False
    for _ in range(30):
        e.step(np.full((2, 2), VMAX), DT, OPEN)
    assert_allclose(e.position_m[1], [0.3, 0.0], rtol=0, atol=0)
    assert_allclose(e.wheel_travel_m[1], 0.0)
    assert e.position_m[0, 0] == pytest.approx(0.6)  # drove through the removed robot's place
    assert e.robot_contacts == 0


def test_ebots_are_deterministic_for_a_seed() -> None:
    def final(seed: int) -> np.ndarray:
        e = ebots([[0.5, 0.5], [1.0, 1.0]], [0.0, 2.0], DiffDriveParams(), seed=seed)
        for _ in range(50):
            e.step(np.array([[0.2, 0.15], [0.1, 0.2]]), DT, room(2.0))
        return np.concatenate((e.position_m.ravel(), e.heading_rad))

    assert_allclose(final(1), final(1), rtol=0, atol=0)
    assert not np.allclose(final(1), final(2))
