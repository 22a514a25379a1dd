"""A fleet's buoy MPCs solved together: per step, one call of the QP-data Function and one of the DAQP conic,
both mapped over the vessels with casadi's `Function.map`, instead of two calls per vessel.

Why: in a lockstep fleet each of the 45 solves also paid the Python of its two casadi calls and of filling
their buffers. `python benchmarks/mpc_batch.py` measured the mapped solve at 0.65 of the per-vessel one on
random states (a block-diagonal QP was 16 times slower with OSQP and 680 with DAQP; casadi's "thread" map
was faster alone but slowed the whole fleet step). In the 45-buoy `aggregation` fleet the controllers' share
of a step fell from 7.5 to 6.3 ms (three alternating runs each): DAQP's own work is most of what remains.

What stays the same: the fleet's inputs are made finite, and its commands limited and turned into the body
frames, row by row in numpy with the float operations of `BuoyMpc._prepare` and `_finish` (what needs math's
functions, the polygon test of a point not well inside the inscribed circle and the heading's cos and sin, is
done by them vessel by vessel); a vessel without thrust or with a non-finite plan goes through its own
`_finish`. The mapped QP data are written with the same float operations as `BuoyMpc._solve_qp`, and DAQP
plans from them are bit for bit the per-vessel ones (DAQP through casadi ignores the warm start). If any
vessel's QP fails, the mapped call raises and that step is solved vessel by vessel, so every vessel gets what
`solve` gives it. Only controllers that can share it are batched: one tuning (the same casadi Functions),
DAQP, and no CPU-time budget (simulated time: a budget is per solve). `thrust` gives the commands as two
(n, 2) arrays without a result object per vessel. On random states of 45 buoys the Python around the mapped
call fell from about 5.1 to 1.1 M instructions per step (callgrind), the mapped call itself being about
19.4 M (DAQP's setup, `update_M` most of it, and its solve; 32.0 M before the polygon's opposite sides were
paired into two-sided rows, `mpc.polygon_rows`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from bob_autonomy.control.mpc import BuoyMpc, MpcResult, _Call
from bob_autonomy.control.qp import Pair, _BufferedCall, _SolveError, share_one_mapped_call
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
        body, world, special = self._solve(desired_mps, velocity_mps, water_mps, heading_rad, max_thrust_n)
        return [
            special[k] if k in special else MpcResult(body[k], world[k], True, False, 0.0, "optimal")
            for k in range(len(self.controllers))
        ]

    def thrust(
        self,
        desired_mps: FloatArray,
        velocity_mps: FloatArray,
        water_mps: FloatArray,
        heading_rad: FloatArray,
        max_thrust_n: FloatArray,
    ) -> tuple[FloatArray, FloatArray]:
        """The commands of `solve` as (n, 2) arrays, body frame (x forward, y left) and world frame, N, without
        building a result per vessel (a lockstep fleet needs only these)."""
        body, world, _ = self._solve(desired_mps, velocity_mps, water_mps, heading_rad, max_thrust_n)
        return body, world

    def _solve(
        self,
        desired_mps: FloatArray,
        velocity_mps: FloatArray,
        water_mps: FloatArray,
        heading_rad: FloatArray,
        max_thrust_n: FloatArray,
    ) -> tuple[FloatArray, FloatArray, dict[int, MpcResult]]:
        """Body and world commands (n, 2) N, and the results of the vessels `BuoyMpc._finish` made alone (no
        thrust, a non-finite plan, or all of them after a failed mapped call), by index.

        The fleet's inputs are made finite and its commands limited with the float operations of `_prepare` and
        `_finish`, row by row in numpy; what needs math's functions (`polygon_peak`, cos and sin of the heading)
        is computed by them, vessel by vessel, so every value is the one `BuoyMpc.solve` gives."""
        n, controllers = len(self.controllers), self.controllers
        desired = _finite(desired_mps, (n, 2))
        velocity = _finite(velocity_mps, (n, 2))
        water = _finite(water_mps, (n, 2))
        heading = _finite(heading_rad, (n,))
        limit = np.asarray(max_thrust_n, dtype=float).reshape(n)
        limit = np.where(np.isfinite(limit) & (limit > 0.0), limit, 0.0)  # max(0.0, finite or 0.0)
        previous = self._into_polygon(np.array([c._last_thrust for c in controllers]).reshape(n, 2), limit)
        solving = limit > 1e-9  # as _Call.solving
        self._write(desired, velocity, water, limit, previous, solving)
        try:
            self._data()
            self._qp()
        except _SolveError:  # one vessel's QP did not solve: each vessel as `solve` would, its own way
            self.unbatched += 1
            special = {
                k: c._solve_call(self._call(k, desired, velocity, water, heading, limit, previous))
                for k, c in enumerate(controllers)
            }
            world = np.array([special[k].thrust_world_n for k in range(n)])
            return self._body(world, heading), world, special
        self.calls += 1
        first = controllers[0]
        plans = (first.model.max_thrust_n * self._x).reshape(n, first.horizon, 2)
        # A row of finite entries each below 1e300 in size has a finite sum (what `_solve_call` checks); only the
        # other rows need their sum.
        flat = plans.reshape(n, -1)
        finite = np.isfinite(flat).all(axis=1) & (np.abs(flat).max(axis=1) < 1e300)
        special = {}
        for k in np.flatnonzero(~(solving & finite)).tolist():
            call = self._call(k, desired, velocity, water, heading, limit, previous)
            if not solving[k]:
                outcome: FloatArray | Exception | None = None
            elif math.isfinite(float(plans[k].sum())):
                outcome = plans[k]
            else:
                outcome = _SolveError("non-finite solution")
            special[k] = controllers[k]._finish(call, outcome, 0.0)
        world = self._within_limits(plans[:, 0, :], previous, limit)
        for k, c, plan, pair in zip(range(n), controllers, plans, world.tolist(), strict=True):
            if k in special:
                world[k] = special[k].thrust_world_n
            else:  # what _finish keeps of a solved plan
                c.solves += 1
                c.last_plan_world_n = plan
                c._last_thrust = (pair[0], pair[1])
        return self._body(world, heading), world, special

    def _write(
        self,
        desired: FloatArray,
        velocity: FloatArray,
        water: FloatArray,
        limit: FloatArray,
        previous: FloatArray,
        solving: NDArray[np.bool_],
    ) -> None:
        """The parameters and bounds of every vessel's QP, each value the one `BuoyMpc._solve_qp` writes (a
        vessel without thrust gets a harmless QP whose plan is not used)."""
        first = self.controllers[0]
        scale, ratio = first.model.max_thrust_n, first.inradius_ratio
        step = first.max_thrust_change_n / scale
        limit = np.where(solving, limit, scale)
        previous = np.where(solving[:, None], previous, 0.0)
        p = self._p
        p[:, 0:2] = velocity
        p[:, 2:4] = water
        p[:, 4:6] = desired
        prev = previous / scale
        p[:, 6:8] = prev
        box = limit / scale
        self._lbx[:] = -box[:, None]
        self._ubx[:] = box[:, None]
        self._uba[:, : first._n_poly] = (box * ratio)[:, None]
        self._lba[:, : first._n_poly] = (box * first.polygon_lower_ratio)[:, None]
        self._lbx[:, :2] = np.maximum(-box[:, None], prev - step)
        self._ubx[:, :2] = np.minimum(box[:, None], prev + step)

    def _into_polygon(self, thrust_n: FloatArray, limit: FloatArray) -> FloatArray:
        """Each row (x, y) N of thrust_n scaled into the polygon of its limit N, as `BuoyMpc._into_polygon` does.

        A point well inside the inscribed circle (x^2 + y^2 below the squared inradius by a factor 1 - 1e-9, far
        more than the round-off of either side; an inradius between 1e-100 and 1e100 N, so that no square
        overflows or loses to underflow what matters) has polygon_peak <= hypot(x, y) < inradius and is kept as
        it is; the others go through the controller's own function."""
        bound = limit * self.controllers[0].inradius_ratio
        x, y = thrust_n[:, 0], thrust_n[:, 1]
        with np.errstate(over="ignore", under="ignore"):  # such rows are left to the controller's function
            inside = (x * x + y * y <= bound * bound * (1.0 - 1e-9)) & (bound >= 1e-100) & (bound <= 1e100)
        out = thrust_n.copy()
        for k in np.flatnonzero(~inside).tolist():
            out[k] = self.controllers[k]._into_polygon(float(x[k]), float(y[k]), float(limit[k]))
        return out

    def _within_limits(self, thrust_n: FloatArray, previous: FloatArray, limit: FloatArray) -> FloatArray:
        """`BuoyMpc._within_limits` of each row (n, 2) N: into the polygon, then the change from previous bounded
        by a convex combination with it."""
        xy = self._into_polygon(thrust_n, limit)
        change = self.controllers[0].max_thrust_change_n
        delta = xy - previous
        largest = np.maximum(np.abs(delta[:, 0]), np.abs(delta[:, 1]))
        over = largest > change
        if over.any():
            fraction = change / largest[over] * (1.0 - 1e-12)
            xy[over] = previous[over] + fraction[:, None] * delta[over]
        return xy

    @staticmethod
    def _body(world: FloatArray, heading: FloatArray) -> FloatArray:
        """(n, 2) world thrust N turned into the body frames of (finite) headings rad, with math's cos and sin as
        `_finish` does."""
        angles = heading.tolist()
        c = np.array([math.cos(a) for a in angles])
        s = np.array([math.sin(a) for a in angles])
        x, y = world[:, 0], world[:, 1]
        return np.column_stack((c * x + s * y, -s * x + c * y))

    @staticmethod
    def _call(
        k: int,
        desired: FloatArray,
        velocity: FloatArray,
        water: FloatArray,
        heading: FloatArray,
        limit: FloatArray,
        previous: FloatArray,
    ) -> _Call:
        """Vessel k's prepared call, the one `BuoyMpc._prepare` makes of the same inputs."""
        return _Call(
            _tuple(desired[k]), _tuple(velocity[k]), _tuple(water[k]), float(heading[k]), float(limit[k]),
            _tuple(previous[k]),
        )  # fmt: skip


def _finite(value: FloatArray, shape: tuple[int, ...]) -> FloatArray:
    """value as a float array of `shape` with non-finite entries replaced by 0 (as qp._pair and _finite_float)."""
    array = np.asarray(value, dtype=float).reshape(shape)
    return np.where(np.isfinite(array), array, 0.0)


def _tuple(row: FloatArray) -> Pair:
    x, y = row.tolist()
    return (x, y)
