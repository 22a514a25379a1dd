"""Physical bodies for the full-stack SITL: the BoB buoy and the eBot.

What: rigid-body dynamics, vectorized over N agents, that stand beside the
kinematic bodies of `sitl.vehicles.bodies` (which stay for behaviour design). The buoy
is driven by a vectored thruster against water drag, windage and drift; the
eBot is a differential drive with wheel limits, wheel slip, and contacts with
walls and with other robots.

Why: the autonomy stack under test (EKF, MPC) needs a plant with the effects it
must cope with: a thrust limit that a weak battery lowers, a thrust direction
that cannot jump, a drift from wind and current, a heading that wanders (the
compass measures it), accelerations for the IMU, wheel travel for the encoders
that differs from the ground travel (slip), and bumps.

Numerical method.
Buoy, per step of dt_s, split into sub-steps of at most `max_substep_s`:
  * thrust nozzle: its body-frame angle turns towards the commanded body angle
    by at most thrust_slew_radps * h; the thrust magnitude follows the command
    (clipped to the per-agent limit) at once; the body thrust is rotated into the
    world by the TRUE heading;
  * translation: M dv/dt = T + D_w (u_w - v) + D_a (w - v), with
    M = mass + added mass, u_w = current + wind_drift_factor * wind (surface
    water), w = wind, D_w = c1 + c2 |v - u_w| (water drag) and
    D_a = 0.5 rho Cd A |w - v| (air drag on the hull). With the coefficients
    frozen the equation is linear and is integrated exactly (an exponential
    integrator: unconditionally stable however stiff the drag, and its fixed
    point is exactly the force balance, so terminal speeds carry no
    discretization error). The coefficients are frozen at the midpoint of a
    predictor step (second order). Position integrates the same exact solution;
  * yaw: I dr/dt = -yaw_damping * r + tau, integrated exactly the same way,
    where tau is a small random disturbance torque: a first-order Gauss-Markov
    process (exact OU discretization, updated once per step) of stationary std
    yaw_torque_std_nm. The thruster acts through the centre (no yaw torque).
eBot, per step: wheel commands clipped; ground wheel speed = wheel speed *
(1 + slip), slip ~ N(0, slip_noise^2) per wheel per step (clipped to
+-max_slip); unicycle kinematics integrated exactly along the arc; then contacts
resolved by projection (walls via World.push_out_of_walls, robot pairs pushed
apart symmetrically along their line of centres, a few passes; a robot pinned
against a wall yields nothing). Robots still overlapping by more than
overlap_tolerance_m after those passes (a dense jam) stall for the step: they
stay where the step started, which was clear. Robots pressing into each other
therefore stop, as real ones do when their wheels slip.

Frames: x east, y north (m); headings in rad from east, counter-clockwise,
wrapped to (-pi, pi]. Buoy body frame: x forward along the heading, y to the
left. All randomness comes from the numpy Generator passed in.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from sitl.world.world import World

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


def wrap_angle(angle_rad: FloatArray | float) -> FloatArray:
    """Angles (rad) wrapped to (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(angle_rad, dtype=float), 2.0 * np.pi)


def _init_planar_state(body, params, position: FloatArray, heading: FloatArray, rng: np.random.Generator) -> int:
    """Set the state every planar body has (position, heading, velocity, yaw rate); return the body count."""
    body.params = params
    body.rng = rng
    body.position_m = np.array(position, dtype=float).reshape(-1, 2)
    n = body.position_m.shape[0]
    body.heading_rad = wrap_angle(np.broadcast_to(np.asarray(heading, dtype=float), (n,)).copy())
    body.velocity_mps = np.zeros((n, 2))
    body.yaw_rate_radps = np.zeros(n)
    return n


def _phi1(x: FloatArray) -> FloatArray:
    """(1 - exp(-x)) / x, with its limit 1 at x = 0 (x >= 0)."""
    small = x < 1e-4
    if not small.any():  # the usual case: the closed form alone (what np.where would pick, to the bit)
        return -np.expm1(-x) / x
    safe = np.where(small, 1.0, x)
    return np.where(small, 1.0 - x / 2.0 + x * x / 6.0, -np.expm1(-safe) / safe)


