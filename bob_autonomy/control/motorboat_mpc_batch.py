"""A fleet's motorboat MPCs solved together: per step one call each of the QP-data Function, the DAQP conic and
the plan-speeds Function, all mapped over the boats with casadi's `Function.map`, instead of three per boat.

Why: in a lockstep fleet of 45 motorboats the controllers took about 45 % of a direct-link step
(`aggregation-motorboats`, cProfile), and about two thirds of that was the Python around each boat's three
casadi calls and the filling of their buffers, not the solver (docs/performance.md, "Motorboats").

What stays the same: each controller makes its references and its command exactly as `MotorboatMpc.solve`
does (`_prepare`, `_finish`); the mapped QP data are written with the values `MotorboatMpc._solve_qp` writes,
so the plans, the next linearisation points and the commands are the per-boat ones bit for bit
(tests/test_motorboat_mpc_batch.py). If the mapped call fails (one boat's QP not solved), that step is
solved boat by boat, so every boat gets what `solve` gives it. Only controllers that can share the call are
batched: one model and tuning (the same casadi Functions), DAQP, and no CPU-time budget (simulated time).
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
        self._qp = _BufferedCall(first._qp.function.map(n, "serial"), self._data.outputs, first.solver)
        self._speeds = _BufferedCall(first._speeds.function.map(n, "serial"))
        qp = self._qp.inputs
        qp["a"][:] = np.resize(first._qp.inputs["a"], qp["a"].size)  # the constant constraint matrix, per boat
        self._step = first.model.steering_slew_per_s * first.step_s  # steering change per plan step, at most
        # The change rows' bounds (steering, then thrust with a throttle slew), per boat.
        qp["lba"][:] = np.resize(first._qp.inputs["lba"], qp["lba"].size)
        qp["uba"][:] = np.resize(first._qp.inputs["uba"], qp["uba"].size)
        self._p = self._data.inputs["p"].reshape(n, -1)
        self._lbx, self._ubx = qp["lbx"].reshape(n, -1), qp["ubx"].reshape(n, -1)
        self._x = self._qp.outputs["x"].reshape(n, -1)
        self._throttles = self._speeds.inputs["i0"].reshape(n, -1)
        self._u0 = self._speeds.inputs["i1"]
        self._planned = self._speeds.outputs["o0"].reshape(n, -1)
        self.calls = 0  # mapped calls made
        self.unbatched = 0  # steps solved boat by boat after a mapped call failed

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
            self._qp()
            self._throttles[:] = self._x[:, : self._x.shape[1] // 2]
            self._speeds()
        except _SolveError:  # one boat's QP did not solve: each boat as `solve` would, its own way
            self.unbatched += 1
            return [call if isinstance(call, MotorboatCommand) else c._solve_call(call) for c, call in
                    zip(controllers, calls, strict=True)]  # fmt: skip
        self.calls += 1
        horizon = controllers[0].horizon
        commands: list[MotorboatCommand] = []
        for k, (c, call) in enumerate(zip(controllers, calls, strict=True)):
            if isinstance(call, MotorboatCommand):
                commands.append(call)
                continue
            x = self._x[k]
            plan = np.column_stack((x[:horizon], x[horizon:]))  # as `MotorboatMpc._solve_qp` returns it
            if not np.isfinite(plan).all():
                commands.append(c._finish(call, _SolveError("non-finite solution"), 0.0))
                continue
            c.last_plan = plan
            c._bar[:] = self._planned[k]
            commands.append(c._finish(call, plan, 0.0))
        return commands

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
