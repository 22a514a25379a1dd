"""A fleet's buoy MPCs solved together: per step, one call of the QP-data Function and one of the DAQP conic,
both mapped over the vessels with casadi's `Function.map`, instead of two calls per vessel.

Why: in a lockstep fleet each of the 45 solves also paid the Python of its two casadi calls and of filling
their buffers. `python benchmarks/mpc_batch.py` measured the mapped solve at 0.65 of the per-vessel one on
random states (a block-diagonal QP was 16 times slower with OSQP and 680 with DAQP; casadi's "thread" map
was faster alone but slowed the whole fleet step). In the 45-buoy `aggregation` fleet the controllers' share
of a step fell from 7.5 to 6.3 ms (three alternating runs each): DAQP's own work is most of what remains.

What stays the same: each controller prepares its call and makes its command exactly as `BuoyMpc.solve`
does (`_prepare`, `_finish`); the mapped QP data are written with the same float operations as
`BuoyMpc._solve_qp`, and DAQP plans from them are bit for bit the per-vessel ones (DAQP through casadi ignores
the warm start). If any vessel's QP fails, the mapped call raises and that step is solved vessel by vessel,
so every vessel gets what `solve` gives it. Only controllers that can share it are batched: one tuning (the
same casadi Functions), DAQP, and no CPU-time budget (simulated time: a budget is per solve).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from bob_autonomy.control.mpc import BuoyMpc, MpcResult, _Call
from bob_autonomy.control.qp import _BufferedCall, _SolveError, share_one_mapped_call
from bob_autonomy.core.arrays import FloatArray


class BuoyMpcBatch:
    """The mapped QP of `controllers` (all of one tuning, DAQP, without a time budget: see `fits`)."""

    def __init__(self, controllers: Sequence[BuoyMpc]) -> None:
        if not self.fits(controllers):
            raise ValueError("batched buoy MPCs need two or more controllers of one tuning, DAQP and no time budget")
        self.controllers = list(controllers)
        first = self.controllers[0]
        n = len(self.controllers)
        self._data = _BufferedCall(first._data.function.map(n, "serial"))
        self._qp = _BufferedCall(first._qp.function.map(n, "serial"), self._data.outputs, first.solver)
        qp = self._qp.inputs
        qp["a"][:] = np.resize(first._qp.inputs["a"], qp["a"].size)  # the constant constraint matrix, per vessel
        self._p = self._data.inputs["p"].reshape(n, -1)
        self._lbx, self._ubx = qp["lbx"].reshape(n, -1), qp["ubx"].reshape(n, -1)
        self._lba, self._uba = qp["lba"].reshape(n, -1), qp["uba"].reshape(n, -1)
        step = first.max_thrust_change_n / first.model.max_thrust_n
        self._lba[:, first._n_poly :], self._uba[:, first._n_poly :] = -step, step
        self._x = self._qp.outputs["x"].reshape(n, -1)
        self.calls = 0  # mapped calls made
        self.unbatched = 0  # steps solved vessel by vessel after a mapped call failed

    @staticmethod
    def fits(controllers: Sequence[BuoyMpc]) -> bool:
        """Whether these controllers can be solved together (one QP and thrust step: see share_one_mapped_call)."""
        return share_one_mapped_call(controllers, BuoyMpc, lambda c: (c._qp.function, c.max_thrust_change_n))

    def solve(
        self,
        desired_mps: FloatArray,
        velocity_mps: FloatArray,
        water_mps: FloatArray,
        heading_rad: FloatArray,
        max_thrust_n: FloatArray,
    ) -> list[MpcResult]:
        """Each controller's `solve(desired[k], velocity[k], water[k], heading[k], max_thrust[k])` (rows k: (n, 2)
        m/s world, (n,) rad, (n,) N), the previous thrust being each one's last command."""
        controllers = self.controllers
        calls = [
            c._prepare(desired_mps[k], velocity_mps[k], water_mps[k], heading_rad[k], max_thrust_n[k], None)
            for k, c in enumerate(controllers)
        ]
        self._write(calls)
        try:
            self._data()
            self._qp()
        except _SolveError:  # one vessel's QP did not solve: each vessel as `solve` would, its own way
            self.unbatched += 1
            return [c._solve_call(call) for c, call in zip(controllers, calls, strict=True)]
        self.calls += 1
        scale = controllers[0].model.max_thrust_n
        horizon = controllers[0].horizon
        results = []
        for c, call, x in zip(controllers, calls, self._x, strict=True):
            if not call.solving:
                results.append(c._finish(call, None, 0.0))
                continue
            plan = (scale * x).reshape(horizon, 2)
            outcome = plan if math.isfinite(float(plan.sum())) else _SolveError("non-finite solution")
            results.append(c._finish(call, outcome, 0.0))
        return results

    def _write(self, calls: list[_Call]) -> None:
        """The parameters and bounds of every vessel's QP, each value the one `BuoyMpc._solve_qp` writes (a
        vessel without thrust gets a harmless QP whose plan is not used)."""
        first = self.controllers[0]
        scale, ratio = first.model.max_thrust_n, first.inradius_ratio
        step = first.max_thrust_change_n / scale
        limit = np.array([call.limit if call.solving else scale for call in calls])
        previous = np.array([call.previous if call.solving else (0.0, 0.0) for call in calls])
        p = self._p
        p[:, 0:2] = [call.velocity for call in calls]
        p[:, 2:4] = [call.water for call in calls]
        p[:, 4:6] = [call.desired for call in calls]
        prev = previous / scale
        p[:, 6:8] = prev
        box = limit / scale
        self._lbx[:] = -box[:, None]
        self._ubx[:] = box[:, None]
        self._uba[:, : first._n_poly] = (box * ratio)[:, None]
        self._lba[:, : first._n_poly] = (-2.0 * box)[:, None]
        self._lbx[:, :2] = np.maximum(-box[:, None], prev - step)
        self._ubx[:, :2] = np.minimum(box[:, None], prev + step)
