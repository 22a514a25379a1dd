"""Model-predictive velocity control: the buoy's linear MPC here, the eBot's in bob_autonomy.control.ebot_mpc.

What: `BuoyMpc` turns the behaviour's desired velocity into the thrust of the
vectored thruster (body frame, ready for the vehicle interface), planning a few
seconds ahead against water drag and a known drift, within the thruster's
magnitude limit (which a weak battery lowers) and a bound on how fast the
thrust may change. `DiffDriveMpc` turns a desired velocity vector into the
eBot's wheel speeds within their limit.

Why: the proportional controllers of `velocity_control` react to the error of
the moment; the MPC also knows what the thrust does over the next seconds, how
fast it may change, and where the limits are, and it feeds the drift forward
(no steady-state error from a current the estimator knows).

How (buoy). Every call solves one small convex QP, built once per model and tuning:

* state: world-frame velocity v (2,) m/s; input: world-frame thrust u (2,) N,
  held over each step of dt_s; horizon N steps (default 10 x 0.5 s = 5 s).
  Decision variables: the N thrusts, scaled by the nominal maximum thrust
  (z = u / model.max_thrust_n, 2N variables; the velocities are eliminated:
  condensed form).
* dynamics: M dv/dt = u - D(v - w), D(r) = (c1 + c2 |r|) r, w the water velocity
  (current + wind drift, from the estimator) held over the horizon as a known
  disturbance. D is linearized (first-order Taylor, the Jacobian, not the
  secant) at the current estimated velocity relative to the water r0 = v0 - w:
  D(r) ~ D(r0) + J (r - r0), J = (c1 + c2|r0|) I + c2|r0| n n^T, n = r0/|r0|.
  The linear model is exact in value at r0, so at the operating point the
  predicted force balance is the true one, and its damping along the motion is
  the true local one (c1 + 2 c2 |r0|, twice the secant's quadratic part). It is
  discretized exactly (zero-order hold): J is symmetric with eigenvectors n and
  its normal, so Ad = expm(-J dt/M) and Bd = J^-1 (I - Ad) are closed-form.
  It is re-linearized at every call (receding horizon).
* cost: tracking_weight * sum_k |v_k - v_desired|^2 (k = 1..N, (m/s)^2)
  + input_change_weight * sum_k |z_k - z_{k-1}|^2 (k = 0..N-1, z_{-1} the
  previous applied thrust). No cost on the thrust itself: at a fixed point the
  thrust holds the desired velocity against the drag of the drift-relative
  velocity (feed-forward), and the input-change form has no offset when the
  model is right.
* constraints: |u_k| <= max_thrust_n approximated from inside by a regular
  polygon with `polygon_sides` sides (vertices on the circle; per step one
  two-sided row per pair of opposite sides, or with an odd number of sides
  one row per side: `polygon_rows`; bounds scaled per call by max_thrust_n);
  per-step thrust change |u_k - u_{k-1}|_inf <= max_thrust_change_n (a box,
  for k = 0 against the previous applied thrust, as simple bounds on z_0);
  a circumscribing box |z| <= max_thrust_n as simple bounds (redundant, cheap).
  The previous thrust is first scaled into the polygon of this call's limit (a
  weaker battery cannot produce it anyway), so u_k = previous is feasible and
  the QP is never infeasible.
* solver: a dense QP plugin of casadi's `conic` (default: the first of
  QP_PLUGINS available). DAQP, a dual active-set solver made for small dense
  MPC QPs, is the cheapest here (benchmarks/mpc_solve.py, whole solve() call
  from Python: median 0.10 ms with DAQP, 0.10 ms qpOASES, 0.17-0.19 ms OSQP;
  IPOPT on the same problem ~4.8 ms); proxqp and qrqp are left out: on random
  instances proxqp returned plans up to 26 N off (and "primal infeasible" with
  infinite bounds), qrqp failed to find a search direction. The QP data
  (Hessian and gradient) come from a casadi SX Function of the parameters; both
  Functions are called through `Function.buffer` on preallocated numpy arrays,
  the data function writing straight into the solver's input arrays (no
  conversion, no allocation per call). Of the ~0.1 ms per call, the solver
  is ~40 us, the QP-data Function ~13 us, reading the solver's status ~6 us,
  and the rest is Python. The previous plan, shifted by one step, and its
  multipliers are passed as the initial guess (DAQP through casadi re-runs its
  setup every call and ignores them; OSQP uses them).
* failure: a solver exception or failure status, a non-finite plan, or a solve
  that used more than time_budget_s of this thread's CPU time falls back to a saturated proportional command with
  drift feed-forward (as `BuoyVelocityController`), counted in `fallbacks` and
  logged on the "bob_autonomy.control.mpc" logger. Every returned thrust, MPC or
  fallback, is finally scaled into the polygon and its change rate-limited by a
  convex combination with the (in-polygon) previous thrust, so it never leaves
  either bound. The budget counts CPU time (`time.thread_time`), not wall
  time: the check runs after the solve, so discarding a plan saves no time,
  and a solve preempted by other processes (45 autonomy processes on 2 cores
  took 21-56 ms of wall time for ~0.1 ms of work) is not a slow solver; the
  wall time is still reported (`solve_time_s`).

Not modelled: the nozzle's slew limit (3 rad/s in the SITL: the change bound
limits it in part), windage, heading dynamics (the world-frame thrust does not
depend on the heading; the heading only rotates the output into the body
frame). Model mismatch is not integrated away (no disturbance estimator).

Frames: x east, y north; headings rad from east, counter-clockwise; body frame x
forward, y left.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from functools import lru_cache

import casadi as ca
import numpy as np

from bob_autonomy.control.qp import QP_PLUGINS as QP_PLUGINS  # public here before qp.py existed
from bob_autonomy.control.qp import (
    Pair,
    _BufferedCall,
    _conic,
    _cpu_over_budget,
    _finite_float,
    _pair,
    _SolveError,
    default_qp_plugin,
)
from bob_autonomy.control.qp_interior import InteriorMinimiser, take_interior
from bob_autonomy.control.velocity_control import BuoyModel
from bob_autonomy.core.arrays import FloatArray

logger = logging.getLogger("bob_autonomy.control.mpc")


def polygon_normals(sides: int) -> FloatArray:
    """(sides, 2) outward unit normals of a regular polygon with a vertex on the +x axis.

    The polygon inscribed in the circle of radius R is {u : normals @ u <= R cos(pi / sides)}.
    """
    angles = (np.arange(sides) + 0.5) * (2.0 * math.pi / sides)
    return np.column_stack((np.cos(angles), np.sin(angles)))


def polygon_rows(sides: int) -> tuple[FloatArray, bool]:
    """The QP's rows for one step's thrust polygon: (rows, 2) unit normals, and whether each row is two-sided.

    With an even number of sides, opposite sides are parallel: the polygon is {u : |n_i . u| <= R cos(pi / sides),
    i < sides / 2}, half as many rows, each bounded on both sides (DAQP's work per solve grows with the rows: its
    `update_M` forms every row times the inverse Cholesky factor, and each iteration scans every row for the most
    violated). The second half of polygon_normals are the first half's negations to within 1e-16; here they are
    exact. With an odd number of sides each side is its own one-sided row."""
    normals = polygon_normals(sides)
    if sides % 2 == 0:
        return normals[: sides // 2], True
    return normals, False


# --------------------------------------------------------------------------- buoy


@lru_cache(maxsize=32)
def _buoy_qp_functions(
    model: BuoyModel,
    dt_s: float,
    horizon: int,
    polygon_sides: int,
    tracking_weight: float,
    input_change_weight: float,
    solver: str,
) -> tuple[dict[str, ca.SX], ca.Function, ca.Function, FloatArray]:
    """(problem, QP data Function p -> (h, g), conic solver, constraint matrix nonzeros) of BuoyMpc: the QP in
    casadi SX, x (2N scaled thrusts), p (v0, w, v_desired, previous z), f, g (see the module docstring)."""
    c1, c2, mass = model.linear_drag_n_per_mps, model.quadratic_drag_n_per_mps2, model.mass_kg
    scale, dt = model.max_thrust_n, dt_s
    p = ca.SX.sym("p", 8)
    v0, water, desired, z_prev = p[0:2], p[2:4], p[4:6], p[6:8]
    z = ca.SX.sym("z", 2 * horizon)

    r0 = v0 - water
    speed = ca.sqrt(ca.sumsqr(r0) + 1e-18)
    along = r0 / speed
    outer = along @ along.T
    across = ca.SX.eye(2) - outer
    a = c1 + c2 * speed  # eigenvalue of J across the motion, N per m/s
    b = a + c2 * speed  # eigenvalue of J along the motion

    def phi1(x: ca.SX) -> ca.SX:  # (1 - exp(-x)) / x, limit 1 at 0
        safe = ca.if_else(x < 1e-9, 1.0, x)
        return ca.if_else(x < 1e-9, 1.0 - 0.5 * x, (1.0 - ca.exp(-safe)) / safe)

    ad = ca.exp(-a * dt / mass) * across + ca.exp(-b * dt / mass) * outer
    bd = (dt / mass) * (phi1(a * dt / mass) * across + phi1(b * dt / mass) * outer)
    jac = a * across + b * outer
    offset = jac @ water + c2 * speed * r0  # u + offset drives -J v: the affine drag terms

    cost = 0
    v, previous = v0, z_prev
    for k in range(horizon):
        zk = z[2 * k : 2 * k + 2]
        v = ad @ v + bd @ (scale * zk + offset)
        cost += tracking_weight * ca.sumsqr(v - desired) + input_change_weight * ca.sumsqr(zk - previous)
        previous = zk
    normals = ca.DM(polygon_rows(polygon_sides)[0])
    rows = [normals @ z[2 * k : 2 * k + 2] for k in range(horizon)]
    if horizon > 1:
        rows.append(z[2:] - z[:-2])
    problem = {"x": z, "p": p, "f": cost, "g": ca.vertcat(*rows)}

    hessian = ca.hessian(cost, z)[0]
    gradient = ca.substitute(ca.gradient(cost, z), z, ca.DM.zeros(z.shape[0]))
    constraints = ca.jacobian(problem["g"], z)
    if ca.depends_on(constraints, ca.vertcat(z, p)):
        raise AssertionError("constraint matrix must be constant")
    values = np.array(ca.evalf(constraints).nonzeros(), dtype=float)
    data = ca.Function("buoy_mpc_qp_data", [p], [hessian, gradient], ["p"], ["h", "g"], {"cse": True})
    conic = _conic("buoy_mpc_qp", solver, hessian.sparsity(), constraints.sparsity())
    return problem, data, conic, values


@dataclass(frozen=True)
class MpcResult:
    """One buoy MPC command.

    thrust_body_n: (2,) thrust in the body frame (x forward, y left), N.
    thrust_world_n: (2,) the same thrust in the world frame (x east, y north), N.
    ok: the QP was solved and its first thrust is the command.
    fallback: the proportional fallback made the command.
    solve_time_s: wall time of the QP (data + solver), s; 0 if none was run.
    status: "optimal", or why not.
    """

    thrust_body_n: FloatArray
    thrust_world_n: FloatArray
    ok: bool
    fallback: bool
    solve_time_s: float
    status: str


class BuoyMpc:
    """Linear MPC of the buoy's velocity (see the module docstring for the formulation).

    model: the nominal BuoyModel (mass incl. added mass, drag coefficients, and
        the nominal max thrust that scales the decision variables).
    dt_s: step of the prediction, s (the control period); horizon: steps.
    polygon_sides: sides of the regular polygon inscribed in the thrust circle.
    max_thrust_change_n: largest change of each thrust component per step, N.
    tracking_weight: weight of the squared velocity error, per (m/s)^2 per step.
    input_change_weight: weight of the squared thrust change per step, the change
        measured in units of model.max_thrust_n.
    fallback_gain_per_s: proportional gain of the fallback, fraction of mass per s.
    solver: casadi conic plugin; default the cheapest available (QP_PLUGINS).
    time_budget_s: a QP that used more CPU time than this is discarded for the fallback, s.

    Attributes: solves (QPs attempted), fallbacks (commands made by the fallback),
    last_plan_world_n ((horizon, 2) thrust plan of the last successful QP, or None).
    """

    def __init__(
        self,
        model: BuoyModel = BuoyModel(),  # noqa: B008 - frozen dataclass, immutable default
        dt_s: float = 0.5,
        horizon: int = 10,
        polygon_sides: int = 16,
        max_thrust_change_n: float = 15.0,
        tracking_weight: float = 1.0,
        input_change_weight: float = 0.05,
        fallback_gain_per_s: float = 1.5,
        solver: str | None = None,
        time_budget_s: float = 0.02,
    ) -> None:
        if dt_s <= 0.0 or horizon < 1 or polygon_sides < 3 or max_thrust_change_n <= 0.0:
            raise ValueError("need dt_s > 0, horizon >= 1, polygon_sides >= 3, max_thrust_change_n > 0")
        if model.mass_kg <= 0.0 or model.max_thrust_n <= 0.0 or tracking_weight <= 0.0 or input_change_weight <= 0.0:
            raise ValueError("need mass, max thrust, tracking_weight and input_change_weight > 0")
        self.model = model
        self.dt_s = float(dt_s)
        self.horizon = int(horizon)
        self.polygon_sides = int(polygon_sides)
        self.max_thrust_change_n = float(max_thrust_change_n)
        self.tracking_weight = float(tracking_weight)
        self.input_change_weight = float(input_change_weight)
        self.fallback_gain_per_s = float(fallback_gain_per_s)
        self.solver = solver or default_qp_plugin()
        self.time_budget_s = float(time_budget_s)
        self.normals = polygon_normals(self.polygon_sides)
        self.inradius_ratio = math.cos(math.pi / self.polygon_sides)
        row_normals, two_sided = polygon_rows(self.polygon_sides)
        # A polygon row's lower bound per N of limit: the opposite side's, or (one-sided rows) one never active
        # (a row's support is at most the limit) yet finite for every plugin.
        self.polygon_lower_ratio = -self.inradius_ratio if two_sided else -2.0
        self._rows_per_step = len(row_normals)
        self.solves = 0
        self.fallbacks = 0
        self.interior_solves = 0  # QPs whose unconstrained minimiser met every bound (no solver call)
        self.last_plan_world_n: FloatArray | None = None
        self._last_thrust: Pair = (0.0, 0.0)
        self._bounds_limit = math.nan
        self._build()
        self._warm_up()

    # ------------------------------------------------------------------ formulation

    def _build(self) -> None:
        """This controller's buffers on the QP's casadi Functions (built once per model and tuning and shared: a
        fleet of identical buoys builds one), with the bounds that depend on max_thrust_change_n alone."""
        self.problem, data, conic, constraint_values = _buoy_qp_functions(
            self.model,
            self.dt_s,
            self.horizon,
            self.polygon_sides,
            self.tracking_weight,
            self.input_change_weight,
            self.solver,
        )
        self._data = _BufferedCall(data)
        self._qp = _BufferedCall(conic, self._data.outputs, self.solver)
        qp = self._qp.inputs
        qp["a"][:] = constraint_values
        # DAQP only: its plan depends on the QP alone (through casadi it ignores the warm start); OSQP and qpOASES
        # keep state from solve to solve, which a skipped call would change.
        self._interior = (
            InteriorMinimiser(data.sparsity_out("h"), conic.sparsity_in("a"), constraint_values)
            if self.solver == "daqp"
            else None
        )
        n_poly = self._rows_per_step * self.horizon
        qp["lba"][n_poly:] = -self.max_thrust_change_n / self.model.max_thrust_n
        qp["uba"][n_poly:] = self.max_thrust_change_n / self.model.max_thrust_n
        self._n_poly = n_poly

    def _warm_up(self) -> None:
        """One solve at construction, so the first real call is not the slow one."""
        self._solve_qp((0.0, 0.0), (0.0, 0.0), (0.0, 0.0), self.model.max_thrust_n, (0.0, 0.0))
        self.last_plan_world_n = None

    def qp_bounds(self, max_thrust_n: float, previous_thrust_world_n: FloatArray) -> dict[str, FloatArray]:
        """lbx, ubx, lbg, ubg of the scaled QP (for an external solver on `problem`, e.g. IPOPT)."""
        scale = self.model.max_thrust_n
        box = max_thrust_n / scale
        step = self.max_thrust_change_n / scale
        prev = np.asarray(previous_thrust_world_n, dtype=float) / scale
        lbx, ubx = np.full(2 * self.horizon, -box), np.full(2 * self.horizon, box)
        lbx[:2], ubx[:2] = np.maximum(-box, prev - step), np.minimum(box, prev + step)
        polygon_lower = box * self.polygon_lower_ratio
        lbg = np.concatenate((np.full(self._n_poly, polygon_lower), np.full(2 * self.horizon - 2, -step)))
        ubg = np.concatenate((np.full(self._n_poly, box * self.inradius_ratio), np.full(2 * self.horizon - 2, step)))
        return {"lbx": lbx, "ubx": ubx, "lbg": lbg, "ubg": ubg}

    # ------------------------------------------------------------------ solving

    def _solve_qp(self, desired: Pair, velocity: Pair, water: Pair, limit: float, previous: Pair) -> FloatArray:
        """(horizon, 2) world thrust plan, N; raises on a solver failure. `previous` is in the polygon."""
        scale = self.model.max_thrust_n
        data, qp, out = self._data.inputs["p"], self._qp.inputs, self._qp.outputs
        data[0], data[1] = velocity
        data[2], data[3] = water
        data[4], data[5] = desired
        prev_x, prev_y = previous[0] / scale, previous[1] / scale
        data[6], data[7] = prev_x, prev_y
        self._data()  # writes the Hessian and gradient straight into the solver's inputs
        box = limit / scale
        lbx, ubx = qp["lbx"], qp["ubx"]
        if limit != self._bounds_limit:  # the bounds that depend on the limit alone
            lbx.fill(-box)
            ubx.fill(box)
            qp["uba"][: self._n_poly] = box * self.inradius_ratio
            qp["lba"][: self._n_poly] = box * self.polygon_lower_ratio
            self._bounds_limit = limit
        step = self.max_thrust_change_n / scale
        lbx[0], lbx[1] = max(-box, prev_x - step), max(-box, prev_y - step)
        ubx[0], ubx[1] = min(box, prev_x + step), min(box, prev_y + step)
        x = out["x"]
        if self._interior is not None and take_interior(self._interior, qp, out):
            self.interior_solves += 1
            return (scale * x).reshape(self.horizon, 2)
        # Warm start: the previous plan shifted by one step (the last step repeated), and its multipliers.
        x0 = qp["x0"]
        x0[:-2] = x[2:]
        x0[-2:] = x[-2:]
        qp["lam_x0"][:] = out["lam_x"]
        qp["lam_a0"][:] = out["lam_a"]
        self._qp()  # raises _SolveError when not solved
        return (scale * x).reshape(self.horizon, 2)

    def polygon_peak(self, x: float, y: float) -> float:
        """max over the polygon's unit normals of normal . (x, y): (x, y) is inside iff <= limit * inradius_ratio."""
        radius = math.hypot(x, y)
        if radius == 0.0:
            return 0.0
        sector = 2.0 * math.pi / self.polygon_sides
        offset = (math.atan2(y, x) - 0.5 * sector) % sector  # angle past the previous normal
        return radius * math.cos(min(offset, sector - offset))

    def _into_polygon(self, x: float, y: float, limit: float) -> Pair:
        """(x, y) scaled towards 0 onto the polygon of radius limit if it is outside."""
        peak = self.polygon_peak(x, y)
        bound = limit * self.inradius_ratio
        if peak <= bound:
            return x, y
        shrink = bound / peak * (1.0 - 1e-12)  # strictly inside despite round-off
        return x * shrink, y * shrink

    def into_polygon(self, thrust_world_n: FloatArray, max_thrust_n: float) -> FloatArray:
        """(2,) thrust scaled towards 0 onto the polygon of max_thrust_n if it is outside, N."""
        return np.array(self._into_polygon(float(thrust_world_n[0]), float(thrust_world_n[1]), max_thrust_n))

    def _within_limits(self, thrust: Pair, previous: Pair, limit: float) -> Pair:
        """thrust inside the polygon and within the change bound of previous (which is in the polygon).

        The rate limit moves along the segment to `previous`: a convex combination of
        two points of the polygon stays in it."""
        x, y = self._into_polygon(thrust[0], thrust[1], limit)
        dx, dy = x - previous[0], y - previous[1]
        largest = max(abs(dx), abs(dy))
        if largest > self.max_thrust_change_n:
            fraction = self.max_thrust_change_n / largest * (1.0 - 1e-12)
            x, y = previous[0] + fraction * dx, previous[1] + fraction * dy
        return x, y

    def fallback_thrust(self, desired: Pair, velocity: Pair, water: Pair, limit: float) -> Pair:
        """World thrust (N) of the proportional fallback, before the rate limit.

        Drag feed-forward at the desired velocity relative to the water + mass *
        gain * velocity error, clipped to the polygon's inscribed circle."""
        m = self.model
        rx, ry = desired[0] - water[0], desired[1] - water[1]
        drag = m.linear_drag_n_per_mps + m.quadratic_drag_n_per_mps2 * math.hypot(rx, ry)
        gain = m.mass_kg * self.fallback_gain_per_s
        x = drag * rx + gain * (desired[0] - velocity[0])
        y = drag * ry + gain * (desired[1] - velocity[1])
        radius = limit * self.inradius_ratio
        norm = math.hypot(x, y)
        return (x * radius / norm, y * radius / norm) if norm > radius else (x, y)

    def reset(self) -> None:
        """Forget the previous thrust and plan (the thruster is idle)."""
        self._last_thrust = (0.0, 0.0)
        self.last_plan_world_n = None

    def solve(
        self,
        desired_velocity_mps: FloatArray,
        velocity_mps: FloatArray,
        water_velocity_mps: FloatArray,
        heading_rad: float,
        max_thrust_n: float,
        previous_thrust_world_n: FloatArray | None = None,
    ) -> MpcResult:
        """The thrust command for one control step.

        desired_velocity_mps, velocity_mps (estimated, over ground), water_velocity_mps
        (current + wind drift, estimated): (2,) world frame, m/s; non-finite
        entries count as 0. heading_rad: estimated heading (non-finite: 0).
        max_thrust_n: this step's thrust limit, N (a weak battery gives less;
        non-finite or negative: 0). previous_thrust_world_n: (2,) the thrust
        applied last step, N; None: the thrust this controller returned last
        (zero before the first call or after reset()).
        """
        call = self._prepare(
            desired_velocity_mps, velocity_mps, water_velocity_mps, heading_rad, max_thrust_n, previous_thrust_world_n
        )
        return self._solve_call(call)

    def _solve_call(self, call: _Call) -> MpcResult:
        """The QP of a prepared call solved on its own (bob_autonomy.control.buoy_mpc_batch solves many at once),
        or the fallback after any failure, then the command."""
        if not call.solving:
            return self._finish(call, None, 0.0)
        start, cpu = time.perf_counter(), time.thread_time()
        try:
            plan = self._solve_qp(call.desired, call.velocity, call.water, call.limit, call.previous)
            if not math.isfinite(float(plan.sum())):  # a NaN or inf anywhere makes the sum non-finite
                raise _SolveError("non-finite solution")
            _cpu_over_budget(time.thread_time() - cpu, self.time_budget_s)
        except Exception as error:  # any failure of the solve: the vessel still gets a command
            return self._finish(call, error, time.perf_counter() - start)
        return self._finish(call, plan, time.perf_counter() - start)

    def _prepare(
        self,
        desired_velocity_mps: FloatArray,
        velocity_mps: FloatArray,
        water_velocity_mps: FloatArray,
        heading_rad: float,
        max_thrust_n: float,
        previous_thrust_world_n: FloatArray | None,
    ) -> _Call:
        """A call's inputs made finite, and the previous thrust scaled into this call's polygon."""
        limit = max(0.0, _finite_float(max_thrust_n, 0.0))
        previous = self._last_thrust if previous_thrust_world_n is None else _pair(previous_thrust_world_n)
        return _Call(
            _pair(desired_velocity_mps),
            _pair(velocity_mps),
            _pair(water_velocity_mps),
            _finite_float(heading_rad, 0.0),
            limit,
            self._into_polygon(previous[0], previous[1], limit),
        )

    def _finish(self, call: _Call, outcome: FloatArray | Exception | None, elapsed: float) -> MpcResult:
        """The command from a call's QP plan (horizon, 2) N, or the fallback's after a failure (an exception);
        None: no thrust available. Counts the solve, keeps the plan and the command, rotates it into the body."""
        ok, used_fallback, status = True, False, "optimal"
        thrust: Pair
        if outcome is None:
            thrust, status = (0.0, 0.0), "no thrust available"
            self.last_plan_world_n = None
        elif isinstance(outcome, Exception):
            self.solves += 1
            ok, used_fallback = False, True
            status = f"fallback: {type(outcome).__name__}: {outcome}"
            self.fallbacks += 1
            self.last_plan_world_n = None
            logger.warning("buoy MPC fallback #%d: %s", self.fallbacks, status)
            thrust = self.fallback_thrust(call.desired, call.velocity, call.water, call.limit)
        else:
            self.solves += 1
            thrust = (float(outcome[0, 0]), float(outcome[0, 1]))
            self.last_plan_world_n = outcome
        x, y = self._within_limits(thrust, call.previous, call.limit)
        self._last_thrust = (x, y)
        c, s = math.cos(call.heading), math.sin(call.heading)
        body = np.array((c * x + s * y, -s * x + c * y))
        return MpcResult(body, np.array((x, y)), ok, used_fallback, elapsed, status)


@dataclass(frozen=True)
class _Call:
    """One BuoyMpc call's inputs, made finite: velocities (m/s, world), heading (rad), thrust limit and the
    previous thrust scaled into its polygon (N, world)."""

    desired: Pair
    velocity: Pair
    water: Pair
    heading: float
    limit: float
    previous: Pair

    @property
    def solving(self) -> bool:
        """Whether there is thrust to plan with (else the command is zero)."""
        return self.limit > 1e-9


# The eBot's MPC lives in its own module; it is still importable from here.
from bob_autonomy.control.ebot_mpc import DiffDriveMpc as DiffDriveMpc  # noqa: E402
from bob_autonomy.control.ebot_mpc import DiffDriveMpcResult as DiffDriveMpcResult  # noqa: E402