def _phi2(x: FloatArray) -> FloatArray:
    """(x - 1 + exp(-x)) / x^2, with its limit 1/2 at x = 0 (x >= 0)."""
    small = x < 1e-3
    if not small.any():
        return (x + np.expm1(-x)) / (x * x)
    safe = np.where(small, 1.0, x)
    return np.where(small, 0.5 - x / 6.0 + x * x / 24.0, (safe + np.expm1(-safe)) / (safe * safe))


def _norm(v: FloatArray) -> FloatArray:
    """(N,) Euclidean norms of the rows of (N, 2)."""
    return np.hypot(v[:, 0], v[:, 1])


# --------------------------------------------------------------------------- buoy


@dataclass(frozen=True)
class BuoyParams:
    """Physical parameters of one BoB buoy (SI units; defaults for a ~25 kg buoy).

    mass_kg: dry mass, kg.
    added_mass_kg: hydrodynamic added mass for horizontal motion, kg.
    yaw_inertia_kgm2: yaw moment of inertia including added inertia, kg m^2.
    linear_drag_n_per_mps: linear water drag coefficient c1, N per m/s of
        velocity relative to the surface water.
    quadratic_drag_n_per_mps2: quadratic water drag coefficient c2, N per (m/s)^2.
    thrust_slew_radps: maximum turn rate of the thrust direction relative to the
        hull, rad/s ("near-instantaneous" in the paper: a reversal takes ~1 s).
    air_density_kgpm3: air density, kg/m^3.
    windage_area_m2: projected hull area above water, m^2.
    air_drag_coefficient: dimensionless drag coefficient Cd of that area.
    wind_drift_factor: dimensionless; the wind-driven surface current as a
        fraction of the wind velocity (the oceanographers' ~3 % rule of thumb).
    yaw_damping_nms_per_rad: yaw damping, N m per rad/s.
    yaw_torque_std_nm: stationary std of the random yaw disturbance torque, N m.
    yaw_torque_time_constant_s: correlation time of that torque, s.
    design_top_speed_mps: speed through still water, in still air, at full thrust,
        m/s; max_thrust_n is derived from it (1 m/s in the paper).
    max_substep_s: longest integration sub-step, s.
    """

    mass_kg: float = 25.0
    added_mass_kg: float = 10.0
    yaw_inertia_kgm2: float = 1.5
    linear_drag_n_per_mps: float = 5.0
    quadratic_drag_n_per_mps2: float = 40.0
    thrust_slew_radps: float = 3.0
    air_density_kgpm3: float = 1.225
    windage_area_m2: float = 0.15
    air_drag_coefficient: float = 1.0
    wind_drift_factor: float = 0.03
    yaw_damping_nms_per_rad: float = 2.0
    yaw_torque_std_nm: float = 0.05
    yaw_torque_time_constant_s: float = 5.0
    design_top_speed_mps: float = 1.0
    max_substep_s: float = 0.025

    def __post_init__(self) -> None:
        if self.mass_kg + self.added_mass_kg <= 0.0 or self.yaw_inertia_kgm2 <= 0.0:
            raise ValueError("mass and yaw inertia must be > 0")
        if min(self.linear_drag_n_per_mps, self.quadratic_drag_n_per_mps2, self.yaw_damping_nms_per_rad) < 0.0:
            raise ValueError("drag and damping coefficients must be >= 0")
        if self.thrust_slew_radps <= 0.0 or self.max_substep_s <= 0.0 or self.yaw_torque_time_constant_s <= 0.0:
            raise ValueError("thrust_slew_radps, max_substep_s and yaw_torque_time_constant_s must be > 0")

    @property
    def effective_mass_kg(self) -> float:
        """Mass plus added mass, kg: the inertia against horizontal acceleration."""
        return self.mass_kg + self.added_mass_kg

    @property
    def air_drag_n_per_mps2(self) -> float:
        """0.5 rho Cd A, N per (m/s)^2 of air velocity relative to the hull."""
        return 0.5 * self.air_density_kgpm3 * self.air_drag_coefficient * self.windage_area_m2

    @property
    def max_thrust_n(self) -> float:
        """Full thrust, N: the total drag at design_top_speed_mps in still water and still air."""
        v = self.design_top_speed_mps
        return self.linear_drag_n_per_mps * v + (self.quadratic_drag_n_per_mps2 + self.air_drag_n_per_mps2) * v * v


