"""Motorboat dynamics for the full-stack SITL: one thruster, steering by rudder or steerable drive, no sideways thrust.

What: a 3-DOF (surge, sway, yaw) model of a small motorboat, vectorized over N
boats, beside `sitl.vehicles.dynamics.BuoyDynamics`: the same water (surface current
plus wind-driven drift), windage and random yaw torque as the buoy, but a hull
that slides easily along its keel and hardly sideways, one thruster along the
keel and a yaw moment from the steering. It is the commonest boat a field team
owns (any ArduPilot Rover boat with FRAME_TYPE 0: SERVO1 ground steering,
SERVO3 throttle), and it cannot move sideways: to go somewhere it must turn
towards it, and it cannot stop in place against a drift without pointing into it.

Why: the autonomy's motorboat controller (`bob_autonomy.control.motorboat_control`) must
cope with what a real boat does: a top speed, a turning radius, a yaw rate
that needs forward speed (rudder) or thrust (steerable drive), a hull that
skids outwards in a turn, a drift it can only fight by pointing into it.

Commands: (throttle, steering) per boat, each in [-1, 1], as ArduPilot's
throttle (SERVO function 70) and ground steering (function 26) outputs:
throttle > 0 forward (reverse gives `reverse_thrust_fraction` of full thrust),
steering > 0 turns the boat clockwise (to starboard, right) when going ahead.

Model (body frame x forward, y left; velocities relative to the surface water
u_w = current + wind_drift_factor * wind, as the buoy's):
    m_u du/dt = X + m_v v r       m_v dv/dt = Y - m_u u r       I dr/dt = N
with m_u, m_v the masses with the surge and sway added masses (the Coriolis
terms make a turn push the hull outwards); X = thrust along the keel - surge
drag (c1u + c2u |u|) u + windage; Y = the steering's side force at the stern
- sway drag (c1v + c2v |v|) v + windage; N = -lever * (side force at the stern)
- c_r (|u| + u_c) r (yaw damping grows with the speed, as the hull's lift does; u_c = `yaw_damping_floor_fraction`
of top speed damps it at rest) + a random torque (a first-order Gauss-Markov process, as the
buoy's). Windage is 0.5 rho Cd A |w - V| (w - V) on the air velocity relative to
the hull, w the wind and V the velocity over ground (isotropic, as the buoy's).
The steering acts through the actual steering angle, which follows the command
at most `steering_slew_per_s` (full lock to lock in 2 / slew s):
  * "outboard" (steerable drive): the thrust T turns by delta = steering *
    max_steer_angle; side force T sin(delta) at the stern, T cos(delta) along the
    keel. It turns the boat at any speed, as long as there is thrust;
  * "rudder": the thrust stays along the keel; the rudder's side force is
    C_r u |u| sin(delta), C_r = T_max / top_speed^2 (the outboard's side force at
    top speed). No way, no steering; going astern, it reverses.
Top speed and turning radius are what a scenario gives: full thrust T_max is
the surge drag plus the windage at `top_speed_mps` in still water and air, and
the yaw damping c_r is set so that the steady turn at full throttle and full
steering has radius `turning_radius_m` (solved from the steady-state equations
with the sway, see `steady_turn`). With the damping growing with the speed the
turning radius stays within about 20 % of that at any throttle (a rudder's
grows as the boat slows: no way on, no steering). ArduPilot's own SITL motorboat
(libraries/SITL/SIM_Sailboat.cpp, class MotorBoat) is kinematic in yaw (yaw rate
= speed / turning radius) and has no sway; this model keeps the sway, since
the skid in a turn is what the autonomy has to live with.

Numerics: per step of dt_s, sub-steps of at most max_substep_s: the steering
slews; the drags are integrated implicitly with their coefficients frozen
at the sub-step start (u' = (u + h F / m) / (1 + h c / m): stable however stiff
the sway drag), the Coriolis terms and the forces explicitly; heading and
position with the new rates (semi-implicit Euler). Sensors take the mean
world-frame acceleration over the step, as for the buoy.

Frames: x east, y north (m); headings rad from east, counter-clockwise, wrapped
to (-pi, pi]. All randomness comes from the numpy Generator passed in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np
from scipy.optimize import brentq, fsolve

from sitl.vehicles.dynamics import FloatArray, _init_planar_state, _norm, wrap_angle

STEERING_KINDS = ("outboard", "rudder")
MAX_TURN_ACCEL_MPS2 = 4.0  # lateral acceleration of the hardest turn at top speed, ~0.4 g


@dataclass(frozen=True)
class MotorboatParams:
    """Physical parameters of one motorboat (SI units; defaults for a ~1.6 m, 30 kg survey boat).

    top_speed_mps: speed through still water, in still air, at full throttle, m/s (sets the full thrust).
    turning_radius_m: radius of the steady turn at full throttle and full steering, m (sets the yaw damping).
    steering: "outboard" (steerable drive) or "rudder" (module docstring).
    mass_kg: dry mass, kg. surge_added_mass_kg, sway_added_mass_kg: hydrodynamic added masses, kg.
    yaw_inertia_kgm2: yaw moment of inertia including added inertia, kg m^2.
    surge_linear_drag_n_per_mps, surge_quadratic_drag_n_per_mps2: surge drag c1u (N per m/s), c2u (N per (m/s)^2).
    sway_linear_drag_n_per_mps, sway_quadratic_drag_n_per_mps2: sway drag c1v, c2v (a keel: far above surge).
    lever_m: distance from the centre of the hull to the thruster / rudder at the stern, m.
    max_steer_angle_deg: the steering angle at full steering, deg.
    steering_slew_per_s: fastest change of the actual steering, full-scale units per s.
    reverse_thrust_fraction: thrust astern at full reverse throttle as a fraction of the thrust ahead.
    air_density_kgpm3, windage_area_m2, air_drag_coefficient: windage 0.5 rho Cd A.
    wind_drift_factor: the wind-driven surface current as a fraction of the wind (as the buoy's).
    yaw_torque_std_nm, yaw_torque_time_constant_s: the random yaw torque (std N m, correlation time s).
    yaw_damping_floor_fraction: u_c / top speed, the yaw damping at rest (module docstring).
    max_substep_s: longest integration sub-step, s.
    """

    top_speed_mps: float = 2.0
    turning_radius_m: float = 3.0
    steering: str = "outboard"
    mass_kg: float = 30.0
    surge_added_mass_kg: float = 3.0
    sway_added_mass_kg: float = 25.0
    yaw_inertia_kgm2: float = 8.0
    surge_linear_drag_n_per_mps: float = 4.0
    surge_quadratic_drag_n_per_mps2: float = 8.0
    sway_linear_drag_n_per_mps: float = 40.0
    sway_quadratic_drag_n_per_mps2: float = 150.0
    lever_m: float = 0.75
    max_steer_angle_deg: float = 30.0
    steering_slew_per_s: float = 2.0
    reverse_thrust_fraction: float = 0.5
    air_density_kgpm3: float = 1.225
    windage_area_m2: float = 0.3
    air_drag_coefficient: float = 1.0
    wind_drift_factor: float = 0.03
    yaw_torque_std_nm: float = 0.1
    yaw_torque_time_constant_s: float = 5.0
    yaw_damping_floor_fraction: float = 0.1
    max_substep_s: float = 0.02

    def __post_init__(self) -> None:
        if self.steering not in STEERING_KINDS:
            raise ValueError(f"steering must be one of {STEERING_KINDS}, got {self.steering!r}")
        if not (0.1 <= self.top_speed_mps <= 30.0):
            raise ValueError(f"top_speed_mps must be 0.1..30 m/s, got {self.top_speed_mps!r}")
        if not (0.3 <= self.turning_radius_m <= 500.0):
            raise ValueError(f"turning_radius_m must be 0.3..500 m, got {self.turning_radius_m!r}")
        if self.top_speed_mps**2 / self.turning_radius_m > MAX_TURN_ACCEL_MPS2:
            least = self.top_speed_mps**2 / MAX_TURN_ACCEL_MPS2
            raise ValueError(
                f"turning radius {self.turning_radius_m:g} m at top speed {self.top_speed_mps:g} m/s would pull "
                f"{self.top_speed_mps**2 / self.turning_radius_m:.1f} m/s^2; a small hull turns at most "
                f"{MAX_TURN_ACCEL_MPS2:g} m/s^2 (0.4 g): give turning_radius_m >= {least:.2f} m"
            )
        positive = (
            self.mass_kg, self.yaw_inertia_kgm2, self.lever_m, self.steering_slew_per_s, self.max_substep_s,
            self.yaw_torque_time_constant_s, self.sway_linear_drag_n_per_mps + self.sway_quadratic_drag_n_per_mps2,
            self.surge_linear_drag_n_per_mps + self.surge_quadratic_drag_n_per_mps2,
        )  # fmt: skip
        if min(positive) <= 0.0:
            raise ValueError("masses, inertia, lever, slew, sub-step, time constant and drags must be > 0")
        if not (0.0 < self.max_steer_angle_deg < 90.0) or not (0.0 <= self.reverse_thrust_fraction <= 1.0):
            raise ValueError("max_steer_angle_deg must be in (0, 90) and reverse_thrust_fraction in [0, 1]")

    @property
    def surge_mass_kg(self) -> float:
        return self.mass_kg + self.surge_added_mass_kg

    @property
    def sway_mass_kg(self) -> float:
        return self.mass_kg + self.sway_added_mass_kg

    @property
    def air_drag_n_per_mps2(self) -> float:
        """0.5 rho Cd A, N per (m/s)^2 of air velocity relative to the hull."""
        return 0.5 * self.air_density_kgpm3 * self.air_drag_coefficient * self.windage_area_m2

    @property
    def max_thrust_n(self) -> float:
        """Full thrust ahead, N: surge drag plus windage at top speed in still water and still air."""
        v = self.top_speed_mps
        c2 = self.surge_quadratic_drag_n_per_mps2 + self.air_drag_n_per_mps2
        return self.surge_linear_drag_n_per_mps * v + c2 * v * v

    @property
    def rudder_coefficient(self) -> float:
        """C_r, N per (m/s)^2: the rudder's side force at full lock is C_r u^2 sin(max angle)."""
        return self.max_thrust_n / self.top_speed_mps**2

    @property
    def yaw_damping_floor_mps(self) -> float:
        """u_c, m/s: the yaw damping is c_r (|u| + u_c) r."""
        return self.yaw_damping_floor_fraction * self.top_speed_mps

    @property
    def yaw_damping_coefficient(self) -> float:
        """c_r, N m per rad/s per m/s, that gives `turning_radius_m` (see `steady_turn`)."""
        return _yaw_damping(self)


def _side_force(p: MotorboatParams, thrust: float, u: float, steer: float) -> tuple[float, float]:
    """(force along the keel, side force at the stern), N, for thrust N, surge u m/s, steering in [-1, 1]."""
    delta = math.radians(p.max_steer_angle_deg) * steer
    if p.steering == "outboard":
        return thrust * math.cos(delta), thrust * math.sin(delta)
    return thrust, p.rudder_coefficient * u * abs(u) * math.sin(delta)


def steady_turn(p: MotorboatParams, yaw_rate_radps: float) -> tuple[float, float]:
    """(surge, sway) m/s of the steady motion at full throttle and full right steering turning at `yaw_rate_radps`
    (its magnitude; clockwise), from X + m_v v r = 0 and Y - m_u u r = 0 with the yaw rate given."""
    r = -abs(yaw_rate_radps)
    thrust = p.max_thrust_n

    def equations(state: FloatArray) -> list[float]:
        u, v = state
        along, side = _side_force(p, thrust, u, 1.0)
        x = along - (p.surge_linear_drag_n_per_mps + p.surge_quadratic_drag_n_per_mps2 * abs(u)) * u
        y = side - (p.sway_linear_drag_n_per_mps + p.sway_quadratic_drag_n_per_mps2 * abs(v)) * v
        return [x + p.sway_mass_kg * v * r, y - p.surge_mass_kg * u * r]

    u, v = fsolve(equations, [p.top_speed_mps, 0.0], xtol=1e-12)
    return float(u), float(v)


@lru_cache(maxsize=256)
def _yaw_damping(p: MotorboatParams) -> float:
    """Solve |r| = speed(r) / R for the steady full-steering turn; the yaw balance lever * side force =
    c_r (|u| + u_c) |r| of that steady motion then gives c_r."""
    radius = p.turning_radius_m

    def gap(rate: float) -> float:
        u, v = steady_turn(p, rate)
        return math.hypot(u, v) - radius * rate

    top = 2.0 * p.top_speed_mps / radius
    rate = brentq(gap, 1e-6, top, xtol=1e-12)
    u, _ = steady_turn(p, rate)
    _, side = _side_force(p, p.max_thrust_n, u, 1.0)
    return p.lever_m * abs(side) / (rate * (abs(u) + p.yaw_damping_floor_mps))


def params_for(top_speed_mps: float, turning_radius_m: float, steering: str = "outboard") -> MotorboatParams:
    """The default hull with this top speed (m/s), turning radius (m) and steering."""
    return replace(MotorboatParams(), top_speed_mps=top_speed_mps, turning_radius_m=turning_radius_m, steering=steering)


class MotorboatDynamics:
    """N motorboats, each with its own parameters (see the module docstring).

    params: one MotorboatParams per boat (or one for all); position (N, 2) m; heading (N,) rad; rng: draws the
    yaw disturbance torque.

    State (world frame unless said): position_m (N, 2), velocity_mps (N, 2) over ground, heading_rad (N,),
    yaw_rate_radps (N,), steering (N,) actual steering in [-1, 1], thrust_n (N,) actual thrust along the
    propeller, acceleration_mps2 (N, 2) mean over the last step, active (N,) bool: inactive boats do not move.
    """

    def __init__(
        self,
        params: MotorboatParams | list[MotorboatParams],
        position: FloatArray,
        heading: FloatArray,
        rng: np.random.Generator,
    ) -> None:
        n = np.asarray(position, dtype=float).reshape(-1, 2).shape[0]
        each = [params] * n if isinstance(params, MotorboatParams) else list(params)
        if len(each) != n:
            raise ValueError(f"{len(each)} parameter sets for {n} boats")
        _init_planar_state(self, each, position, heading, rng)
        self.boat_params = each

        def column(name: str) -> FloatArray:
            return np.array([getattr(p, name) for p in each], dtype=float)

        self.m_u, self.m_v, self.inertia = column("surge_mass_kg"), column("sway_mass_kg"), column("yaw_inertia_kgm2")
        self.c1u, self.c2u = column("surge_linear_drag_n_per_mps"), column("surge_quadratic_drag_n_per_mps2")
        self.c1v, self.c2v = column("sway_linear_drag_n_per_mps"), column("sway_quadratic_drag_n_per_mps2")
        self.yaw_damping, self.yaw_floor = column("yaw_damping_coefficient"), column("yaw_damping_floor_mps")
        self.lever, self.max_delta = column("lever_m"), np.radians(column("max_steer_angle_deg"))
        self.slew, self.reverse = column("steering_slew_per_s"), column("reverse_thrust_fraction")
        self.air, self.drift_factor = column("air_drag_n_per_mps2"), column("wind_drift_factor")
        self.nominal_thrust_n, self.rudder = column("max_thrust_n"), column("rudder_coefficient")
        self.outboard = np.array([p.steering == "outboard" for p in each])
        self.torque_std, self.torque_tau = column("yaw_torque_std_nm"), column("yaw_torque_time_constant_s")
        self.max_substep_s = min(p.max_substep_s for p in each) if each else 0.02
        self.steering = np.zeros(n)
        self.thrust_n = np.zeros(n)
        self.acceleration_mps2 = np.zeros((n, 2))
        self.active = np.ones(n, dtype=bool)
        self.yaw_torque_nm = self.torque_std * rng.standard_normal(n)

    def __len__(self) -> int:
        return int(self.position_m.shape[0])

    def step(
        self,
        command: FloatArray,
        dt_s: float,
        wind_mps: FloatArray | None = None,
        current_mps: FloatArray | None = None,
        thrust_fraction: FloatArray | float = 1.0,
    ) -> FloatArray:
        """Advance every boat by dt_s s; return acceleration_mps2 (N, 2) over the step.

        command: (N, 2) throttle and steering, each in [-1, 1] (clipped; non-finite -> 0). wind_mps, current_mps:
        (N, 2) over ground at each boat, m/s, held over the step. thrust_fraction: (N,) or scalar, the thrust
        available as a fraction of full (a weak battery gives less).
        """
        n = len(self)
        if dt_s <= 0.0:
            raise ValueError("dt_s must be > 0")
        cmd = np.clip(np.nan_to_num(np.asarray(command, dtype=float).reshape(n, 2)), -1.0, 1.0)
        wind = np.zeros((n, 2)) if wind_mps is None else np.asarray(wind_mps, dtype=float).reshape(n, 2)
        current = np.zeros((n, 2)) if current_mps is None else np.asarray(current_mps, dtype=float).reshape(n, 2)
        fraction = np.broadcast_to(np.asarray(thrust_fraction, dtype=float), (n,))
        throttle = cmd[:, 0]
        thrust = np.where(throttle >= 0, 1.0, self.reverse) * throttle * self.nominal_thrust_n * np.maximum(fraction, 0)

        decay = np.exp(-dt_s / self.torque_tau)
        noise = self.torque_std * np.sqrt(np.maximum(0.0, 1.0 - decay * decay))
        self.yaw_torque_nm = self.yaw_torque_nm * decay + noise * self.rng.standard_normal(n)

        a = self.active
        water = current[a] + self.drift_factor[a, None] * wind[a]
        w = wind[a]
        x, v_ground = self.position_m[a], self.velocity_mps[a]
        heading, r, steer = self.heading_rad[a], self.yaw_rate_radps[a], self.steering[a]
        target, t_a = cmd[a, 1], thrust[a]
        m_u, m_v, inertia = self.m_u[a], self.m_v[a], self.inertia[a]
        c1u, c2u, c1v, c2v = self.c1u[a], self.c2u[a], self.c1v[a], self.c2v[a]
        damping, floor, lever, max_delta = self.yaw_damping[a], self.yaw_floor[a], self.lever[a], self.max_delta[a]
        air, outboard, rudder, torque = self.air[a], self.outboard[a], self.rudder[a], self.yaw_torque_nm[a]
        v_start = v_ground.copy()

        substeps = max(1, math.ceil(dt_s / self.max_substep_s - 1e-9))
        h = dt_s / substeps
        # Loop invariants and values reused within a sub-step are computed once: the same operations on the same
        # operands, so the same bits as computing them where they are used (runs stay byte-identical).
        slew_h = self.slew[a] * h
        every_outboard = bool(outboard.all())
        c, s = np.cos(heading), np.sin(heading)
        for _ in range(substeps):
            steer = steer + np.minimum(np.maximum(target - steer, -slew_h), slew_h)
            rel = v_ground - water
            u, v = c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]
            abs_u = np.abs(u)
            to_air = w - v_ground
            air_force = (air * _norm(to_air))[:, None] * to_air
            air_x, air_y = c * air_force[:, 0] + s * air_force[:, 1], -s * air_force[:, 0] + c * air_force[:, 1]
            delta = max_delta * steer
            sin_delta = np.sin(delta)
            if every_outboard:
                along, side = t_a * np.cos(delta), t_a * sin_delta
            else:
                along = np.where(outboard, t_a * np.cos(delta), t_a)
                side = np.where(outboard, t_a * sin_delta, rudder * u * abs_u * sin_delta)
            force_x = along + air_x + m_v * v * r
            force_y = side + air_y - m_u * u * r
            moment = -lever * side + torque
            u_new = (u + h * force_x / m_u) / (1.0 + h * (c1u + c2u * abs_u) / m_u)
            v_new = (v + h * force_y / m_v) / (1.0 + h * (c1v + c2v * np.abs(v)) / m_v)
            r = (r + h * moment / inertia) / (1.0 + h * damping * (abs_u + floor) / inertia)
            heading = heading + h * r
            c, s = np.cos(heading), np.sin(heading)
            ground = np.empty_like(v_ground)
            ground[:, 0] = c * u_new - s * v_new
            ground[:, 1] = s * u_new + c * v_new
            v_ground = water + ground
            x = x + h * v_ground

        self.position_m[a], self.velocity_mps[a] = x, v_ground
        self.heading_rad[a], self.yaw_rate_radps[a], self.steering[a] = wrap_angle(heading), r, steer
        self.thrust_n = np.where(a, thrust, 0.0)
        self.acceleration_mps2 = np.zeros((n, 2))
        self.acceleration_mps2[a] = (v_ground - v_start) / dt_s
        self.velocity_mps[~a] = 0.0
        self.yaw_rate_radps[~a] = 0.0
        return self.acceleration_mps2.copy()

    def surge_sway(self) -> FloatArray:
        """(N, 2) body-frame velocity over ground (forward, left), m/s."""
        c, s = np.cos(self.heading_rad), np.sin(self.heading_rad)
        v = self.velocity_mps
        return np.column_stack((c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1]))
