"""Kinematic bodies for behaviour design: buoys and eBots as arrays over the fleet.

Buoy: omnidirectional, velocity follows the wish within an acceleration limit,
top speed 1 m/s. eBot: differential drive (unicycle), each wheel at most
0.20 m/s, six range finders and two light sensors. Motorboat: moves only along
its heading (it cannot move sideways), turns at most at speed / turning radius
(so it needs way on to turn, and turns around in a circle rather than in
place), accelerates within a limit up to its top speed (`max_speed` and
`turning_radius` per body, 2 m/s and 3 m unless set). Dynamics with drag, wind
and current replace these behind the same interface in the physics fidelity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from sitl.norms import exceeds, limit_scale
from sitl.row_threads import ONE_THREAD, RowThreads
from sitl.world.world import FloatArray, World, ray_segment_distance

BUOY, EBOT, MOTORBOAT = 0, 1, 2
BODY_KINDS = {"buoy": BUOY, "ebot": EBOT, "motorboat": MOTORBOAT}
MOTORBOAT_TURNING_RADIUS_M = 3.0  # default turning radius at full steering
MOTORBOAT_TURN_SPEED_FRACTION = 0.25  # a motorboat whose wish is behind it turns at least at this fraction of top speed

EBOT_SONAR_ANGLES_RAD = np.radians([0.0, 60.0, 120.0, 180.0, -120.0, -60.0])
# A sonar returns the nearest echo inside its cone (about +-30 degrees), sampled by these rays.
SONAR_CONE_OFFSETS_RAD = np.radians([-27.0, -13.5, 0.0, 13.5, 27.0])  # no ray shared by two sonars
EBOT_LIGHT_ANGLES_RAD = np.radians([45.0, -45.0])  # left, right
_TURN_THRESHOLD_MPS = np.array(0.05)  # a buoy faces its velocity when faster than this, else keeps its heading


@dataclass(frozen=True)
class BodySpec:
    """Physical limits of one kind of body (SI units)."""

    max_speed_mps: float
    radius_m: float
    max_accel_mps2: float = 0.5
    wheel_base_m: float = 0.1
    max_turn_rate_radps: float = 1.5
    range_max_m: float = 1.5


BODY_SPECS = {
    BUOY: BodySpec(max_speed_mps=1.0, radius_m=0.3, max_accel_mps2=0.5, max_turn_rate_radps=1.5, range_max_m=0.0),
    EBOT: BodySpec(max_speed_mps=0.2, radius_m=0.08, wheel_base_m=0.1, range_max_m=1.5),
    MOTORBOAT: BodySpec(max_speed_mps=2.0, radius_m=0.8, max_accel_mps2=0.5, range_max_m=0.0),
}


class KinematicBodies:
    """The ground-truth state of every simulated body, stepped all at once."""

    threads: RowThreads = ONE_THREAD  # the lockstep fleet's, for the buoys' step and the move in parts

    def __init__(self, kinds: NDArray[np.int_], position: FloatArray, heading: FloatArray) -> None:
        self.kind = np.asarray(kinds, dtype=int)
        self.position = np.asarray(position, dtype=float).copy()
        self.heading = np.asarray(heading, dtype=float).copy()
        self.velocity = np.zeros_like(self.position)
        n = self.kind.shape[0]
        self.max_speed = np.array([BODY_SPECS[k].max_speed_mps for k in self.kind])
        self.radius = np.array([BODY_SPECS[k].radius_m for k in self.kind])
        self.ebots = np.flatnonzero(self.kind == EBOT)
        self.buoys = np.flatnonzero(self.kind == BUOY)
        self.motorboats = np.flatnonzero(self.kind == MOTORBOAT)
        self.turning_radius = np.full(n, MOTORBOAT_TURNING_RADIUS_M)  # m, motorboats' at full steering
        self.active = np.ones(n, dtype=bool)
        self.wall_contacts = 0
        self.robot_contacts = 0  # kinematic bodies pass through each other; physical ones count contacts

    def __len__(self) -> int:
        return int(self.kind.shape[0])

    def apply(self, wish_velocity: FloatArray, wish_heading: FloatArray, dt: float, world: World) -> None:
        """Move every active body for dt s towards its wished velocity (m/s) and heading (rad)."""
        new_velocity = np.zeros_like(self.velocity)
        new_heading = self.heading.copy()
        if self.buoys.size:
            first = int(self.buoys[0])  # rows first..first + n - 1 when the buoys are contiguous: slices, not gathers
            contiguous = int(self.buoys[-1]) - first == self.buoys.size - 1

            def buoys(lo: int, hi: int) -> None:
                b = slice(first + lo, first + hi) if contiguous else self.buoys[lo:hi]
                v, h = self._buoy_step(wish_velocity[b], wish_heading[b], self.velocity[b], self.heading[b], dt)
                new_velocity[b], new_heading[b] = v, h

            self.threads.map_rows(buoys, self.buoys.size, 2 * self.buoys.size)  # (the (n, 2) velocities)
        if self.ebots.size:
            e = self.ebots
            v, h = self._ebot_step(wish_velocity[e], wish_heading[e], self.heading[e], dt)
            new_velocity[e], new_heading[e] = v, h
        if self.motorboats.size:
            m = self.motorboats
            v, h = _motorboat_step(
                wish_velocity[m], self.velocity[m], self.heading[m], self.max_speed[m], self.turning_radius[m], dt
            )
            new_velocity[m], new_heading[m] = v, h
        new_velocity[~self.active] = 0.0
        new_heading[~self.active] = self.heading[~self.active]
        proposed, heading = np.empty_like(self.position), np.empty_like(new_heading)

        def move(lo: int, hi: int) -> None:  # (heading wrapped to [-pi, pi))
            np.add(self.position[lo:hi], new_velocity[lo:hi] * dt, out=proposed[lo:hi])
            np.subtract(np.mod(new_heading[lo:hi] + np.pi, 2 * np.pi), np.pi, out=heading[lo:hi])

        self.threads.map_rows(move, len(self), 2 * len(self))
        if world.walls.shape[0]:
            moving = self.active
            proposed[moving], contact = world.push_out_of_walls(proposed[moving], self.radius[moving])
            self.wall_contacts += int(np.count_nonzero(contact))
            new_velocity = (proposed - self.position) / dt
        self.position = proposed
        self.velocity = new_velocity
        self.heading = heading

    @staticmethod
    def _buoy_step(wish_v: FloatArray, wish_h: FloatArray, v: FloatArray, h: FloatArray, dt: float):
        spec = BODY_SPECS[BUOY]
        # Speed and acceleration limits as min(1, limit / |vector|) and the turn threshold |v| > 0.05 m/s, with
        # hypot's bits but hypot only where a vector is near its limit (sitl.norms).
        wish_v = np.nan_to_num(wish_v)
        wish_v = wish_v * limit_scale(wish_v, spec.max_speed_mps)[:, None]
        dv = wish_v - v
        dv *= limit_scale(dv, spec.max_accel_mps2 * dt)[:, None]
        new_v = v + dv
        moving = exceeds(new_v[:, 0], new_v[:, 1], _TURN_THRESHOLD_MPS, _TURN_THRESHOLD_MPS)
        target_h = np.where(np.isnan(wish_h), np.where(moving, np.arctan2(new_v[:, 1], new_v[:, 0]), h), wish_h)
        return new_v, h + _turn(target_h - h, spec.max_turn_rate_radps * dt)

    @staticmethod
    def _ebot_step(wish_v: FloatArray, wish_h: FloatArray, h: FloatArray, dt: float):
        spec = BODY_SPECS[EBOT]
        wish_v = np.nan_to_num(wish_v)
        speed = np.hypot(wish_v[:, 0], wish_v[:, 1])
        target_h = np.where(np.isnan(wish_h), np.where(speed > 1e-6, np.arctan2(wish_v[:, 1], wish_v[:, 0]), h), wish_h)
        error = np.mod(target_h - h + np.pi, 2 * np.pi) - np.pi
        # Forward speed along the heading; turn with a proportional law, then
        # scale both wheels together so that neither exceeds its limit.
        forward = np.minimum(speed, spec.max_speed_mps) * np.maximum(np.cos(error), 0.0)
        omega = 4.0 * error
        half = 0.5 * spec.wheel_base_m
        left, right = forward - omega * half, forward + omega * half
        scale = np.minimum(1.0, spec.max_speed_mps / np.maximum(np.maximum(np.abs(left), np.abs(right)), 1e-12))
        left, right = left * scale, right * scale
        forward = 0.5 * (left + right)
        omega = (right - left) / spec.wheel_base_m
        turn = np.clip(omega * dt, -np.abs(error), np.abs(error))
        mid = h + 0.5 * turn
        velocity = forward[:, None] * np.column_stack((np.cos(mid), np.sin(mid)))
        return velocity, h + turn

    def range_finders(self, rows: NDArray[np.int_], world: World) -> FloatArray:
        """(len(rows), 6, 2) offsets (m, world frame, from the centre) to what each eBot sonar hits.

        Each sonar reports the nearest wall or other active robot inside its
        cone, placed on its axis (a sonar measures range, not bearing); NaN
        where nothing is within range.
        """
        n = rows.shape[0]
        spec = BODY_SPECS[EBOT]
        k, c = EBOT_SONAR_ANGLES_RAD.shape[0], SONAR_CONE_OFFSETS_RAD.shape[0]
        axes = self.heading[rows][:, None] + EBOT_SONAR_ANGLES_RAD[None]  # (n, k)
        angles = (axes[..., None] + SONAR_CONE_OFFSETS_RAD).reshape(-1)  # (n * k * c,)
        directions = np.column_stack((np.cos(angles), np.sin(angles)))
        origins = np.repeat(self.position[rows], k * c, axis=0)
        distance = ray_segment_distance(origins, directions, world.walls)
        distance = np.minimum(distance, self._robot_hits(rows, directions, spec.range_max_m, k * c))
        distance = distance.reshape(n, k, c).min(axis=2)
        distance[distance > spec.range_max_m] = np.nan
        return np.stack((np.cos(axes), np.sin(axes)), axis=-1) * distance[..., None]

    def _robot_hits(self, rows: NDArray[np.int_], directions: FloatArray, max_range: float, k: int) -> FloatArray:
        """Distance along each of the k rays per sensing robot to the nearest other active robot's disc."""
        result = np.full(rows.shape[0] * k, np.inf)
        others = np.flatnonzero(self.active)
        if others.size < 2:
            return result
        tree = cKDTree(self.position[others])
        reach = max_range + self.radius.max()
        lists = tree.query_ball_point(self.position[rows], reach)
        sensor = np.repeat(np.arange(rows.shape[0]), [len(x) for x in lists])
        target = others[np.concatenate([np.asarray(x, dtype=int) for x in lists])] if sensor.size else sensor
        keep = target != rows[sensor]
        sensor, target = sensor[keep], target[keep]
        if sensor.size == 0:
            return result
        ray = (sensor[:, None] * k + np.arange(k)[None]).ravel()
        w = np.repeat(self.position[target] - self.position[rows[sensor]], k, axis=0)
        u = directions[ray]
        along = np.einsum("ij,ij->i", w, u)
        miss2 = np.einsum("ij,ij->i", w, w) - along**2
        r2 = np.repeat(self.radius[target], k) ** 2
        hit = (miss2 <= r2) & (along > 0.0)
        t = np.maximum(along - np.sqrt(np.maximum(r2 - miss2, 0.0)), 0.0)
        np.minimum.at(result, ray[hit], t[hit])
        return result

    def believed(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(position, heading, velocity) the agents act on: the truth, at kinematic fidelity."""
        return self.position, self.heading, self.velocity

    def environment_at(self) -> tuple[FloatArray, FloatArray]:
        """(wind, current) at each body, m/s: none at kinematic fidelity."""
        zeros = np.zeros_like(self.position)
        return zeros, zeros

    def light_sensors(self, rows: NDArray[np.int_], world: World) -> FloatArray:
        """(len(rows), 2) left and right light readings (W/m^2) of the given eBots."""
        angles = self.heading[rows][:, None] + EBOT_LIGHT_ANGLES_RAD[None]
        return world.light_readings(self.position[rows], angles)


def _motorboat_step(
    wish_v: FloatArray, v: FloatArray, h: FloatArray, top_speed: FloatArray, radius: FloatArray, dt: float
) -> tuple[FloatArray, FloatArray]:
    """Kinematic motorboats: speed along the heading towards |wish| (times the cosine of the heading error, but at
    least a turning speed while the wish is behind), within the acceleration limit and top speed; heading towards
    the wish at most at speed / turning radius. Returns the new velocities (n, 2) m/s and headings (n,) rad."""
    spec = BODY_SPECS[MOTORBOAT]
    wish_v = np.nan_to_num(wish_v)
    wished = np.minimum(np.hypot(wish_v[:, 0], wish_v[:, 1]), top_speed)
    target = np.where(wished > 1e-6, np.arctan2(wish_v[:, 1], wish_v[:, 0]), h)
    error = np.mod(target - h + np.pi, 2 * np.pi) - np.pi
    turning = np.minimum(wished, MOTORBOAT_TURN_SPEED_FRACTION * top_speed)
    speed_ref = np.maximum(wished * np.maximum(np.cos(error), 0.0), turning)
    speed = np.maximum(0.0, v[:, 0] * np.cos(h) + v[:, 1] * np.sin(h))  # along the keel: it never slides sideways
    speed = speed + np.clip(speed_ref - speed, -spec.max_accel_mps2 * dt, spec.max_accel_mps2 * dt)
    max_turn = speed / radius * dt
    turn = np.clip(error, -max_turn, max_turn)
    mid = h + 0.5 * turn
    return speed[:, None] * np.column_stack((np.cos(mid), np.sin(mid))), h + turn


def _turn(delta: FloatArray, max_step: float) -> FloatArray:
    """The wrapped angle delta (rad) limited to +-max_step."""
    wrapped = np.mod(delta + np.pi, 2 * np.pi) - np.pi
    return np.clip(wrapped, -max_step, max_step)
