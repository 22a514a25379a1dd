"""Motorboat control: the behaviour's desired velocity into steering + throttle, for a boat that cannot move sideways.

What: `MotorboatMpc` (a linear MPC, one small convex QP per call, as the buoy's
`bob_autonomy.mpc.BuoyMpc`) and `MotorboatController` (proportional, the MPC's
counted fallback and the `controller = "simple"` choice) turn a desired
velocity over ground into ArduPilot's normalised throttle (> 0 ahead) and
steering (> 0 turns clockwise, to starboard), each in [-1, 1]: what
`AutopilotSession.override` sends on RCMAP_THROTTLE / RCMAP_ROLL to a
FRAME_TYPE 0 Rover boat (SERVO1 ground steering, SERVO3 throttle).

Why: a motorboat has one thruster along its keel; to go somewhere it must turn
towards it, its yaw rate needs way on (about speed / turning radius at full
steering), and it cannot hold a spot against a drift except by pointing into it.

The references (the same for both controllers). d = v_desired - w is the
velocity wished through the water, w the drift (current plus wind drift, the
estimator's, a known disturbance): the boat must point along d and move at |d|.
  * heading error e0 = angle of d - heading, wrapped to (-pi, pi]; beyond
    +-150 deg the side of the last turn is kept (no dithering behind the stern);
  * speed through the water U = |d| cos(e0) when facing d, but never less than
    min(|d|, turn_speed) (turn_speed = `turn_speed_fraction` of the model's top
    speed) while turning: a turn needs way on, so a boat whose wish is behind it
    turns around in a circle of about its turning radius rather than stopping;
  * hold: when |d| is under `hold_speed_mps` (with hysteresis to 1.5 times that)
    the boat has nothing useful to do: throttle 0, steering 0, it drifts. This
    is how a motorboat "holds" a spot: it drifts near it, or orbits it when the
    drift is stronger than hold_speed_mps (it points into the drift and turns
    back whenever it overshoots).

The MPC (every call; the QP is built once, casadi SX):
  * state: u, speed through the water along the keel (m/s); r, yaw rate (rad/s);
    delta, heading change since now (rad). Inputs held over each step of
    `step_s` (default 0.5 s, horizon 12: 6 s): throttle tau_k, steering s_k.
  * speed: m du/dt = T tau - (c1 + c2 |u|) u, the drag linearised (Jacobian)
    at each step's speed in the previous plan (u0 on the first call or after a
    hold) and discretised exactly (zero-order hold), as BuoyMpc does at u0;
  * yaw: the steady yaw rate at steering s and speed u is -s u / R (R the
    turning radius at full steering); it is bilinear, so it is linearised about
    the previous plan's speeds and steering (u_bar_k, s_bar_k) (first-order
    Taylor: s u ~ s_bar u + s u_bar - s_bar u_bar; u_bar at least 0.1 m/s so
    the first plan from rest sees that steering turns); the yaw rate follows it
    with a first-order lag `yaw_time_constant_s`; delta integrates r
    (trapezoid). The heading dynamics know the turning limit: |yaw rate| <= u / R;
  * cost: heading_weight * sum (delta_k - e0)^2 (0 when holding) +
    speed_weight * sum ((u_k - U) / top speed)^2 + steering_weight * sum s_k^2 +
    throttle / steering change weights * sum (input_k - input_{k-1})^2;
  * constraints: throttle in [min_throttle, the available fraction and the
    throttle that holds 1.5 U + 0.2 m/s (MotorboatModel.throttle_cap)], steering
    in [-1, 1], steering change per step at most steering_slew_per_s * step_s;
  * solver: the cheapest casadi conic plugin (DAQP, see bob_autonomy.mpc).
  * failure: a solver failure, a non-finite plan or a solve over
    `time_budget_s` falls back to `MotorboatController`, counted in `fallbacks`
    and logged on "bob_autonomy.motorboat_control".
Not modelled: the sway (the hull skids outwards in a turn), reverse (throttle
>= 0 by default: a motorboat stops by its drag), the windage on the hull (the
drift estimate carries it).

Frames: x east, y north; headings rad from east, counter-clockwise.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from functools import lru_cache

import casadi as ca
import numpy as np

from bob_autonomy.mpc import _BufferedCall, _conic, _over_budget, _SolveError, default_qp_plugin
from bob_autonomy.simple_estimator import FloatArray

logger = logging.getLogger("bob_autonomy.motorboat_control")
NOMINAL_TOP_SPEED_MPS = 2.0
MIN_TURN_SPEED_MPS = 0.1  # the speed the yaw model is linearised at, at least (steering turns a boat under way)
# Below this wished speed through the water a boat holds (drifts). Absolute, not a fraction of the top speed: the
# behaviours wish speeds of about 1 m/s whatever the boat (ArduPilot's SITL motorboat goes 10 m/s and more).
HOLD_SPEED_MPS = 0.1
SPEED_CAP_FACTOR, SPEED_CAP_MARGIN_MPS = 1.5, 0.2  # MotorboatModel.throttle_cap


@dataclass(frozen=True)
class MotorboatModel:
    """The motorboat as the autonomy knows it (not the simulator's truth). Defaults: a ~1.6 m, 30 kg survey boat.

    mass_kg: surge mass with added mass, kg. linear_drag_n_per_mps, quadratic_drag_n_per_mps2: surge drag (water
    and air together), N per m/s and per (m/s)^2. max_thrust_n: full thrust ahead, N (top speed 2 m/s with these).
    turning_radius_m: turning radius at full steering, m. yaw_time_constant_s: how fast the yaw rate follows the
    steering, s. steering_slew_per_s: fastest steering change, full-scale units per s.
    """

    mass_kg: float = 33.0
    linear_drag_n_per_mps: float = 4.0
    quadratic_drag_n_per_mps2: float = 8.18
    max_thrust_n: float = 40.72
    turning_radius_m: float = 3.0
    yaw_time_constant_s: float = 0.3
    steering_slew_per_s: float = 2.0

    def __post_init__(self) -> None:
        values = (self.mass_kg, self.max_thrust_n, self.turning_radius_m, self.yaw_time_constant_s)
        if min(values) <= 0.0 or self.steering_slew_per_s <= 0.0 or not all(map(math.isfinite, values)):
            raise ValueError("mass, max thrust, turning radius, yaw time constant and steering slew must be > 0")
        if min(self.linear_drag_n_per_mps, self.quadratic_drag_n_per_mps2) < 0.0:
            raise ValueError("drag coefficients must be >= 0")
        if self.linear_drag_n_per_mps + self.quadratic_drag_n_per_mps2 <= 0.0:
            raise ValueError("the hull needs some drag")

    @classmethod
    def for_top_speed(cls, top_speed_mps: float, turning_radius_m: float | None = None) -> MotorboatModel:
        """The nominal boat with its drag rescaled to reach `top_speed_mps` at full throttle (the split between
        linear and quadratic drag at top speed kept, as BuoyModel.for_top_speed), and this turning radius (m).
        Its mass is scaled by nominal top speed / top speed, so that full throttle takes it to its top speed in
        the same time whatever that speed (1.6 s to 63 %): the autopilot tells a top speed, never a mass, and a
        fast boat is not a slow boat with a heavier hull (ArduPilot's SITL motorboat: 2 kg, 10 m/s)."""
        v = float(top_speed_mps)
        if not (math.isfinite(v) and 0.1 <= v <= 50.0):
            raise ValueError(f"top speed must be 0.1..50 m/s, got {top_speed_mps!r}")
        base = cls()
        scale = NOMINAL_TOP_SPEED_MPS / v
        radius = base.turning_radius_m if turning_radius_m is None else float(turning_radius_m)
        return cls(
            mass_kg=base.mass_kg * scale,
            linear_drag_n_per_mps=base.linear_drag_n_per_mps * scale,
            quadratic_drag_n_per_mps2=base.quadratic_drag_n_per_mps2 * scale**2,
            max_thrust_n=base.max_thrust_n,
            turning_radius_m=radius,
            yaw_time_constant_s=base.yaw_time_constant_s,
            steering_slew_per_s=base.steering_slew_per_s,
        )

    def drag_n(self, speed_mps: float) -> float:
        """Surge drag at this speed through the water, N (signed)."""
        return (self.linear_drag_n_per_mps + self.quadratic_drag_n_per_mps2 * abs(speed_mps)) * speed_mps

    def throttle_cap(self, speed_ref_mps: float) -> float:
        """The throttle that holds SPEED_CAP_FACTOR * speed_ref + SPEED_CAP_MARGIN_MPS in steady state (at most 1):
        the most the controllers give for this speed reference. It leaves room to accelerate and bounds what a
        model error can do (a boat far lighter than the model would otherwise run away in a turn)."""
        cap = self.drag_n(SPEED_CAP_FACTOR * max(speed_ref_mps, 0.0) + SPEED_CAP_MARGIN_MPS) / self.max_thrust_n
        return min(1.0, cap)

    @property
    def top_speed_mps(self) -> float:
        """Speed through the water at full throttle, m/s."""
        a, b, c = self.quadratic_drag_n_per_mps2, self.linear_drag_n_per_mps, -self.max_thrust_n
        return float((-b + math.sqrt(b * b - 4 * a * c)) / (2 * a)) if a > 0 else float(-c / b)


@dataclass(frozen=True)
class MotorboatCommand:
    """One motorboat command and how it was made.

    throttle: [-1, 1], > 0 ahead. steering: [-1, 1], > 0 turns clockwise (to starboard) going ahead.
    ok: the QP was solved and its first inputs are the command. fallback: the proportional law made it.
    solve_time_s: wall time of the QP, s (0 without one). status: "optimal", "hold", "simple", or why not.
    heading_error_rad: e0, the heading the references ask for less the heading (rad; 0 when holding).
    speed_ref_mps: U, the speed through the water they ask for, m/s.
    """

    throttle: float
    steering: float
    ok: bool
    fallback: bool
    solve_time_s: float
    status: str
    heading_error_rad: float = 0.0
    speed_ref_mps: float = 0.0


def _finite(value: object, default: float = 0.0) -> float:
    number = float(value)  # type: ignore[arg-type]
    return number if math.isfinite(number) else default


def _pair(value: object) -> tuple[float, float]:
    array = np.asarray(value, dtype=float).reshape(2)
    return _finite(array[0]), _finite(array[1])


class References:
    """Heading error and speed references from the wish, the drift and the pose (module docstring), with the
    hysteresis state of one boat (hold, side of the last big turn)."""

    def __init__(self, model: MotorboatModel, hold_speed_mps: float, turn_speed_fraction: float) -> None:
        self.model = model
        self.hold_speed_mps = float(hold_speed_mps)
        self.turn_speed_mps = float(turn_speed_fraction) * model.top_speed_mps
        self.holding = True
        self.turn_side = 0.0

    def reset(self) -> None:
        self.holding, self.turn_side = True, 0.0

    def __call__(
        self, desired: tuple[float, float], water: tuple[float, float], heading: float
    ) -> tuple[float, float, bool]:
        """(heading error e0 rad, speed reference U m/s, holding)."""
        dx, dy = desired[0] - water[0], desired[1] - water[1]
        speed = math.hypot(dx, dy)
        threshold = self.hold_speed_mps * (1.5 if self.holding else 1.0)
        self.holding = speed < threshold
        if self.holding:
            self.turn_side = 0.0
            return 0.0, 0.0, True
        error = math.remainder(math.atan2(dy, dx) - heading, 2.0 * math.pi)
        if abs(error) > math.radians(150.0) and self.turn_side != 0.0 and math.copysign(1.0, error) != self.turn_side:
            error += 2.0 * math.pi * self.turn_side  # keep turning the way we were
        if abs(error) > math.radians(30.0):
            self.turn_side = math.copysign(1.0, error)
        elif abs(error) < math.radians(10.0):
            self.turn_side = 0.0
        facing = speed * max(math.cos(error), 0.0) if abs(error) < math.pi / 2 else 0.0
        reference = min(max(facing, min(speed, self.turn_speed_mps)), self.model.top_speed_mps)
        return error, reference, False


class MotorboatController:
    """Proportional steering + throttle (the `simple` controller and the MPC's fallback).

    A yaw-rate loop: the wished yaw rate is r_d = heading_gain_per_s * e0, and steering = -(R / u') (r_d +
    yaw_damping * (r_d - r)) (clipped), u' = max(u, 0.2 m/s): the steering that gives r_d at speed u (r = -s u /
    R), plus a correction on the yaw rate measured. Throttle = drag feed-forward at the speed reference + mass *
    speed_gain_per_s * (U - u) over full thrust (clipped to [min_throttle, available]).
    """

    def __init__(
        self,
        model: MotorboatModel = MotorboatModel(),  # frozen dataclass: an immutable default
        *,
        heading_gain_per_s: float = 0.6,
        yaw_damping: float = 1.0,
        speed_gain_per_s: float = 1.0,
        hold_speed_mps: float | None = None,
        turn_speed_fraction: float = 0.25,
        min_throttle: float = 0.0,
    ) -> None:
        self.model = model
        self.heading_gain_per_s, self.yaw_damping = heading_gain_per_s, yaw_damping
        self.speed_gain_per_s, self.min_throttle = speed_gain_per_s, min_throttle
        hold = HOLD_SPEED_MPS if hold_speed_mps is None else hold_speed_mps
        self.references = References(model, hold, turn_speed_fraction)

    def law(self, error: float, reference: float, surge: float, yaw_rate: float, limit: float) -> tuple[float, float]:
        """(throttle, steering) for heading error `error` rad, speed reference and surge m/s, yaw rate rad/s and
        throttle limit."""
        m = self.model
        force = m.drag_n(reference) + m.mass_kg * self.speed_gain_per_s * (reference - surge)
        limit = min(limit, m.throttle_cap(reference))
        throttle = min(max(force / m.max_thrust_n, self.min_throttle), limit) if reference > 0 else 0.0
        wished = self.heading_gain_per_s * error
        steering = -(m.turning_radius_m / max(surge, 0.2)) * (wished + self.yaw_damping * (wished - yaw_rate))
        return throttle, min(max(steering, -1.0), 1.0)

    def command(
        self,
        desired: FloatArray,
        velocity: FloatArray,
        water: FloatArray,
        heading: float,
        yaw_rate: float = 0.0,
        limit: float = 1.0,
    ) -> MotorboatCommand:
        """The command towards `desired` (world, m/s) from the velocity over ground, the drift (m/s), the heading
        (rad) and yaw rate (rad/s); `limit`: the throttle available (a weak battery gives less)."""
        d, v, w, psi = _pair(desired), _pair(velocity), _pair(water), _finite(heading)
        error, reference, holding = self.references(d, w, psi)
        if holding:
            return MotorboatCommand(0.0, 0.0, True, False, 0.0, "hold")
        surge = math.cos(psi) * (v[0] - w[0]) + math.sin(psi) * (v[1] - w[1])
        throttle, steering = self.law(error, reference, surge, _finite(yaw_rate), max(0.0, _finite(limit)))
        return MotorboatCommand(throttle, steering, True, False, 0.0, "simple", error, reference)


class MotorboatMpc:
    """Linear MPC of a motorboat's heading and speed (see the module docstring for the formulation).

    model: the nominal MotorboatModel. step_s, horizon: the prediction's step (s) and length (steps).
    heading_weight (per rad^2), speed_weight (per (speed / top speed)^2), steering_weight, throttle_change_weight,
    steering_change_weight: cost weights per step. hold_speed_mps: below this wished speed through the water the
    boat holds (default HOLD_SPEED_MPS, 0.1 m/s); turn_speed_fraction: the least speed while turning, as a
    fraction of top speed. min_throttle: the lowest throttle (0: never astern). solver: casadi conic plugin.
    time_budget_s: a solve slower than this is discarded for the fallback, s.

    Attributes: solves, fallbacks (counts), last_plan ((horizon, 2) throttle and steering of the last QP, or None).
    """

    def __init__(
        self,
        model: MotorboatModel = MotorboatModel(),  # frozen dataclass: an immutable default
        step_s: float = 0.5,
        horizon: int = 12,
        heading_weight: float = 1.0,
        speed_weight: float = 1.0,
        steering_weight: float = 0.01,
        throttle_change_weight: float = 0.1,
        steering_change_weight: float = 0.05,
        hold_speed_mps: float | None = None,
        turn_speed_fraction: float = 0.25,
        min_throttle: float = 0.0,
        solver: str | None = None,
        time_budget_s: float = 0.02,
    ) -> None:
        if step_s <= 0.0 or horizon < 2 or not -1.0 <= min_throttle < 1.0:
            raise ValueError("need step_s > 0, horizon >= 2 and min_throttle in [-1, 1)")
        positive = (heading_weight, speed_weight, throttle_change_weight, steering_change_weight)
        if min(positive) <= 0 or steering_weight < 0:
            raise ValueError("need heading, speed and change weights > 0 and steering_weight >= 0")
        self.model, self.step_s, self.horizon = model, float(step_s), int(horizon)
        self.weights = (heading_weight, speed_weight, steering_weight, throttle_change_weight, steering_change_weight)
        self.min_throttle = float(min_throttle)
        self.solver = solver or default_qp_plugin()
        self.time_budget_s = float(time_budget_s)
        self.fallback = MotorboatController(
            model, hold_speed_mps=hold_speed_mps, turn_speed_fraction=turn_speed_fraction, min_throttle=min_throttle
        )
        self.references = self.fallback.references
        self.solves = 0
        self.fallbacks = 0
        self.last_plan: FloatArray | None = None
        self._previous = (0.0, 0.0)  # (throttle, steering) last returned
        self._bar = np.zeros((self.horizon, 2))  # the linearisation point (speed, steering) per step
        self._bounds_limit = math.nan
        # The QP is formulated and its casadi Functions built once per boat model and tuning (cached: a fleet of
        # identical boats shares them); each controller has its own buffers.
        self.problem, data, conic, constraint_values, self._speeds = _qp_functions(
            model, self.step_s, self.horizon, self.weights, self.solver
        )
        self._data = _BufferedCall(data)
        self._qp = _BufferedCall(conic, self._data.outputs)
        self._qp.inputs["a"][:] = constraint_values
        step = self.model.steering_slew_per_s * self.step_s
        self._qp.inputs["lba"][:] = -step
        self._qp.inputs["uba"][:] = step
        self._solve_qp(0.0, 0.0, 0.5, 1.0, 1.0, 1.0)  # warm-up: the first real call is not the slow one
        self.reset()

    def reset(self) -> None:
        """Forget the previous command and plan (the boat is idle)."""
        self._previous = (0.0, 0.0)
        self._bar = np.zeros((self.horizon, 2))
        self.last_plan = None
        self.references.reset()

    # ------------------------------------------------------------------ solving

    def _solve_qp(
        self, u0: float, r0: float, target: float, reference: float, heading_on: float, limit: float
    ) -> FloatArray:
        """(horizon, 2) plan of (throttle, steering); raises on a solver failure."""
        n = self.horizon
        data, qp, out = self._data.inputs["p"], self._qp.inputs, self._qp.outputs
        data[:7] = (u0, r0, target, reference, heading_on, *self._previous)
        data[7 : 7 + n] = self._bar[:, 0]
        data[7 + n :] = self._bar[:, 1]
        self._data()
        lbx, ubx = qp["lbx"], qp["ubx"]
        if limit != self._bounds_limit:
            lbx[:n], ubx[:n] = min(self.min_throttle, limit), limit
            lbx[n:], ubx[n:] = -1.0, 1.0
            self._bounds_limit = limit
        step = self.model.steering_slew_per_s * self.step_s
        lbx[n], ubx[n] = max(-1.0, self._previous[1] - step), min(1.0, self._previous[1] + step)
        self._qp()
        stats = self._qp.stats()
        if not stats["success"]:
            raise _SolveError(f"{self.solver}: {stats.get('return_status')}")
        x = out["x"]
        return np.column_stack((x[:n], x[n:]))

    def solve(
        self,
        desired_velocity_mps: FloatArray,
        velocity_mps: FloatArray,
        water_velocity_mps: FloatArray,
        heading_rad: float,
        yaw_rate_radps: float = 0.0,
        max_throttle: float = 1.0,
    ) -> MotorboatCommand:
        """The command for one control step.

        desired_velocity_mps, velocity_mps (estimated, over ground), water_velocity_mps (drift, estimated): (2,)
        world frame, m/s (non-finite entries count as 0). heading_rad, yaw_rate_radps: estimated (non-finite: 0).
        max_throttle: the throttle available, [0, 1] (a weak battery gives less).
        """
        d, v, w = _pair(desired_velocity_mps), _pair(velocity_mps), _pair(water_velocity_mps)
        psi, r0 = _finite(heading_rad), _finite(yaw_rate_radps)
        limit = min(max(_finite(max_throttle), 0.0), 1.0)
        error, reference, holding = self.references(d, w, psi)
        u0 = math.cos(psi) * (v[0] - w[0]) + math.sin(psi) * (v[1] - w[1])
        if holding or limit <= 1e-9:
            self._previous = (0.0, self._slewed(0.0))
            self.last_plan = None
            return MotorboatCommand(0.0, self._previous[1], True, False, 0.0, "hold")
        limit = min(limit, self.model.throttle_cap(reference))
        self.solves += 1
        ok, fallback, status = True, False, "optimal"
        if self.last_plan is None:  # no plan to linearise about: the speed now, steering straight
            self._bar[:] = (u0, 0.0)
        start = time.perf_counter()
        try:
            plan = self._solve_qp(u0, r0, error, reference, 1.0, limit)
            elapsed = time.perf_counter() - start
            if not np.isfinite(plan).all():
                raise _SolveError("non-finite solution")
            if elapsed > self.time_budget_s:
                raise _SolveError(_over_budget(elapsed, self.time_budget_s))
            throttle, steering = float(plan[0, 0]), float(plan[0, 1])
            self.last_plan = plan
            self._bar[:, 0] = np.asarray(self._speeds(plan[:, 0], u0), dtype=float).ravel()
            self._bar[:, 1] = plan[:, 1]
        except Exception as error_:  # any failure of the solve: the boat still gets a command
            elapsed = time.perf_counter() - start
            ok, fallback = False, True
            status = f"fallback: {type(error_).__name__}: {error_}"
            self.fallbacks += 1
            self.last_plan = None
            logger.warning("motorboat MPC fallback #%d: %s", self.fallbacks, status)
            throttle, steering = self.fallback.law(error, reference, u0, r0, limit)
        throttle = min(max(throttle, min(self.min_throttle, limit)), limit)
        steering = self._slewed(min(max(steering, -1.0), 1.0))
        self._previous = (throttle, steering)
        return MotorboatCommand(throttle, steering, ok, fallback, elapsed, status, error, reference)

    def _slewed(self, steering: float) -> float:
        """`steering` moved at most one step's slew from the previous command."""
        step = self.model.steering_slew_per_s * self.step_s
        return min(max(steering, self._previous[1] - step), self._previous[1] + step)


def _formulate(model: MotorboatModel, step_s: float, horizon: int, weights: tuple[float, ...]) -> dict[str, ca.SX]:
    """The QP in casadi SX: z (throttles, then steerings), p (module docstring), cost f, change rows g."""
    m, n, h = model, horizon, step_s
    w_heading, w_speed, w_steer, w_dthrottle, w_dsteer = weights
    p = ca.SX.sym("p", 7 + 2 * n)
    u0, r0, target, reference, heading_on, throttle_prev, steer_prev = (p[i] for i in range(7))
    u_bar, s_bar = p[7 : 7 + n], p[7 + n : 7 + 2 * n]
    z = ca.SX.sym("z", 2 * n)
    throttle, steer = z[:n], z[n:]
    c1, c2, mass = m.linear_drag_n_per_mps, m.quadratic_drag_n_per_mps2, m.mass_kg
    lag = math.exp(-h / m.yaw_time_constant_s)
    top = m.top_speed_mps
    cost, u, r, delta = 0, u0, r0, 0
    previous = (throttle_prev, steer_prev)
    for k in range(n):
        # Yaw rate the steering asks for at the speed of the step's start, linearised about the plan.
        bar = ca.fmax(u_bar[k], MIN_TURN_SPEED_MPS)
        r_steady = -(s_bar[k] * u + steer[k] * bar - s_bar[k] * bar) / m.turning_radius_m
        r_next = lag * r + (1.0 - lag) * r_steady
        delta = delta + 0.5 * h * (r + r_next)
        # Speed: drag linearised (Jacobian) at the plan's speed for this step, exact zero-order hold.
        speed = ca.sqrt(u_bar[k] ** 2 + 1e-12)
        jac = c1 + 2.0 * c2 * speed
        x = jac * h / mass
        a = ca.exp(-x)
        b = ca.if_else(x < 1e-9, h / mass, (1.0 - a) / jac)
        u = a * u + b * (m.max_thrust_n * throttle[k] + c2 * u_bar[k] * speed)
        r = r_next
        cost += w_heading * heading_on * (delta - target) ** 2 + w_speed * ((u - reference) / top) ** 2
        cost += w_steer * steer[k] ** 2
        cost += w_dthrottle * (throttle[k] - previous[0]) ** 2 + w_dsteer * (steer[k] - previous[1]) ** 2
        previous = (throttle[k], steer[k])
    return {"x": z, "p": p, "f": cost, "g": steer[1:] - steer[:-1]}


def _predicted_speeds(model: MotorboatModel, step_s: float, z: ca.SX, u0: ca.SX) -> ca.SX:
    """Speeds through the water the nonlinear surge model predicts for the throttle plan z, m/s (5 Euler
    sub-steps per step)."""
    m, sub = model, 5
    u, out = u0, []
    for k in range(z.shape[0]):
        for _ in range(sub):
            drag = (m.linear_drag_n_per_mps + m.quadratic_drag_n_per_mps2 * ca.fabs(u)) * u
            u = u + (step_s / sub) * (m.max_thrust_n * z[k] - drag) / m.mass_kg
        out.append(u)
    return ca.vertcat(*out)


@lru_cache(maxsize=32)
def _qp_functions(
    model: MotorboatModel, step_s: float, horizon: int, weights: tuple[float, ...], solver: str
) -> tuple[dict[str, ca.SX], ca.Function, ca.Function, FloatArray, ca.Function]:
    """(problem, QP data Function p -> (h, g), conic solver, constraint matrix nonzeros, plan speeds Function)."""
    problem = _formulate(model, step_s, horizon, weights)
    z, p, cost, g = problem["x"], problem["p"], problem["f"], problem["g"]
    hessian = ca.hessian(cost, z)[0]
    gradient = ca.substitute(ca.gradient(cost, z), z, ca.DM.zeros(z.shape[0]))
    constraints = ca.jacobian(g, z)
    values = np.array(ca.evalf(constraints).nonzeros(), dtype=float)
    data = ca.Function("motorboat_mpc_qp_data", [p], [hessian, gradient], ["p"], ["h", "g"], {"cse": True})
    conic = _conic("motorboat_mpc_qp", solver, hessian.sparsity(), constraints.sparsity())
    throttles, u0 = ca.SX.sym("throttles", horizon), ca.SX.sym("u0")
    speeds = ca.Function("motorboat_speeds", [throttles, u0], [_predicted_speeds(model, step_s, throttles, u0)])
    return problem, data, conic, values, speeds
