"""Motorboat control: the behaviour's desired velocity into steering + throttle, for a boat that cannot move sideways.

What: `MotorboatMpc` (a linear MPC, one small convex QP per call, as the buoy's
`bob_autonomy.control.mpc.BuoyMpc`) and `MotorboatController` (proportional, the MPC's
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
    speed) while turning: a turn needs way on, so a boat whose wish is well
    behind it and fast turns around in a circle of about its turning radius;
  * astern: a wish behind the boat (more than 90 deg off the bow) no faster
    than `reverse_speed_mps` (1 m/s: the behaviours' usual top wish) is met
    going astern, the stern pointing along d (e0 measured from the stern,
    U = -|d| cos(e0)): a boat backs away from what is in front of it rather
    than circling through its neighbours, or turning across one beside it;
    a faster wish behind, a far goal, is met by turning round;
  * hold: when |d| is under `hold_speed_mps` (with hysteresis to 1.5 times that, or
    above it for HOLD_DWELL_S, 3 s, when the time is known: a steady slow wish is meant)
    the boat has nothing useful to do: steering 0, throttle 0 once its way is off
    (a boat still making way through the water faster than hold_speed_mps is
    braked, astern thrust against its surge: coasting on into the boat ahead is
    what a skipper avoids), then it drifts. This
    is how a motorboat "holds" a spot: it drifts near it, or orbits it when the
    drift is stronger than hold_speed_mps (it points into the drift and turns
    back whenever it overshoots).

The MPC (every call; the QP is built once, casadi SX):
  * state: u, speed through the water along the keel (m/s); r, yaw rate (rad/s);
    delta, heading change since now (rad). Inputs held over each step of
    `step_s` (default 0.5 s, horizon 12: 6 s): thrust fraction tau_k (the
    throttle, astern scaled by the model's reverse_thrust_fraction), steering s_k.
  * speed: m du/dt = T tau - (c1 + c2 |u|) u, the drag linearised (Jacobian)
    at each step's speed in the previous plan (u0 on the first call or after a
    hold) and discretised exactly (zero-order hold), as BuoyMpc does at u0;
  * yaw: the steady yaw rate at steering s and speed u is -s u / R (R the
    turning radius at full steering); it is bilinear, so u is taken from the
    previous plan's speeds u_bar_k (the nonlinear surge model run on its
    throttles): -s u_bar_k / R, a time-varying linear model. u_bar_k is at least
    0.1 m/s in the direction the reference goes (ahead, or astern, where the
    steering turns the other way), so a boat at rest, or pushed backwards by a
    current while it means to go ahead, still sees that steering turns it (an
    outboard turns it by its thrust); the yaw rate follows it
    with a first-order lag `yaw_time_constant_s`; delta integrates r
    (trapezoid). The heading dynamics know the turning limit: |yaw rate| <= u / R;
  * cost: heading_weight * sum (delta_k - e0)^2 +
    speed_weight * sum ((u_k - U) / top speed)^2 + steering_weight * sum s_k^2 +
    throttle / steering change weights * sum (input_k - input_{k-1})^2;
  * constraints: thrust fraction within the available throttle (astern: times
    reverse_thrust_fraction; none with min_throttle 0) and within what holds
    1.5 |U| + 0.2 m/s either way (MotorboatModel.throttle_cap), steering
    in [-1, 1], steering change per step at most steering_slew_per_s * step_s;
  * solver: the cheapest casadi conic plugin (DAQP, see bob_autonomy.control.mpc).
  * failure: a solver failure, a non-finite plan or a solve over
    `time_budget_s` falls back to `MotorboatController`, counted in `fallbacks`
    and logged on "bob_autonomy.control.motorboat_control".
Not modelled: the sway (the hull skids outwards in a turn), the windage on the
hull (the drift estimate carries it).

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

from bob_autonomy.control.qp import _BufferedCall, _conic, _cpu_over_budget, _SolveError, default_qp_plugin
from bob_autonomy.core.arrays import FloatArray

logger = logging.getLogger("bob_autonomy.control.motorboat_control")
NOMINAL_TOP_SPEED_MPS = 2.0
MIN_TURN_SPEED_MPS = 0.1  # the speed the yaw model is linearised at, at least (steering turns a boat under way)
# Below this wished speed through the water a boat holds (drifts). Absolute, not a fraction of the top speed: the
# behaviours wish speeds of about 1 m/s whatever the boat (ArduPilot's SITL motorboat goes 10 m/s and more).
# 0.2 m/s: in a crowd of boats (leader-follower-motorboats) the wishes of a settled group churn at 0.1-0.2 m/s; a boat
# that answers them turns on its turning circle through its neighbours. Holding there (0.1 m/s) left 0.1-0.5 m
# between boats; with 0.2 (and the two choices below) about 1 m.
HOLD_SPEED_MPS = 0.2
HOLD_HYSTERESIS = 1.5  # a holding boat gets under way again above this times hold_speed_mps (1.25: closer calls)
# ... or once the wish has stayed above hold_speed_mps for this long, s (when the caller gives the time): without it a
# steady wish between 1 and 1.5 times the hold speed never gets a holding boat under way (a leader driven at 0.3 m/s
# against a 0.03 m/s drift, stopped once, stayed stopped for good; a follower pulled at 0.25 m/s never set off).
HOLD_DWELL_S = 3.0
TURN_SPEED_FRACTION = 0.1  # the least speed while turning, of the top speed (0.25 swept boats into neighbours faster)
REVERSE_SPEED_MPS = 1.0  # a wish behind the boat up to this speed through the water is met astern
ASTERN_FROM_DEG, ASTERN_UNTIL_DEG = 90.0, 70.0  # a wish more than this off the bow starts (keeps) going astern
SPEED_CAP_FACTOR, SPEED_CAP_MARGIN_MPS = 1.5, 0.2  # MotorboatModel.throttle_cap


@dataclass(frozen=True)
class MotorboatModel:
    """The motorboat as the autonomy knows it (not the simulator's truth). Defaults: a ~1.6 m, 30 kg survey boat.

    mass_kg: surge mass with added mass, kg. linear_drag_n_per_mps, quadratic_drag_n_per_mps2: surge drag (water
    and air together), N per m/s and per (m/s)^2. max_thrust_n: full thrust ahead, N (top speed 2 m/s with these).
    turning_radius_m: turning radius at full steering, m. yaw_time_constant_s: how fast the yaw rate follows the
    steering, s. steering_slew_per_s: fastest steering change, full-scale units per s. reverse_thrust_fraction:
    thrust astern at full reverse throttle as a fraction of max_thrust_n (a propeller pushes less astern; the
    autopilot does not say: 0.5 is a cautious guess, ArduPilot's SITL motorboat has 1). throttle_slew_per_s: the
    fastest throttle change the autopilot lets through, full-scale throttle units per s (ArduPilot's MOT_SLEWRATE /
    100: its default 100 %/s takes 2 s from full ahead to full astern; AP_MotorsUGV::slew_limit_throttle); 0: none.
    """

    mass_kg: float = 33.0
    linear_drag_n_per_mps: float = 4.0
    quadratic_drag_n_per_mps2: float = 8.18
    max_thrust_n: float = 40.72
    turning_radius_m: float = 3.0
    yaw_time_constant_s: float = 0.3
    steering_slew_per_s: float = 2.0
    reverse_thrust_fraction: float = 0.5
    throttle_slew_per_s: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.reverse_thrust_fraction <= 1.0:
            raise ValueError("reverse_thrust_fraction must be in [0, 1]")
        if not (math.isfinite(self.throttle_slew_per_s) and self.throttle_slew_per_s >= 0.0):
            raise ValueError(f"throttle_slew_per_s must be finite and >= 0 (0: none), got {self.throttle_slew_per_s!r}")
        values = (self.mass_kg, self.max_thrust_n, self.turning_radius_m, self.yaw_time_constant_s)
        if min(values) <= 0.0 or self.steering_slew_per_s <= 0.0 or not all(map(math.isfinite, values)):
            raise ValueError("mass, max thrust, turning radius, yaw time constant and steering slew must be > 0")
        if min(self.linear_drag_n_per_mps, self.quadratic_drag_n_per_mps2) < 0.0:
            raise ValueError("drag coefficients must be >= 0")
        if self.linear_drag_n_per_mps + self.quadratic_drag_n_per_mps2 <= 0.0:
            raise ValueError("the hull needs some drag")

    @classmethod
    def for_top_speed(
        cls, top_speed_mps: float, turning_radius_m: float | None = None, throttle_slew_per_s: float = 0.0
    ) -> MotorboatModel:
        """The nominal boat with its drag rescaled to reach `top_speed_mps` at full throttle (the split between
        linear and quadratic drag at top speed kept, as BuoyModel.for_top_speed), and this turning radius (m).
        Its mass is scaled by nominal top speed / top speed, so that full throttle takes it to its top speed in
        the same time whatever that speed (1.6 s to 63 %): the autopilot tells a top speed, never a mass, and a
        fast boat is not a slow boat with a heavier hull (ArduPilot's SITL motorboat: 2 kg, 10 m/s).
        throttle_slew_per_s: the autopilot's throttle slew (MOT_SLEWRATE / 100), per s; 0: none."""
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
            reverse_thrust_fraction=base.reverse_thrust_fraction,
            throttle_slew_per_s=throttle_slew_per_s,
        )

    def throttle_of(self, fraction: float) -> float:
        """The throttle that gives this fraction of max_thrust_n (negative: astern, at reverse_thrust_fraction)."""
        if fraction >= 0.0:
            return fraction
        return fraction / self.reverse_thrust_fraction if self.reverse_thrust_fraction > 0 else 0.0

    def fraction_of(self, throttle: float) -> float:
        """The fraction of max_thrust_n this throttle gives (the inverse of `throttle_of`)."""
        return throttle if throttle >= 0.0 else throttle * self.reverse_thrust_fraction

    def drag_n(self, speed_mps: float) -> float:
        """Surge drag at this speed through the water, N (signed)."""
        return (self.linear_drag_n_per_mps + self.quadratic_drag_n_per_mps2 * abs(speed_mps)) * speed_mps

    def throttle_cap(self, speed_ref_mps: float) -> float:
        """The thrust fraction that holds SPEED_CAP_FACTOR * |speed_ref| + SPEED_CAP_MARGIN_MPS steadily (at most 1):
        the most the controllers give for this speed reference. It leaves room to accelerate and bounds what a
        model error can do (a boat far lighter than the model would otherwise run away in a turn)."""
        cap = self.drag_n(SPEED_CAP_FACTOR * abs(speed_ref_mps) + SPEED_CAP_MARGIN_MPS) / self.max_thrust_n
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


@dataclass(frozen=True)
class _BoatCall:
    """One MotorboatMpc call's QP inputs: surge u0 m/s and yaw rate r0 rad/s now, heading error rad, speed
    reference m/s, thrust-fraction bounds and the throttle available."""

    u0: float
    r0: float
    error: float
    reference: float
    bounds: tuple[float, float]
    limit: float


def _finite(value: object, default: float = 0.0) -> float:
    number = float(value)  # type: ignore[arg-type]
    return number if math.isfinite(number) else default


def _pair(value: object) -> tuple[float, float]:
    array = np.asarray(value, dtype=float).reshape(2)
    return _finite(array[0]), _finite(array[1])


class References:
    """Heading error and speed references from the wish, the drift and the pose (module docstring), with the
    hysteresis state of one boat (hold, astern, side of the last big turn).

    reverse_speed_mps: a wish through the water behind the boat (more than ASTERN_FROM_DEG off its bow) and no
    faster than this is met going astern, stern first (0: never); astern it stays while the wish is more than
    ASTERN_UNTIL_DEG off the bow and no faster than 1.5 times this. In a crowd this backs a boat away from the
    neighbour in front or beside it instead of sending it round a circle through the others.
    """

    def __init__(
        self, model: MotorboatModel, hold_speed_mps: float, turn_speed_fraction: float, reverse_speed_mps: float
    ) -> None:
        self.model = model
        self.hold_speed_mps = float(hold_speed_mps)
        self.turn_speed_mps = float(turn_speed_fraction) * model.top_speed_mps
        self.reverse_speed_mps = float(reverse_speed_mps)
        self.holding, self.astern, self.turn_side = True, False, 0.0
        self.above_since: float | None = None  # when the wish of a holding boat rose above hold_speed_mps, s

    def reset(self) -> None:
        self.holding, self.astern, self.turn_side = True, False, 0.0
        self.above_since = None

    def __call__(
        self, desired: tuple[float, float], water: tuple[float, float], heading: float, t_s: float | None = None
    ) -> tuple[float, float, bool]:
        """(heading error e0 rad, speed reference U m/s (negative: astern), holding). t_s: the time, s (None: no
        dwell): a holding boat also gets under way once its wish has stayed above hold_speed_mps for HOLD_DWELL_S."""
        dx, dy = desired[0] - water[0], desired[1] - water[1]
        speed = math.hypot(dx, dy)
        threshold = self.hold_speed_mps * (HOLD_HYSTERESIS if self.holding else 1.0)
        if self.holding and speed >= self.hold_speed_mps and t_s is not None and math.isfinite(t_s):
            self.above_since = t_s if self.above_since is None else self.above_since
            if t_s - self.above_since >= HOLD_DWELL_S:
                threshold = self.hold_speed_mps
        else:
            self.above_since = None
        self.holding = speed < threshold
        if self.holding:
            self.turn_side, self.astern = 0.0, False
            return 0.0, 0.0, True
        error = math.remainder(math.atan2(dy, dx) - heading, 2.0 * math.pi)
        if self.astern:
            self.astern = speed <= 1.5 * self.reverse_speed_mps and abs(error) > math.radians(ASTERN_UNTIL_DEG)
        else:
            self.astern = speed <= self.reverse_speed_mps and abs(error) > math.radians(ASTERN_FROM_DEG)
        if self.astern:  # the stern points along the wish
            self.turn_side = 0.0
            stern = math.remainder(error - math.pi, 2.0 * math.pi)
            return stern, -speed * max(math.cos(stern), 0.0), False
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
    R; u' = -max(|u|, 0.2) astern), plus a correction on the yaw rate measured. Thrust = drag feed-forward at the
    speed reference + mass * speed_gain_per_s * (U - u), as a fraction of full thrust clipped to `fraction_bounds`
    (astern only if min_throttle < 0), then turned into a throttle (reverse is weaker: MotorboatModel.throttle_of).
    """

    def __init__(
        self,
        model: MotorboatModel = MotorboatModel(),  # frozen dataclass: an immutable default
        *,
        heading_gain_per_s: float = 0.6,
        yaw_damping: float = 1.0,
        speed_gain_per_s: float = 1.0,
        hold_speed_mps: float | None = None,
        turn_speed_fraction: float = TURN_SPEED_FRACTION,
        min_throttle: float = -1.0,
        reverse_speed_mps: float = REVERSE_SPEED_MPS,
    ) -> None:
        if not -1.0 <= min_throttle <= 0.0:
            raise ValueError(f"min_throttle must be in [-1, 0], got {min_throttle!r}")
        self.model = model
        self.heading_gain_per_s, self.yaw_damping = heading_gain_per_s, yaw_damping
        self.speed_gain_per_s, self.min_throttle = speed_gain_per_s, min_throttle
        hold = HOLD_SPEED_MPS if hold_speed_mps is None else hold_speed_mps
        self.references = References(model, hold, turn_speed_fraction, reverse_speed_mps if min_throttle < 0 else 0.0)

    def fraction_bounds(self, reference: float, limit: float) -> tuple[float, float]:
        """(lowest, highest) thrust fraction for this speed reference and throttle limit: at most what holds
        1.5 |U| + 0.2 m/s (MotorboatModel.throttle_cap) either way, astern only if min_throttle < 0."""
        m = self.model
        cap = m.throttle_cap(reference)
        low = -min(-self.min_throttle * m.reverse_thrust_fraction * limit, cap)
        return low, min(limit, cap)

    def brake(self, surge: float, limit: float) -> float:
        """The throttle that stops a holding boat still making way: thrust against the surge (m/s) at
        speed_gain_per_s, at most full astern (or ahead, if it drifts backwards), none below the hold speed."""
        if abs(surge) <= self.references.hold_speed_mps or self.min_throttle >= 0.0:
            return 0.0
        m = self.model
        wished = -m.mass_kg * self.speed_gain_per_s * surge / m.max_thrust_n
        most = m.reverse_thrust_fraction * limit * -self.min_throttle if surge > 0 else limit
        return m.throttle_of(min(max(wished, -most), most))

    def law(self, error: float, reference: float, surge: float, yaw_rate: float, limit: float) -> tuple[float, float]:
        """(throttle, steering) for heading error `error` rad, speed reference and surge m/s, yaw rate rad/s and
        throttle limit."""
        m = self.model
        force = m.drag_n(reference) + m.mass_kg * self.speed_gain_per_s * (reference - surge)
        low, high = self.fraction_bounds(reference, limit)
        throttle = m.throttle_of(min(max(force / m.max_thrust_n, low), high)) if reference != 0 else 0.0
        wished = self.heading_gain_per_s * error
        way = max(abs(surge), 0.2) if reference >= 0 else -max(abs(surge), 0.2)
        steering = -(m.turning_radius_m / way) * (wished + self.yaw_damping * (wished - yaw_rate))
        return throttle, min(max(steering, -1.0), 1.0)

    def command(
        self,
        desired: FloatArray,
        velocity: FloatArray,
        water: FloatArray,
        heading: float,
        yaw_rate: float = 0.0,
        limit: float = 1.0,
        t_s: float | None = None,
    ) -> MotorboatCommand:
        """The command towards `desired` (world, m/s) from the velocity over ground, the drift (m/s), the heading
        (rad) and yaw rate (rad/s); `limit`: the throttle available (a weak battery gives less); t_s: the time, s
        (for the hold's dwell, References)."""
        d, v, w, psi = _pair(desired), _pair(velocity), _pair(water), _finite(heading)
        error, reference, holding = self.references(d, w, psi, t_s)
        surge = math.cos(psi) * (v[0] - w[0]) + math.sin(psi) * (v[1] - w[1])
        if holding:
            return MotorboatCommand(self.brake(surge, max(0.0, _finite(limit))), 0.0, True, False, 0.0, "hold")
        throttle, steering = self.law(error, reference, surge, _finite(yaw_rate), max(0.0, _finite(limit)))
        return MotorboatCommand(throttle, steering, True, False, 0.0, "simple", error, reference)


class MotorboatMpc:
    """Linear MPC of a motorboat's heading and speed (see the module docstring for the formulation).

    model: the nominal MotorboatModel. step_s, horizon: the prediction's step (s) and length (steps).
    heading_weight (per rad^2), speed_weight (per (speed / top speed)^2), steering_weight, throttle_change_weight,
    steering_change_weight: cost weights per step. hold_speed_mps: below this wished speed through the water the
    boat holds (default HOLD_SPEED_MPS); turn_speed_fraction: the least speed while turning, as a
    fraction of top speed. min_throttle: the lowest throttle (-1, the default: full astern; 0: never astern).
    reverse_speed_mps: see References. solver: casadi conic plugin.
    time_budget_s: a solve using more CPU time than this is discarded for the fallback, s.
    call_period_s: how often `solve` is called, s (default step_s): how far the autopilot's throttle output can
    have moved towards a command by the next call, when the model has a throttle slew.

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
        turn_speed_fraction: float = TURN_SPEED_FRACTION,
        min_throttle: float = -1.0,
        reverse_speed_mps: float = REVERSE_SPEED_MPS,
        solver: str | None = None,
        time_budget_s: float = 0.02,
        call_period_s: float | None = None,
    ) -> None:
        if step_s <= 0.0 or horizon < 2:
            raise ValueError("need step_s > 0 and horizon >= 2")
        period = step_s if call_period_s is None else float(call_period_s)
        if not (math.isfinite(period) and period > 0.0):
            raise ValueError(f"call_period_s must be finite and > 0, got {call_period_s!r}")
        self.call_period_s = period
        positive = (heading_weight, speed_weight, throttle_change_weight, steering_change_weight)
        if min(positive) <= 0 or steering_weight < 0:
            raise ValueError("need heading, speed and change weights > 0 and steering_weight >= 0")
        self.model, self.step_s, self.horizon = model, float(step_s), int(horizon)
        self.weights = (heading_weight, speed_weight, steering_weight, throttle_change_weight, steering_change_weight)
        self.min_throttle = float(min_throttle)
        self.solver = solver or default_qp_plugin()
        self.time_budget_s = float(time_budget_s)
        self.fallback = MotorboatController(
            model, hold_speed_mps=hold_speed_mps, turn_speed_fraction=turn_speed_fraction, min_throttle=min_throttle,
            reverse_speed_mps=reverse_speed_mps,
        )  # fmt: skip
        self.references = self.fallback.references
        self.solves = 0
        self.fallbacks = 0
        self.last_plan: FloatArray | None = None
        self._previous = (0.0, 0.0)  # (thrust fraction, steering) last returned
        self._output = 0.0  # the autopilot's throttle output as its slew lets it follow our commands (throttle units)
        self._bar = np.zeros(self.horizon)  # the linearisation point: the plan's speed through the water per step
        # The QP is formulated and its casadi Functions built once per boat model and tuning (cached: a fleet of
        # identical boats shares them); each controller has its own buffers.
        self.problem, data, conic, constraint_values, speeds = _qp_functions(
            model, self.step_s, self.horizon, self.weights, self.solver
        )
        self._speeds = _BufferedCall(speeds)  # the plan's speeds, the next linearisation point (no DM per call)
        self._data = _BufferedCall(data)
        self._qp = _BufferedCall(conic, self._data.outputs, self.solver)
        self._qp.inputs["a"][:] = constraint_values
        self._qp.inputs["lba"][:], self._qp.inputs["uba"][:] = _change_row_bounds(self.model, self.step_s, self.horizon)
        self._solve_qp(0.0, 0.0, 0.5, 1.0, (-0.5, 1.0))  # warm-up: the first real call is not the slow one
        self.reset()

    def reset(self) -> None:
        """Forget the previous command and plan (the boat is idle)."""
        self._previous = (0.0, 0.0)
        self._output = 0.0
        self._bar = np.zeros(self.horizon)
        self.last_plan = None
        self.references.reset()

    # ------------------------------------------------------------------ solving

    def _solve_qp(
        self, u0: float, r0: float, target: float, reference: float, bounds: tuple[float, float]
    ) -> FloatArray:
        """(horizon, 2) plan of (thrust fraction, steering); raises on a solver failure."""
        n = self.horizon
        data, qp, out = self._data.inputs["p"], self._qp.inputs, self._qp.outputs
        direction = -1.0 if reference < 0 else 1.0
        data[:7] = (u0, r0, target, reference, direction, *self._previous)
        data[7 : 7 + n] = self._bar
        self._data()
        lbx, ubx = qp["lbx"], qp["ubx"]
        lbx[:n], ubx[:n] = bounds
        lbx[0], ubx[0] = self.first_thrust_bounds(bounds)
        lbx[n:], ubx[n:] = -1.0, 1.0
        step = self.model.steering_slew_per_s * self.step_s
        lbx[n], ubx[n] = max(-1.0, self._previous[1] - step), min(1.0, self._previous[1] + step)
        self._qp()  # raises _SolveError when not solved
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
        t_s: float | None = None,
    ) -> MotorboatCommand:
        """The command for one control step.

        desired_velocity_mps, velocity_mps (estimated, over ground), water_velocity_mps (drift, estimated): (2,)
        world frame, m/s (non-finite entries count as 0). heading_rad, yaw_rate_radps: estimated (non-finite: 0).
        max_throttle: the throttle available, [0, 1] (a weak battery gives less).
        t_s: the time, s (None: none known): a holding boat whose wish stays above the hold speed for HOLD_DWELL_S
        gets under way (References).
        """
        call = self._prepare(
            desired_velocity_mps, velocity_mps, water_velocity_mps, heading_rad, yaw_rate_radps, max_throttle, t_s
        )
        return call if isinstance(call, MotorboatCommand) else self._solve_call(call)

    def _prepare(
        self,
        desired_velocity_mps: FloatArray,
        velocity_mps: FloatArray,
        water_velocity_mps: FloatArray,
        heading_rad: float,
        yaw_rate_radps: float,
        max_throttle: float,
        t_s: float | None,
    ) -> MotorboatCommand | _BoatCall:
        """The references of a call (`solve`'s arguments); the hold's command when there is nothing to solve,
        else the QP's inputs (counted as a solve; a boat without a plan is linearised about its speed now)."""
        d, v, w = _pair(desired_velocity_mps), _pair(velocity_mps), _pair(water_velocity_mps)
        psi, r0 = _finite(heading_rad), _finite(yaw_rate_radps)
        limit = min(max(_finite(max_throttle), 0.0), 1.0)
        error, reference, holding = self.references(d, w, psi, t_s)
        u0 = math.cos(psi) * (v[0] - w[0]) + math.sin(psi) * (v[1] - w[1])
        if holding or limit <= 1e-9:
            throttle = self.fallback.brake(u0, limit)
            self._previous = (self.model.fraction_of(throttle), self._slewed(0.0))
            self._follow(throttle)
            self.last_plan = None
            return MotorboatCommand(throttle, self._previous[1], True, False, 0.0, "hold")
        self.solves += 1
        if self.last_plan is None:  # no plan to linearise about: the speed now, steering straight
            self._bar[:] = u0
        return _BoatCall(u0, r0, error, reference, self.fallback.fraction_bounds(reference, limit), limit)

    def _solve_call(self, call: _BoatCall) -> MotorboatCommand:
        """The QP of a prepared call solved on its own (bob_autonomy.control.motorboat_mpc_batch solves many at
        once), or the fallback after any failure, then the command."""
        start, cpu = time.perf_counter(), time.thread_time()
        try:
            plan = self._solve_qp(call.u0, call.r0, call.error, call.reference, call.bounds)
            elapsed = time.perf_counter() - start
            if not np.isfinite(plan).all():
                raise _SolveError("non-finite solution")
            # CPU time, as the buoy MPC: on a busy computer a quick solve can wait for the processor (wall time).
            _cpu_over_budget(time.thread_time() - cpu, self.time_budget_s)
            self.last_plan = plan
            speeds = self._speeds
            speeds.inputs["i0"][:] = plan[:, 0]
            speeds.inputs["i1"][0] = call.u0
            speeds()
            self._bar[:] = speeds.outputs["o0"]
        except Exception as error_:  # any failure of the solve: the boat still gets a command
            return self._finish(call, error_, time.perf_counter() - start)
        return self._finish(call, plan, elapsed)

    def _finish(self, call: _BoatCall, outcome: FloatArray | Exception, elapsed: float) -> MotorboatCommand:
        """The command from the first step of a plan (horizon, 2), or the fallback's after a failure (an
        exception, counted and logged), bounded and slewed; it becomes the previous command."""
        if isinstance(outcome, Exception):
            ok, fallback = False, True
            status = f"fallback: {type(outcome).__name__}: {outcome}"
            self.fallbacks += 1
            self.last_plan = None
            logger.warning("motorboat MPC fallback #%d: %s", self.fallbacks, status)
            throttle, steering = self.fallback.law(call.error, call.reference, call.u0, call.r0, call.limit)
            fraction = self.model.fraction_of(throttle)
        else:
            ok, fallback, status = True, False, "optimal"
            fraction, steering = float(outcome[0, 0]), float(outcome[0, 1])
        bounds = self.first_thrust_bounds(call.bounds)  # what the autopilot's throttle slew can reach too
        fraction = min(max(fraction, bounds[0]), bounds[1])
        steering = self._slewed(min(max(steering, -1.0), 1.0))
        self._previous = (fraction, steering)
        throttle = self.model.throttle_of(fraction)
        self._follow(throttle)
        return MotorboatCommand(throttle, steering, ok, fallback, elapsed, status, call.error, call.reference)

    def first_thrust_bounds(self, bounds: tuple[float, float]) -> tuple[float, float]:
        """The plan's first thrust fraction: within `bounds` and within what the autopilot's throttle slew reaches
        in one plan step from its output now (all of `bounds` without a slew). Where the two do not meet (the
        output is still far outside the bounds), the reachable value nearest them."""
        m = self.model
        if m.throttle_slew_per_s <= 0.0:
            return bounds
        reach = m.throttle_slew_per_s * self.step_s
        low = m.fraction_of(max(-1.0, self._output - reach))
        high = m.fraction_of(min(1.0, self._output + reach))
        if low > bounds[1]:
            return low, low
        if high < bounds[0]:
            return high, high
        return max(low, bounds[0]), min(high, bounds[1])

    def _follow(self, throttle: float) -> None:
        """Move the autopilot's throttle output towards `throttle` as its slew does over one call period."""
        slew = self.model.throttle_slew_per_s * self.call_period_s
        if slew <= 0.0:
            self._output = throttle
        else:
            self._output = min(max(throttle, self._output - slew), self._output + slew)

    def _slewed(self, steering: float) -> float:
        """`steering` moved at most one step's slew from the previous command."""
        step = self.model.steering_slew_per_s * self.step_s
        return min(max(steering, self._previous[1] - step), self._previous[1] + step)


def _formulate(model: MotorboatModel, step_s: float, horizon: int, weights: tuple[float, ...]) -> dict[str, ca.SX]:
    """The QP in casadi SX: z (thrust fractions, then steerings); p = (u0 m/s, r0 rad/s, e0 rad, U m/s, direction
    +-1, previous thrust fraction, previous steering, the plan's speeds u_bar (horizon,) m/s); cost f; the
    steering-change rows g."""
    m, n, h = model, horizon, step_s
    w_heading, w_speed, w_steer, w_dthrottle, w_dsteer = weights
    p = ca.SX.sym("p", 7 + n)
    u0, r0, target, reference, direction, throttle_prev, steer_prev = (p[i] for i in range(7))
    u_bar = p[7 : 7 + n]
    z = ca.SX.sym("z", 2 * n)
    throttle, steer = z[:n], z[n:]
    c1, c2, mass = m.linear_drag_n_per_mps, m.quadratic_drag_n_per_mps2, m.mass_kg
    lag = math.exp(-h / m.yaw_time_constant_s)
    top = m.top_speed_mps
    cost, u, r, delta = 0, u0, r0, 0
    previous = (throttle_prev, steer_prev)
    for k in range(n):
        # Yaw rate the steering asks for at the speed of the step's start, linearised about the plan.
        bar = direction * ca.fmax(direction * u_bar[k], MIN_TURN_SPEED_MPS)
        r_steady = -steer[k] * bar / m.turning_radius_m
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
        cost += w_heading * (delta - target) ** 2 + w_speed * ((u - reference) / top) ** 2
        cost += w_steer * steer[k] ** 2
        cost += w_dthrottle * (throttle[k] - previous[0]) ** 2 + w_dsteer * (steer[k] - previous[1]) ** 2
        previous = (throttle[k], steer[k])
    g = steer[1:] - steer[:-1]
    if m.throttle_slew_per_s > 0.0:  # the autopilot slews the throttle: so does the plan
        g = ca.vertcat(g, throttle[1:] - throttle[:-1])
    return {"x": z, "p": p, "f": cost, "g": g}


def _change_row_bounds(model: MotorboatModel, step_s: float, horizon: int) -> tuple[FloatArray, FloatArray]:
    """(lower, upper) bounds of the QP's change rows (`_formulate`'s g): each plan step's steering change within
    steering_slew_per_s * step_s, then (with a throttle slew) its thrust-fraction change within throttle_slew_per_s *
    step_s: exact ahead; astern, where a throttle change moves the thrust by reverse_thrust_fraction of it, the
    plan may change faster than the autopilot (the first step is exact: MotorboatMpc.first_thrust_bounds)."""
    steering = np.full(horizon - 1, model.steering_slew_per_s * step_s)
    throttle = np.full(horizon - 1 if model.throttle_slew_per_s > 0.0 else 0, model.throttle_slew_per_s * step_s)
    upper = np.concatenate((steering, throttle))
    return -upper, upper


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