def equivalent_drift_mps(
    params: BuoyParams,
    wind_mps: FloatArray,
    current_mps: FloatArray,
    velocity_mps: FloatArray | None = None,
) -> FloatArray:
    """The equivalent drift (N, 2), m/s over ground, from the force balance of `BuoyDynamics` (thrust aside).

    wind_mps, current_mps: (N, 2) or (2,) wind and current over ground, m/s. velocity_mps: (N, 2) or (2,) hull
    velocity over ground v, m/s, or None.

    The environment pushes a hull moving at v with E(v) = D_w(u - v) + D_a(w - v) (N), where u = current +
    wind_drift_factor * wind is the surface water, w the wind, D_w(x) = (c1 + c2 |x|) x the water drag and
    D_a(x) = 0.5 rho Cd A |x| x the windage. The equivalent drift at v is the surface-water velocity d that, by
    water drag alone, would push the hull at v just as hard: D_w(d - v) = E(v), so M dv/dt = T - D_w(v - d) holds
    exactly at v (the nominal model of `bob_autonomy`, with d for the water).

    velocity_mps None: v is the velocity over ground an unpowered buoy settles to, E(v) = 0, which is also its
    own equivalent drift (d = v). There the water drag and the windage are opposite, so v lies on the segment
    from u to w: v = u + s (w - u) / L, L = |w - u|, with s the slip through the water solving
    c1 s + c2 s^2 = ka (L - s)^2 (closed form, stable for any c2 - ka).
    """
    p = params
    wind = np.atleast_2d(np.asarray(wind_mps, dtype=float))
    current = np.atleast_2d(np.asarray(current_mps, dtype=float))
    water = current + p.wind_drift_factor * wind
    c1, c2, ka = p.linear_drag_n_per_mps, p.quadratic_drag_n_per_mps2, p.air_drag_n_per_mps2
    if velocity_mps is None:
        offset = wind - water
        length = _norm(offset)
        b = c1 + 2.0 * ka * length
        slip = 2.0 * ka * length**2 / np.maximum(b + np.sqrt(b * b + 4.0 * (c2 - ka) * ka * length**2), 1e-300)
        unit = offset / np.maximum(length, 1e-300)[:, None]
        return water + slip[:, None] * unit
    v = np.atleast_2d(np.asarray(velocity_mps, dtype=float))
    to_water, to_wind = water - v, wind - v
    force = (c1 + c2 * _norm(to_water))[:, None] * to_water + (ka * _norm(to_wind))[:, None] * to_wind
    magnitude = _norm(force)
    # |x| solving c1 |x| + c2 |x|^2 = |E| (the stable root), along E.
    relative = 2.0 * magnitude / np.maximum(c1 + np.sqrt(c1 * c1 + 4.0 * c2 * magnitude), 1e-300)
    return v + (relative / np.maximum(magnitude, 1e-300))[:, None] * force


