"""A fleet's motorboat MPCs solved together: per step one call each of the QP-data Function and the plan-speeds
Function, both mapped over the boats with casadi's `Function.map`, the unconstrained minimisers of all the QPs in
one stacked numpy solve (`bob_autonomy.control.qp_interior`), and the solver (DAQP) only for the boats whose
minimiser breaks a bound.

Why: in a lockstep fleet of 45 motorboats the controllers took about 45 % of a direct-link step
(`aggregation-motorboats`, cProfile), and about two thirds of that was the Python around each boat's three
casadi calls and the filling of their buffers, not the solver (docs/performance.md, "Motorboats"). Of what
remained, most was DAQP's set-up, paid even by the QPs no bound constrains (84 % of them in
`aggregation-motorboats`, 70 % in `leader-follower-motorboats`).

What stays the same: each controller makes its references and its command exactly as `MotorboatMpc.solve`
does (`_prepare`, `_finish`); the mapped QP data are written with the values `MotorboatMpc._solve_qp` writes,
the interior test gives each row what it gives one QP alone, and a boat with an active bound is solved by its
own `_solve_qp`, so the plans, the next linearisation points and the commands are the per-boat ones bit for
bit (tests/test_motorboat_mpc_batch.py). A boat whose solve fails gets its own fallback; if a mapped call
fails, that step is solved boat by boat. Only controllers that can share the calls are batched: one model and
tuning (the same casadi Functions), DAQP, and no CPU-time budget (simulated time).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from bob_autonomy.control.motorboat_control import MotorboatCommand, MotorboatMpc, _BoatCall
from bob_autonomy.control.qp import _BufferedCall, _SolveError, share_one_mapped_call
from bob_autonomy.core.arrays import FloatArray

# What a boat with nothing to solve this step is given (its plan is not used): the inputs of the warm-up solve.
_IDLE_DATA = (0.0, 0.0, 0.5, 1.0, 1.0, 0.0, 0.0)
_IDLE_BOUNDS = (-0.5, 1.0)


def _shared(c: MotorboatMpc) -> tuple:
    """What boats solved in one call must share: their QP data, conic and plan-speeds Functions, and the most
    steering change per plan step."""
    return c._qp.function, c._data.function, c._speeds.function, c.model.steering_slew_per_s * c.step_s


class MotorboatMpcBatch:
    """The mapped QP of `controllers` (all of one model and tuning, DAQP, without a time budget: see `fits`)."""

    def __init__(self, controllers: Sequence[MotorboatMpc]) -> None:
        if not self.fits(controllers):
            raise ValueError(
                "batched motorboat MPCs need two or more controllers of one model and tuning, DAQP and no time budget"
            )
        self.controllers = list(controllers)
        first = self.controllers[0]
        n = len(self.controllers)
        self._data = _BufferedCall(first._data.function.map(n, "serial"))
        self._speeds = _BufferedCall(first._speeds.function.map(n, "serial"))
        self._step = first.model.steering_slew_per_s * first.step_s  # steering change per plan step, at most
        qp = first._qp.inputs
        # The change rows' bounds (steering, then thrust with a throttle slew), per boat.
        self._lba, self._uba = np.tile(qp["lba"], (n, 1)), np.tile(qp["uba"], (n, 1))
        self._p = self._data.inputs["p"].reshape(n, -1)
        self._h, self._g = self._data.outputs["h"].reshape(n, -1), self._data.outputs["g"].reshape(n, -1)
        self._lbx, self._ubx = np.zeros((n, qp["lbx"].size)), np.zeros((n, qp["ubx"].size))
        self._throttles = self._speeds.inputs["i0"].reshape(n, -1)
        self._u0 = self._speeds.inputs["i1"]
        self._planned = self._speeds.outputs["o0"].reshape(n, -1)
        self.calls = 0  # steps solved together
        self.unbatched = 0  # steps solved boat by boat after a mapped call failed
        self.interior = 0  # QPs whose unconstrained minimiser met every bound
        self.solver_calls = 0  # QPs with an active bound, each handed to its boat's solver

    @staticmethod
    def fits(controllers: Sequence[MotorboatMpc]) -> bool:
        """Whether these controllers can be solved together (the same Functions and steering slew: see
        share_one_mapped_call)."""
        return share_one_mapped_call(controllers, MotorboatMpc, _shared)

    def solve(
        self,
        desired_mps: FloatArray,
        velocity_mps: FloatArray,
        water_mps: FloatArray,
        heading_rad: FloatArray,
        yaw_rate_radps: FloatArray,
        max_throttle: FloatArray,
        t_s: float | None = None,
    ) -> list[MotorboatCommand]:
        """Each controller's `solve(desired[k], velocity[k], water[k], heading[k], yaw_rate[k], max_throttle[k],
        t_s)` (rows k: (n, 2) m/s world, (n,) rad, rad/s and throttle in [0, 1])."""
        controllers = self.controllers
        calls = [
            c._prepare(desired_mps[k], velocity_mps[k], water_mps[k], heading_rad[k], yaw_rate_radps[k],
                       max_throttle[k], t_s)
            for k, c in enumerate(controllers)
        ]  # fmt: skip
        if not any(isinstance(call, _BoatCall) for call in calls):
            return calls  # every boat holds: nothing to solve
        self._write(calls)
        try:
            self._data()
        except _SolveError:  # one boat's QP data could not be made: each boat as `solve` would, its own way
            return self._one_by_one(calls)
        x, inside = controllers[0]._interior.solve(self._h, self._g, self._lbx, self._ubx, self._lba, self._uba)
        failed: dict[int, Exception] = {}
        solving = [k for k, call in enumerate(calls) if isinstance(call, _BoatCall)]
        for k in solving:
            if inside[k]:
                continue
            call = calls[k]
            try:  # a bound is active: this boat's own solve
                plan = controllers[k]._solve_qp(call.u0, call.r0, call.error, call.reference, call.bounds)
            except Exception as error:  # as `_solve_call`: the boat gets its own fallback
                failed[k] = error
                continue
            x[k] = plan.T.reshape(-1)  # (thrust..., steering...) as the solver's x
        self.interior += int(inside[solving].sum())
        self.solver_calls += len(solving) - int(inside[solving].sum())
        self._throttles[:] = x[:, : x.shape[1] // 2]
        try:
            self._speeds()
        except _SolveError:
            return self._one_by_one(calls)
        self.calls += 1
        horizon = controllers[0].horizon
        commands: list[MotorboatCommand] = []
        for k, (c, call) in enumerate(zip(controllers, calls, strict=True)):
            if isinstance(call, MotorboatCommand):
                commands.append(call)
                continue
            if k in failed:
                commands.append(c._finish(call, failed[k], 0.0))
                continue
            plan = np.column_stack((x[k, :horizon], x[k, horizon:]))  # as `MotorboatMpc._solve_qp` returns it
            if not np.isfinite(plan).all():
                commands.append(c._finish(call, _SolveError("non-finite solution"), 0.0))
                continue
            c.interior_solves += bool(inside[k])
            c.last_plan = plan
            c._bar[:] = self._planned[k]
            commands.append(c._finish(call, plan, 0.0))
        return commands

    def _one_by_one(self, calls: list[MotorboatCommand | _BoatCall]) -> list[MotorboatCommand]:
        """Each boat's command as its own `solve` makes it (a mapped call failed)."""
        self.unbatched += 1
        return [call if isinstance(call, MotorboatCommand) else c._solve_call(call) for c, call in
                zip(self.controllers, calls, strict=True)]  # fmt: skip

    def _write(self, calls: list[MotorboatCommand | _BoatCall]) -> None:
        """The parameters and bounds of every boat's QP and the start speed of its plan, each value the one
        `MotorboatMpc._solve_qp` and `_solve_call` write (a boat without a QP gets the warm-up's)."""
        step = self._step
        for k, (c, call) in enumerate(zip(self.controllers, calls, strict=True)):
            p, lbx, ubx = self._p[k], self._lbx[k], self._ubx[k]
            n = c.horizon
            if isinstance(call, _BoatCall):
                direction = -1.0 if call.reference < 0 else 1.0
                p[:7] = (call.u0, call.r0, call.error, call.reference, direction, *c._previous)
                p[7 : 7 + n] = c._bar
                lbx[:n], ubx[:n] = call.bounds
                lbx[0], ubx[0] = c.first_thrust_bounds(call.bounds)
                previous = c._previous[1]
                self._u0[k] = call.u0
            else:
                p[:7] = _IDLE_DATA
                p[7 : 7 + n] = 0.0
                lbx[:n], ubx[:n] = _IDLE_BOUNDS
                previous = 0.0
                self._u0[k] = 0.0
            lbx[n:], ubx[n:] = -1.0, 1.0
            lbx[n], ubx[n] = max(-1.0, previous - step), min(1.0, previous + step)
