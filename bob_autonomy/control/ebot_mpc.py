"""The eBot's MPC (`DiffDriveMpc`): a desired velocity vector turned into wheel speeds within their limit, as a
convex QP (casadi conic, the default) or the unicycle as is (casadi nlpsol). See the class docstring for the
model and the measured comparison; the buoy's MPC and the QP plumbing are in bob_autonomy.control.mpc and
bob_autonomy.control.qp."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from functools import lru_cache

import casadi as ca
import numpy as np

from bob_autonomy.control.qp import (
    _PLUGIN_OPTIONS,
    _BufferedCall,
    _conic,
    _cpu_over_budget,
    _finite_float,
    _SolveError,
    _vector2,
    default_qp_plugin,
)
from bob_autonomy.control.velocity_control import DiffDriveController
from bob_autonomy.core.arrays import FloatArray, finite_pair

logger = logging.getLogger("bob_autonomy.control.mpc")  # the MPCs' one logger (fallbacks are logged there)
# (max wheel speed m/s, wheel base m, dt s, horizon, tracking weight, input change weight): what the QP depends on.
EbotTuning = tuple[float, float, float, int, float, float]


# --------------------------------------------------------------------------- eBot


@dataclass(frozen=True)
class DiffDriveMpcResult:
    """One eBot MPC command.

    wheels_mps: (2,) left and right wheel speeds, m/s, within +-max_wheel_speed_mps.
    ok: the optimization was solved and its first wheel speeds are the command.
    fallback: the heuristic DiffDriveController made the command.
    solve_time_s: wall time of the optimization, s.
    status: "optimal", or why not.
    """

    wheels_mps: FloatArray
    ok: bool
    fallback: bool
    solve_time_s: float
    status: str


class DiffDriveMpc:
    """MPC of the eBot's velocity vector with wheel-speed limits.

    Model (both forms): wheel speeds (l, r) held over each step of dt_s; forward
    speed s = (l + r)/2, yaw rate w = (r - l)/wheel_base; heading
    theta_{k+1} = theta_k + w_k dt; the velocity over step k is s_k e(theta_k +
    w_k dt/2), e(a) = (cos a, sin a). Decision variables: the N wheel pairs
    scaled by max_wheel_speed_mps, bounded by +-1 (simple bounds only). Cost:
    tracking_weight * sum_k |v_k - v_desired|^2 / vmax^2 + input_change_weight
    * sum_k |z_k - z_{k-1}|^2 (z_{-1}: the previous wheel speeds / vmax).
    Everything is written in the frame of the current heading (d = desired
    velocity rotated by -heading; delta_k = theta_k - heading).

    form="linear": the velocity map linearized at the current heading
    (delta = 0) and the nominal speed sbar = +-min(|v_desired|, vmax):
    v_k ~ (s_k, sbar * delta_k), a convex QP (casadi conic, same plugin as
    the buoy), re-linearized every call. sbar takes the sign of the desired
    forward component (reversing is allowed: a velocity vector behind can be
    tracked backwards), keeping the previous sign when that component is small
    (|d_x| < 0.1 |d|) so a sideways wish does not chatter. With forward_only
    (a robot that must face where it goes) sbar > 0 and every step's forward
    speed is constrained to >= 0 (one linear row per step): a wish behind
    makes it pivot on the spot, then drive.
    form="nonlinear": the unicycle model as is, casadi nlpsol (ipopt or
    sqpmethod), warm-started from the previous plan shifted by one step.

    throttle_slew_per_s: the autopilot's throttle slew (MOT_SLEWRATE / 100,
    full-scale units per s; 0: none). A skid-steer rover behind ArduPilot gets
    throttle = (l + r) / 2 (scaled) and steering = (l - r) / 2, and slews the
    throttle only (AP_MotorsUGV::output: slew_limit_throttle, then the skid-steer
    mix). With a slew the plan knows it: each step's throttle changes by at most
    slew x dt_s from the step before (one linear row per step), the first step's
    from the autopilot's output now, which the controller follows as the
    autopilot does (it is called every dt_s); every command, the fallback's too,
    is moved within that reach by shifting both wheels alike (the steering
    kept). `sent` tells it the wheels actually sent when a caller overrode its
    command.

    Measured (benchmarks/mpc_solve.py, this machine): closed loop on an exact
    unicycle, dt 0.1 s, horizon 10, 0.2 m/s wished; mean |v - v_desired| (m/s)
    over the 3 s after the wished direction changes; solve time of the call.

        manoeuvre            heuristic  linear QP  nonlinear IPOPT  nonlinear SQP
        turn 90, from rest     0.032     0.030        0.050            0.200
        turn 90, driving       0.032     0.030        0.030            0.030
        reverse 180, driving   0.058     0.001        0.001            0.001
        turn 135, driving      0.045     0.016        0.043            0.043
        solve median / p99       -       0.04/0.06 ms 3.5/5 ms         0.2/1 ms
        failures (fallbacks)     -       0            0                4 + 10 in 200 random

    The linear form is the default: it is convex, so it always returns the
    global optimum of its model (no failure in the manoeuvres nor in 200
    random calls), it is ~80x cheaper than IPOPT, and it tracks as well or
    better. The nonlinear form is exact but non-convex: from rest, with the
    wish exactly 90 degrees off, the zero plan is a stationary point (no
    gradient either in speed or in heading), so IPOPT returns "optimal" without
    moving for several steps (0.050) and SQP never moves (0.200); at 135
    degrees both keep to the local minimum of a forward U-turn (0.043) where the
    QP backs up (0.016); SQP (DAQP inside, Hessian eigen-clipped) also stops on
    "Search_Direction_Becomes_Too_Small". The price of the linearization is a
    wrong model far from the current heading (it underestimates the turn
    needed), which the re-linearization at every call absorbs.
    """

    DEFAULT_FORM = "linear"

    def __init__(
        self,
        wheel_base_m: float = 0.1,
        max_wheel_speed_mps: float = 0.2,
        dt_s: float = 0.1,
        horizon: int = 10,
        tracking_weight: float = 1.0,
        input_change_weight: float = 0.05,
        form: str | None = None,
        solver: str | None = None,
        nlp_solver: str = "ipopt",
        time_budget_s: float = 0.02,
        throttle_slew_per_s: float = 0.0,
    ) -> None:
        if wheel_base_m <= 0.0 or max_wheel_speed_mps <= 0.0 or dt_s <= 0.0 or horizon < 1:
            raise ValueError("need wheel_base_m, max_wheel_speed_mps, dt_s > 0 and horizon >= 1")
        if not (math.isfinite(throttle_slew_per_s) and throttle_slew_per_s >= 0.0):
            raise ValueError(f"throttle_slew_per_s must be finite and >= 0 (0: none), got {throttle_slew_per_s!r}")
        self.throttle_slew_per_s = float(throttle_slew_per_s)
        self.form = form or self.DEFAULT_FORM
        if self.form not in ("linear", "nonlinear"):
            raise ValueError(f"form must be 'linear' or 'nonlinear', not {self.form!r}")
        self.wheel_base_m = float(wheel_base_m)
        self.max_wheel_speed_mps = float(max_wheel_speed_mps)
        self.dt_s = float(dt_s)
        self.horizon = int(horizon)
        self.tracking_weight = float(tracking_weight)
        self.input_change_weight = float(input_change_weight)
        self.solver = solver or default_qp_plugin()
        self.nlp_solver = nlp_solver
        self.time_budget_s = float(time_budget_s)
        self.heuristic = DiffDriveController(self.wheel_base_m, self.max_wheel_speed_mps)
        self.solves = 0
        self.fallbacks = 0
        self._last_wheels = np.zeros(2)
        self._sign = 1.0
        self._plan = np.zeros(2 * self.horizon)
        self._output = 0.0  # the autopilot's throttle output as its slew follows our commands (scaled)
        self._output_before = 0.0  # ... before the last command (what `sent` follows from again)
        self._fixed_bounds: dict[float, tuple[FloatArray, FloatArray]] = {}  # _row_bounds without a slew
        if self.form == "linear":
            self._build_linear()
        else:
            self._build_nonlinear()
        # Warm-up: the first real call is not the slow one.
        self._solve_plan(self._parameters(np.zeros(2), 0.0, np.zeros(2)))
        self.reset()

    def _model(self, linear: bool) -> dict[str, ca.SX]:
        """Cost of the scaled wheel plan z (2N,) given p = (d (2,) in the heading frame, z_prev (2,), sbar)."""
        return _ebot_problem(self._tuning(), linear, self.throttle_slew_per_s > 0.0)

    def _tuning(self) -> EbotTuning:
        return (
            self.max_wheel_speed_mps,
            self.wheel_base_m,
            self.dt_s,
            self.horizon,
            self.tracking_weight,
            self.input_change_weight,
        )

    def _build_linear(self) -> None:
        """This controller's buffers on the QP's casadi Functions (built once per tuning and shared by a fleet)."""
        slewed = self.throttle_slew_per_s > 0.0
        self.problem, data, conic, constraint_values = _ebot_qp_functions(self._tuning(), self.solver, slewed)
        self._data = _BufferedCall(data)
        self._qp = _BufferedCall(conic, self._data.outputs, self.solver)
        self._qp.inputs["a"][:] = constraint_values
        self._qp.inputs["lbx"][:] = -1.0
        self._qp.inputs["ubx"][:] = 1.0
        self._qp.inputs["lba"][:], self._qp.inputs["uba"][:] = self._row_bounds(-1.0)  # see _row_bounds

    def _build_nonlinear(self) -> None:
        problem = self._model(linear=False)
        options: dict[str, object] = {"print_time": False, "error_on_fail": False}
        if self.nlp_solver == "ipopt":
            options["ipopt"] = {"print_level": 0, "sb": "yes", "max_wall_time": max(self.time_budget_s, 1e-3)}
        elif self.nlp_solver == "sqpmethod":
            # The unicycle's exact Hessian is indefinite away from the optimum: convexify it for the QP.
            qp_plugin = self.solver
            options.update(
                {
                    "qpsol": qp_plugin,
                    "qpsol_options": {"error_on_fail": False, **_PLUGIN_OPTIONS.get(qp_plugin, {})},
                    "convexify_strategy": "eigen-clip",
                    "print_header": False,
                    "print_iteration": False,
                    "print_status": False,
                }
            )
        self._nlp = ca.nlpsol("ebot_mpc_nlp", self.nlp_solver, problem, options)
        self._lbx = -np.ones(2 * self.horizon)
        self._ubx = np.ones(2 * self.horizon)
        self.problem = problem

    def reset(self) -> None:
        """Forget the previous wheel speeds and plan (the robot is at rest)."""
        self._last_wheels = np.zeros(2)
        self._plan = np.zeros(2 * self.horizon)
        self._sign = 1.0
        self._output = self._output_before = 0.0

    def _row_bounds(self, lowest_forward: float) -> tuple[FloatArray, FloatArray]:
        """Bounds of the constraint rows: each step's scaled forward speed (the throttle) at least lowest_forward
        (-1: none, 0: forward only), then with a throttle slew each step's change from the step before within
        slew x dt_s, the first step's from the autopilot's output now. Where forward only asks for more than the
        slew reaches by a step (a robot still backing up), that step gets what the slew reaches: the plan stays
        feasible (a ramp at the slew from the output is)."""
        if self.throttle_slew_per_s <= 0.0:  # fixed per lowest_forward: built once (the arrays are only read)
            bounds = self._fixed_bounds.get(lowest_forward)
            if bounds is None:
                bounds = self._fixed_bounds[lowest_forward] = (
                    np.full(self.horizon, float(lowest_forward)),
                    np.ones(self.horizon),
                )
            return bounds
        lower, upper = np.full(self.horizon, float(lowest_forward)), np.ones(self.horizon)
        reach, out = self.throttle_slew_per_s * self.dt_s, self._output
        upper[0] = min(1.0, out + reach)
        lower[0] = min(max(lowest_forward, out - reach), upper[0])
        ramp = out + reach * np.arange(2, self.horizon + 1)  # the most the slew reaches by steps 1..N-1
        lower[1:] = np.minimum(lower[1:], ramp)
        change = np.full(self.horizon - 1, reach)
        return np.concatenate((lower, -change)), np.concatenate((upper, change))

    def _within_reach(self, wheels: FloatArray) -> FloatArray:
        """`wheels` (m/s) shifted alike (the steering kept) so that their throttle is within one step of slew from
        the autopilot's output now, as far as the wheel limits allow; unchanged without a slew."""
        if self.throttle_slew_per_s <= 0.0:
            return wheels
        vmax, reach = self.max_wheel_speed_mps, self.throttle_slew_per_s * self.dt_s
        throttle = 0.5 * (wheels[0] + wheels[1]) / vmax
        shift = min(max(throttle, self._output - reach), self._output + reach) - throttle
        return _clipped(wheels + shift * vmax, vmax) if shift != 0.0 else wheels

    def _follow(self, wheels: FloatArray) -> None:
        """The autopilot's throttle output after one call period (dt_s) of its slew towards `wheels`' throttle."""
        self._output_before = out = self._output
        throttle = 0.5 * (wheels[0] + wheels[1]) / self.max_wheel_speed_mps
        if self.throttle_slew_per_s <= 0.0:
            self._output = throttle
            return
        reach = self.throttle_slew_per_s * self.dt_s
        self._output = min(max(throttle, out - reach), out + reach)

    def sent(self, wheels_mps: FloatArray) -> None:
        """The wheels (m/s) the robot was sent instead of the last `solve`'s command: the autopilot's throttle
        output follows them (the input-change cost still starts from this controller's own last command)."""
        self._output = self._output_before
        self._follow(_clipped(wheels_mps, self.max_wheel_speed_mps))

    def _parameters(
        self, desired_world: FloatArray, heading: float, previous: FloatArray, forward_only: bool = False
    ) -> FloatArray:
        c, s = math.cos(heading), math.sin(heading)
        along = c * desired_world[0] + s * desired_world[1]
        side = -s * desired_world[0] + c * desired_world[1]
        speed = min(math.hypot(along, side), self.max_wheel_speed_mps)
        if forward_only:
            self._sign = 1.0
        elif abs(along) > 0.1 * math.hypot(along, side):
            self._sign = 1.0 if along > 0.0 else -1.0
        vmax = self.max_wheel_speed_mps
        return np.array((along, side, previous[0] / vmax, previous[1] / vmax, self._sign * speed))

    def _solve_plan(self, parameters: FloatArray, forward_only: bool = False) -> FloatArray:
        """Scaled wheel plan (2N,); raises on a failure. forward_only: no step's forward speed below 0."""
        warm = np.concatenate((self._plan[2:], self._plan[-2:]))
        lowest_forward = 0.0 if forward_only else -1.0
        if forward_only:
            warm = np.clip(warm, -1.0, 1.0)
            backwards = np.minimum(0.0, 0.5 * (warm[0::2] + warm[1::2]))
            warm -= np.repeat(backwards, 2)  # a feasible start: the backward part of each step removed
        lbg, ubg = self._row_bounds(lowest_forward)
        if self.form == "linear":
            self._data.inputs["p"][:] = parameters
            self._data()
            self._qp.inputs["lba"][:], self._qp.inputs["uba"][:] = lbg, ubg
            self._qp.inputs["x0"][:] = warm
            self._qp()  # raises _SolveError when not solved
            return self._qp.outputs["x"].copy()
        solution = self._nlp(x0=warm, p=parameters, lbx=self._lbx, ubx=self._ubx, lbg=lbg, ubg=ubg)
        stats = self._nlp.stats()
        if not stats["success"]:
            raise _SolveError(f"{self.nlp_solver}: {stats.get('return_status')}")
        return np.array(solution["x"], dtype=float).ravel()

    def solve(
        self,
        desired_velocity_mps: FloatArray,
        heading_rad: float,
        previous_wheels_mps: FloatArray | None = None,
        *,
        forward_only: bool = False,
    ) -> DiffDriveMpcResult:
        """Wheel speeds (left, right) for one control step.

        desired_velocity_mps: (2,) world frame, m/s (non-finite: 0); heading_rad:
        estimated heading (non-finite: 0); previous_wheels_mps: (2,) the wheel
        speeds applied last step, m/s; None: those this controller returned last.
        forward_only: never back up (every planned step's forward speed >= 0), for a robot whose body heading
        matters (a behaviour that wished a heading: heading consensus broadcasts the body's heading).
        """
        desired = _vector2(desired_velocity_mps)
        heading = _finite_float(heading_rad, 0.0)
        vmax = self.max_wheel_speed_mps
        previous = self._last_wheels if previous_wheels_mps is None else _vector2(previous_wheels_mps)
        previous = _clipped(previous, vmax)
        self.solves += 1
        ok, used_fallback, status = True, False, "optimal"
        start, cpu = time.perf_counter(), time.thread_time()
        try:
            plan = self._solve_plan(self._parameters(desired, heading, previous, forward_only), forward_only)
            elapsed = time.perf_counter() - start
            if not math.isfinite(float(plan.sum())):  # a NaN or inf anywhere makes the sum non-finite
                raise _SolveError("non-finite solution")
            _cpu_over_budget(time.thread_time() - cpu, self.time_budget_s)
            self._plan = plan
            wheels = vmax * plan[:2]
        except Exception as error:  # any failure of the solve: the robot still gets a command
            elapsed = time.perf_counter() - start
            ok, used_fallback = False, True
            status = f"fallback: {type(error).__name__}: {error}"
            self.fallbacks += 1
            self._plan = np.zeros(2 * self.horizon)
            logger.warning("eBot MPC fallback #%d: %s", self.fallbacks, status)
            wheels = self.heuristic.wheels(desired[None, :], np.array([np.nan]), np.array([heading]))[0]
        wheels = self._within_reach(_clipped(wheels, vmax))
        self._last_wheels = wheels
        self._follow(wheels)
        return DiffDriveMpcResult(wheels, ok, used_fallback, elapsed, status)