class BuoyDynamics:
    """N buoys with vectored thrust, water drag, windage and drift (see the module docstring).

    params: BuoyParams; position: (N, 2) m; heading: (N,) rad; rng: numpy
    Generator (draws the yaw disturbance torque).

    State (world frame unless said): position_m (N, 2), velocity_mps (N, 2) over
    ground, heading_rad (N,), yaw_rate_radps (N,), thrust_n (N, 2) actual thrust,
    thrust_angle_body_rad (N,) nozzle direction relative to the hull,
    yaw_torque_nm (N,), acceleration_mps2 (N, 2) mean over the last step,
    active (N,) bool: inactive buoys do not move at all.
    """

    def __init__(self, params: BuoyParams, position: FloatArray, heading: FloatArray, rng: np.random.Generator) -> None:
        n = _init_planar_state(self, params, position, heading, rng)
        self.thrust_n = np.zeros((n, 2))
        self.thrust_angle_body_rad = np.zeros(n)
        self.acceleration_mps2 = np.zeros((n, 2))
        self.active = np.ones(n, dtype=bool)
        self.yaw_torque_nm = params.yaw_torque_std_nm * rng.standard_normal(n)

    def __len__(self) -> int:
        return int(self.position_m.shape[0])

    def step(
        self,
        thrust_cmd_body_n: FloatArray,
        dt_s: float,
        wind_mps: FloatArray | None = None,
        current_mps: FloatArray | None = None,
        max_thrust_n: FloatArray | float | None = None,
    ) -> FloatArray:
        """Advance every buoy by dt_s seconds; return acceleration_mps2 (N, 2) over the step.

        thrust_cmd_body_n: (N, 2) commanded thrust in the BODY frame, N (x forward,
            y left); its magnitude is clipped to max_thrust_n.
        wind_mps, current_mps: (N, 2) wind and current over ground at each buoy,
            m/s (default: none), held constant over the step.
        max_thrust_n: (N,) or scalar per-agent thrust limit, N (a weak battery
            gives less); default params.max_thrust_n.
        """
        p = self.params
        n = len(self)
        if dt_s <= 0.0:
            raise ValueError("dt_s must be > 0")
        cmd = np.asarray(thrust_cmd_body_n, dtype=float).reshape(n, 2)
        wind = np.zeros((n, 2)) if wind_mps is None else np.asarray(wind_mps, dtype=float).reshape(n, 2)
        current = np.zeros((n, 2)) if current_mps is None else np.asarray(current_mps, dtype=float).reshape(n, 2)
        limit = np.asarray(p.max_thrust_n if max_thrust_n is None else max_thrust_n, dtype=float)
        if limit.shape != (n,):
            limit = np.broadcast_to(limit, (n,))

        cmd_mag = _norm(cmd)
        thrust_mag = np.minimum(cmd_mag, np.maximum(limit, 0.0))
        cmd_angle = np.where(cmd_mag > 1e-9, np.arctan2(cmd[:, 1], cmd[:, 0]), self.thrust_angle_body_rad)
        water = current + p.wind_drift_factor * wind  # surface water velocity over ground

        # Disturbance torque: exact OU step, held over the step.
        decay = math.exp(-dt_s / p.yaw_torque_time_constant_s)
        torque_noise = p.yaw_torque_std_nm * math.sqrt(max(0.0, 1.0 - decay * decay))
        self.yaw_torque_nm = self.yaw_torque_nm * decay + torque_noise * self.rng.standard_normal(n)

        # The active rows: a view of every row when all are active (the usual case), else a copy of some.
        act = self.active
        every = bool(act.all())
        rows = slice(None) if every else act
        c = _substeps(p, dt_s)
        nozzle, world_angles, heading, rate = _turn(
            self.thrust_angle_body_rad[rows], cmd_angle[rows], self.heading_rad[rows], self.yaw_rate_radps[rows],
            self.yaw_torque_nm[rows], c,
        )  # fmt: skip
        # The thrust over ground at every substep, (substeps, 2, M) N: the nozzle direction does not depend on the
        # translation, so the trigonometry is done once for all substeps.
        thrusts = np.empty((c.count, 2, world_angles.shape[1]))
        np.cos(world_angles, out=thrusts[:, 0])
        np.sin(world_angles, out=thrusts[:, 1])
        np.multiply(thrust_mag[rows], thrusts, out=thrusts)
        # Vectors are (2, M) (x row, y row) in the substep loop, so that the per-buoy coefficients broadcast.
        x_start, v_start = self.position_m[rows].T, self.velocity_mps[rows].T
        flow = np.empty((2, *v_start.shape))  # the surface water and the wind, m/s
        flow[0], flow[1] = water[rows].T, wind[rows].T
        x, v = _translate(x_start, v_start, thrusts, flow, c)

        accel = (v - v_start) / dt_s  # before the write-back: v_start may be a view of velocity_mps
        self.position_m[rows], self.velocity_mps[rows] = x.T, v.T
        self.heading_rad[rows], self.yaw_rate_radps[rows] = wrap_angle(heading), rate
        self.thrust_angle_body_rad[rows] = wrap_angle(nozzle)
        self.thrust_n[rows] = thrusts[-1].T
        self.acceleration_mps2 = np.zeros((n, 2))
        self.acceleration_mps2[rows] = accel.T
        if not every:
            idle = ~act
            self.velocity_mps[idle] = 0.0
            self.yaw_rate_radps[idle] = 0.0
            self.thrust_n[idle] = 0.0
        return self.acceleration_mps2.copy()


class _Substeps(NamedTuple):
    """What a buoy step needs that depends on the parameters and the step length alone.

    The factors are read-only 0-d float64 arrays: numpy combines an array with one faster than with a Python float
    (no conversion at each call), with the same float64 arithmetic.
    """

    count: int  # substeps per step
    h: FloatArray  # substep length, s
    h2: FloatArray  # h^2, s^2
    half: FloatArray  # 0.5
    slew: FloatArray  # largest nozzle turn per substep, rad
    neg_slew: FloatArray  # -slew, rad
    pi: FloatArray  # pi
    two_pi: FloatArray  # 2 pi
    damping: FloatArray  # yaw damping, N m s/rad
    inertia: FloatArray  # yaw inertia, kg m^2
    yaw_phi1: FloatArray  # phi1 and phi2 of h over the yaw time constant
    yaw_phi2: FloatArray
    mass: FloatArray  # effective mass, kg
    scale: FloatArray  # (2, 1) c2 and ka: drag coefficients = scale |flow - v| + offset (N per m/s)
    offset: FloatArray  # (2, 1) c1 and 0
    closed: bool  # every drag rate h / tau is above the _phi1 / _phi2 series thresholds


@functools.lru_cache(maxsize=32)
def _substeps(p: BuoyParams, dt_s: float) -> _Substeps:
    """The substeps of a buoy step of dt_s s: at most p.max_substep_s each (see _Substeps)."""
    count = max(1, math.ceil(dt_s / p.max_substep_s - 1e-9))
    h = dt_s / count
    slew = p.thrust_slew_radps * h
    damping, inertia, mass = p.yaw_damping_nms_per_rad, p.yaw_inertia_kgm2, p.effective_mass_kg
    # The yaw integrator's factors depend on h alone (exact exponential integrator of I r' = -c r + tau).
    yaw_rate_decay = np.full(1, damping / inertia * h)
    scale = [[p.quadratic_drag_n_per_mps2], [p.air_drag_n_per_mps2]]
    offset = [[p.linear_drag_n_per_mps], [0.0]]  # ka |w - v| + 0 is ka |w - v|, never -0
    factors = [np.array(value, dtype=float) for value in (h, h * h, 0.5, slew, -slew, np.pi, 2.0 * np.pi)]
    factors += [np.array(value, dtype=float) for value in (damping, inertia)]
    factors += [_phi1(yaw_rate_decay).reshape(()), _phi2(yaw_rate_decay).reshape(())]
    factors += [np.array(value, dtype=float) for value in (mass, scale, offset)]
    for factor in factors:
        factor.setflags(write=False)  # shared by every step of this length
    # Every h / time constant is at least c1 / M h (the coefficients are c1 + c2 |.| >= c1 and ka |.| >= 0,
    # and rounding is monotonic): above the _phi1 / _phi2 series thresholds their closed forms apply to all.
    closed = p.linear_drag_n_per_mps / mass * h >= 1e-3
    return _Substeps(count, *factors, closed)