def _clipped(wheels_mps: object, limit: float) -> FloatArray:
    """A (2,) float copy clipped to [-limit, limit], non-finite entries by numpy.nan_to_num's rule first (NaN -> 0,
    +-inf -> +-limit): np.clip(np.nan_to_num(w), -limit, limit) without numpy's per-call cost on a 2-vector."""
    left, right = finite_pair(wheels_mps)
    return np.array((min(max(left, -limit), limit), min(max(right, -limit), limit)))


def _ebot_problem(tuning: EbotTuning, linear: bool, slewed: bool = False) -> dict[str, ca.SX]:
    """DiffDriveMpc's problem for its tuning (DiffDriveMpc._tuning): the cost of the scaled wheel plan z (2N,) given
    p = (d (2,) in the heading frame, z_prev (2,), sbar), and g the scaled forward speed (the throttle) of each step,
    then when `slewed` each step's throttle change from the step before (N - 1 rows)."""
    vmax, base, dt, horizon, tracking_weight, input_change_weight = tuning
    z = ca.SX.sym("z", 2 * horizon)
    p = ca.SX.sym("p", 5)
    desired, z_prev, nominal = p[0:2], p[2:4], p[4]
    cost, delta, previous = 0, 0, z_prev
    for k in range(horizon):
        zk = z[2 * k : 2 * k + 2]
        forward = vmax * 0.5 * (zk[0] + zk[1])
        turn = vmax * (zk[1] - zk[0]) / base * dt
        mid = delta + 0.5 * turn
        # linear: first order at (s, delta) = (sbar, 0); nonlinear: the unicycle as is.
        exact = forward * ca.vertcat(ca.cos(mid), ca.sin(mid))
        velocity = ca.vertcat(forward, nominal * mid) if linear else exact
        cost += tracking_weight * ca.sumsqr(velocity - desired) / vmax**2
        cost += input_change_weight * ca.sumsqr(zk - previous)
        delta, previous = delta + turn, zk
    # g: the forward speed of each step, scaled (>= 0 when the robot must face along its wish).
    forward = [0.5 * (z[2 * k] + z[2 * k + 1]) for k in range(horizon)]
    changes = [forward[k] - forward[k - 1] for k in range(1, horizon)] if slewed else []
    return {"x": z, "p": p, "f": cost, "g": ca.vertcat(*forward, *changes)}


@lru_cache(maxsize=32)
def _ebot_qp_functions(
    tuning: EbotTuning, solver: str, slewed: bool = False
) -> tuple[dict[str, ca.SX], ca.Function, ca.Function, FloatArray]:
    """(problem, QP data Function p -> (h, g), conic solver, constraint matrix nonzeros) of the linear
    DiffDriveMpc (`slewed`: with the throttle change rows)."""
    problem = _ebot_problem(tuning, True, slewed)
    z, p, cost = problem["x"], problem["p"], problem["f"]
    hessian = ca.hessian(cost, z)[0]
    gradient = ca.substitute(ca.gradient(cost, z), z, ca.DM.zeros(z.shape[0]))
    constraints = ca.jacobian(problem["g"], z)
    data = ca.Function("ebot_mpc_qp_data", [p], [hessian, gradient], ["p"], ["h", "g"], {"cse": True})
    conic = _conic("ebot_mpc_qp", solver, hessian.sparsity(), constraints.sparsity())
    return problem, data, conic, np.array(ca.evalf(constraints).nonzeros(), dtype=float)