def _turn(
    nozzle: FloatArray, target: FloatArray, heading: FloatArray, rate: FloatArray, torque: FloatArray, c: _Substeps
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Slew the nozzles (M,) rad towards target and integrate the yaw under the torque (M,) N m over the substeps.

    Returns the final nozzle angles (M,) rad (unwrapped), the world thrust angle heading + nozzle at each
    substep (substeps, M) rad (the heading at the start of the substep, the nozzle after its slew), and the
    final heading (M,) rad (unwrapped) and yaw rate (M,) rad/s.
    """
    m = nozzle.shape[0]
    nozzles, changes = np.empty((c.count, m)), np.empty((c.count, m))
    rates = np.empty((c.count + 1, m))
    rates[0] = rate
    for k in range(c.count):
        turn = c.pi - np.mod(c.pi - (target - nozzle), c.two_pi)  # wrap_angle(target - nozzle)
        nozzle = np.add(nozzle, np.minimum(np.maximum(turn, c.neg_slew), c.slew), out=nozzles[k])
        # The yaw acceleration times h (rad/s), then the rate at the end of the substep.
        change = np.multiply((torque - c.damping * rate) / c.inertia, c.h, out=changes[k])
        rate = np.add(rate, change * c.yaw_phi1, out=rates[k + 1])
    # The heading does not feed back: its increments h (r + change phi2) for all substeps at once, summed in
    # order (np.add.accumulate adds row after row, as the substeps would).
    headings = np.empty((c.count + 1, m))
    headings[0] = heading
    np.multiply(c.h, rates[:-1] + changes * c.yaw_phi2, out=headings[1:])
    headings = np.add.accumulate(headings, axis=0)
    world_angles = headings[:-1] + nozzles  # the heading at the start of each substep, the slewed nozzle
    return nozzle, world_angles, headings[-1], rate


def _translate(
    x: FloatArray, v: FloatArray, thrusts: FloatArray, flow: FloatArray, c: _Substeps
) -> tuple[FloatArray, FloatArray]:
    """Integrate M v' = T + Dw (u - v) + Da (w - v), x' = v over the substeps; return x and v (2, M).

    x, v: (2, M) position m and velocity m/s; thrusts: (substeps, 2, M) N; flow: (2, 2, M) the surface water u
    and the wind w, m/s. Each substep: a predictor with the drag coefficients frozen at v gives the midpoint
    velocity, then the exact solution with the coefficients frozen there.
    """
    h, scale, offset = c.h, c.scale, c.offset
    velocities = np.empty((c.count + 1, *v.shape))  # v at the start of each substep, and at the end
    velocities[0] = v
    positions = np.empty((c.count + 1, *x.shape))  # x, then the displacement in each substep
    drifts = positions[1:]  # first the displacement beyond h v of each substep, h v added after the loop
    for k, thrust in enumerate(thrusts):
        relative = flow - v  # both frozen-coefficient solutions start from v
        coefficients = scale * np.hypot(relative[:, 0], relative[:, 1]) + offset
        accel, rate = _acceleration(thrust, relative, coefficients, c.mass, h)
        # (-e) / r == e / (-r): the closed forms divide by the -r they take the expm1 of.
        neg_rate = -rate
        phi1 = np.expm1(neg_rate) / neg_rate if c.closed else _phi1(rate)
        dv_pred = accel * (h * phi1)  # (the predictor needs no displacement)
        mid = flow - (v + c.half * dv_pred)  # the flow relative to the midpoint velocity
        coefficients = scale * np.hypot(mid[:, 0], mid[:, 1]) + offset
        accel, rate = _acceleration(thrust, relative, coefficients, c.mass, h)
        if c.closed:
            neg_rate = -rate
            decay = np.expm1(neg_rate)
            phi1, phi2 = decay / neg_rate, (rate + decay) / (rate * rate)
        else:
            phi1, phi2 = _phi1(rate), _phi2(rate)
        np.multiply(accel, c.h2 * phi2, out=drifts[k])
        v = np.add(v, accel * (h * phi1), out=velocities[k + 1])
    # dx = h v + drift for every substep at once, then x summed over the substeps in order (row after row).
    np.add(h * velocities[:-1], drifts, out=drifts)
    positions[0] = x
    return np.add.accumulate(positions, axis=0)[-1], v


def _acceleration(
    thrust: FloatArray, relative: FloatArray, coefficients: FloatArray, mass: float, h: float
) -> tuple[FloatArray, FloatArray]:
    """The acceleration (2, M) m/s^2 with frozen drag, and h over each drag time constant (M,).

    thrust: (2, M) N; relative: (2, 2, M) the water and the wind relative to the hull, m/s; coefficients:
    (2, M) the water and air drag coefficients, N per m/s; mass in kg, h in s.
    """
    terms = coefficients[:, None] * relative  # the water drag and the windage, N
    force = thrust + terms[0] + terms[1]
    rate = (coefficients[0] + coefficients[1]) / mass * h  # dimensionless: h / time constant
    return force / mass, rate


# --------------------------------------------------------------------------- eBot


@dataclass(frozen=True)
class DiffDriveParams:
    """Physical parameters of one eBot (SI units).

    wheel_base_m: distance between the wheels, m.
    max_wheel_speed_mps: wheel rim speed limit, m/s (the eBot's top speed).
    radius_m: body radius for contacts, m.
    slip_noise: dimensionless std of the per-wheel, per-step relative slip:
        ground motion = wheel motion * (1 + slip), slip clipped to +-max_slip.
    max_slip: dimensionless clip of the relative slip (keeps a step short).
    contact_iterations: most projection passes when resolving contacts.
    overlap_tolerance_m: largest robot-robot overlap left after a step, m;
        robots in a deeper jam stall at their start positions instead.
    """

    wheel_base_m: float = 0.1
    max_wheel_speed_mps: float = 0.2
    radius_m: float = 0.08
    slip_noise: float = 0.05
    max_slip: float = 0.5
    contact_iterations: int = 10
    overlap_tolerance_m: float = 5e-4

    def __post_init__(self) -> None:
        if self.wheel_base_m <= 0.0 or self.radius_m <= 0.0 or self.max_wheel_speed_mps < 0.0:
            raise ValueError("wheel_base_m and radius_m must be > 0, max_wheel_speed_mps >= 0")
        if self.slip_noise < 0.0 or not 0.0 <= self.max_slip < 1.0:
            raise ValueError("slip_noise must be >= 0 and max_slip in [0, 1)")

    def max_step_m(self, dt_s: float) -> float:
        """Longest distance (m) a robot centre can travel in dt_s s, slip included."""
        return (1.0 + self.max_slip) * self.max_wheel_speed_mps * dt_s


class DiffDriveDynamics:
    """N eBots: differential drive with wheel slip and contacts (see the module docstring).

    params: DiffDriveParams; position: (N, 2) m; heading: (N,) rad; rng: numpy
    Generator (draws the slip).

    State: position_m (N, 2), heading_rad (N,), velocity_mps (N, 2) over ground
    (after contacts), yaw_rate_radps (N,), wheel_travel_m (N, 2) cumulative
    left/right wheel rim travel as the wheels turned (before slip; what encoders
    count), acceleration_mps2 (N, 2) mean over the last step, active (N,) bool
    (an inactive robot is out of the arena: it neither moves nor collides),
    wall_contacts and robot_contacts: running counts of robots touching a wall
    and of touching robot pairs, summed over steps.

    No tunnelling: a robot starts every step at least radius_m from every wall
    and moves at most max_step_m(dt_s) (3 cm at 0.2 m/s, dt 0.1 s with the slip
    clip), which step() requires to be below radius_m (8 cm); contact pushes are
    capped at half a radius per pass and each pass ends with the walls, and a
    stalled robot goes back to its clear start, so a centre never crosses a wall
    line (this assumes the initial positions are clear of walls and each other).
    """

    def __init__(
        self, params: DiffDriveParams, position: FloatArray, heading: FloatArray, rng: np.random.Generator
    ) -> None:
        n = _init_planar_state(self, params, position, heading, rng)
        self.wheel_travel_m = np.zeros((n, 2))
        self.acceleration_mps2 = np.zeros((n, 2))
        self.active = np.ones(n, dtype=bool)
        self.wall_contacts = 0
        self.robot_contacts = 0

    def __len__(self) -> int:
        return int(self.position_m.shape[0])

    def step(self, wheel_cmd_mps: FloatArray, dt_s: float, world: World) -> FloatArray:
        """Drive every active robot for dt_s s with left/right wheel speeds (N, 2) m/s.

        Returns acceleration_mps2 (N, 2). Raises ValueError if dt_s would let a
        robot move a radius or more in one step (it could tunnel through a wall).
        """
        p = self.params
        n = len(self)
        if dt_s <= 0.0:
            raise ValueError("dt_s must be > 0")
        if p.max_step_m(dt_s) >= p.radius_m:
            raise ValueError(
                f"dt_s={dt_s} s lets a robot move {p.max_step_m(dt_s):.3f} m per step, "
                f"not below its radius {p.radius_m} m: walls could be tunnelled"
            )
        wheels = np.clip(
            np.asarray(wheel_cmd_mps, dtype=float).reshape(n, 2), -p.max_wheel_speed_mps, p.max_wheel_speed_mps
        )
        slip = np.clip(p.slip_noise * self.rng.standard_normal((n, 2)), -p.max_slip, p.max_slip)
        act = self.active
        wheels[~act] = 0.0
        ground = wheels * (1.0 + slip)

        forward = 0.5 * (ground[:, 0] + ground[:, 1])
        omega = (ground[:, 1] - ground[:, 0]) / p.wheel_base_m
        turn = omega * dt_s
        heading = self.heading_rad
        # Exact arc: chord length forward*dt*sinc(turn/2) along the mid heading.
        chord = forward * dt_s * np.sinc(turn / (2.0 * np.pi))
        mid = heading + 0.5 * turn
        start = self.position_m.copy()
        proposed = start + chord[:, None] * np.column_stack((np.cos(mid), np.sin(mid)))

        resolved = self._resolve_contacts(proposed, start, act, world)
        velocity = (resolved - start) / dt_s
        velocity[~act] = 0.0
        self.acceleration_mps2 = (velocity - self.velocity_mps) / dt_s
        self.velocity_mps = velocity
        self.position_m = resolved
        self.yaw_rate_radps = np.where(act, omega, 0.0)
        self.heading_rad = wrap_angle(np.where(act, heading + turn, heading))
        self.wheel_travel_m += wheels * dt_s
        return self.acceleration_mps2.copy()

    def _resolve_contacts(self, proposed: FloatArray, start: FloatArray, act: BoolArray, world: World) -> FloatArray:
        """Project active robots out of walls and out of each other; count the contacts.

        Walls first; then, for at most contact_iterations passes, every
        overlapping pair is pushed apart along its line of centres (half each, or
        all of it on the robot that is not pinned against a wall), each push
        capped at half a radius, followed by the walls again. Robots still
        overlapping by more than overlap_tolerance_m after that (a dense jam)
        stall: they are returned to their start positions, which were clear,
        repeatedly until no such overlap is left.
        """
        p = self.params
        rows = np.flatnonzero(act)
        positions = proposed.copy()
        positions[~act] = start[~act]
        if rows.size == 0:
            return positions
        origin = start[rows]
        radius = np.full(rows.size, p.radius_m)
        reach = 2.0 * p.radius_m
        pts, pinned = world.push_out_of_walls(positions[rows], radius)
        in_wall = pinned.copy()
        touching: set[tuple[int, int]] = set()
        for _ in range(p.contact_iterations):
            pairs, delta, dist = _overlapping_pairs(pts, reach)
            if pairs.shape[0] == 0:
                break
            touching.update(map(tuple, pairs.tolist()))
            if (reach - dist).max() <= 1e-7:
                break
            # Coincident centres: separate along an arbitrary fixed axis.
            unit = np.where(dist[:, None] > 1e-12, delta / np.maximum(dist, 1e-12)[:, None], [1.0, 0.0])
            free = (~pinned[pairs]).astype(float)  # (K, 2): a robot against a wall yields no ground
            total = free.sum(axis=1, keepdims=True)
            share = np.where(total > 0.0, free / np.maximum(total, 1.0), 0.5)
            gap = (reach - dist)[:, None] * unit
            push = np.zeros_like(pts)
            np.add.at(push, pairs[:, 0], -share[:, 0:1] * gap)
            np.add.at(push, pairs[:, 1], share[:, 1:2] * gap)
            push *= np.minimum(1.0, 0.5 * p.radius_m / np.maximum(_norm(push), 1e-12))[:, None]
            pts, contact = world.push_out_of_walls(pts + push, radius)
            pinned |= contact
            in_wall |= contact
        moved = np.ones(rows.size, dtype=bool)
        for _ in range(rows.size):
            pairs, _, dist = _overlapping_pairs(pts, reach - p.overlap_tolerance_m)
            stall = np.zeros(rows.size, dtype=bool)
            stall[pairs.ravel()] = True
            stall &= moved
            if not np.any(stall):
                break
            pts[stall] = origin[stall]
            moved &= ~stall
        self.wall_contacts += int(np.count_nonzero(in_wall))
        self.robot_contacts += len(touching)
        positions[rows] = pts
        return positions


def _overlapping_pairs(points: FloatArray, reach_m: float) -> tuple[NDArray[np.int_], FloatArray, FloatArray]:
    """Pairs (K, 2) of points closer than reach_m (beyond float round-off), their offsets (K, 2) and distances (K,)."""
    if points.shape[0] < 2:
        return np.zeros((0, 2), dtype=int), np.zeros((0, 2)), np.zeros(0)
    pairs = cKDTree(points).query_pairs(reach_m, output_type="ndarray")
    delta = points[pairs[:, 1]] - points[pairs[:, 0]]
    dist = _norm(delta)
    close = dist < reach_m - 1e-9  # a contact resolved to the exact reach is no contact
    return pairs[close], delta[close], dist[close]
