"""A fleet's buoy MPCs solved together: per step, one call of the QP-data Function mapped over the vessels with
casadi's `Function.map`, the unconstrained minimisers of all their QPs in one stacked numpy solve
(`bob_autonomy.control.qp_interior`), and the solver (DAQP) only for the vessels whose minimiser breaks a bound.

Why: in a lockstep fleet each of the 45 solves paid the Python of its two casadi calls and of filling their
buffers; a mapped call of both cut that (`python benchmarks/mpc_batch.py`: 0.65 of the per-vessel time on random
states; a block-diagonal QP was 16 times slower with OSQP and 680 with DAQP). What remained was DAQP's own set-up
(about 19.4 M instructions per step, a quarter of a full-stack step), paid even by the 98 % of the QPs that no
bound constrains: those now cost a row of a stacked linear solve.

What stays the same: each vessel gets, bit for bit, what its own `BuoyMpc.solve` gives it (tests/
test_buoy_mpc_batch.py). The fleet's inputs are made finite, and its commands limited and turned into the body
frames, row by row in numpy with the float operations of `BuoyMpc._prepare` and `_finish` (what needs math's
functions, the polygon test of a point not well inside the inscribed circle and the heading's cos and sin, is
done by them vessel by vessel); a vessel without thrust or with a non-finite plan goes through its own
`_finish`. The mapped QP data are written with the same float operations as `BuoyMpc._solve_qp`, the interior
test gives each row what it gives one QP alone, and a vessel with an active bound is solved by its own
controller's `_solve_qp` (a failure there is its own fallback). Only controllers that can share a call are
batched: one tuning (the same casadi Functions), DAQP, and no CPU-time budget (simulated time: a budget is per
solve). `thrust` gives the commands as two (n, 2) arrays without a result object per vessel.
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
        self._p = self._data.inputs["p"].reshape(n, -1)
        self._h = self._data.outputs["h"].reshape(n, -1)
        self._g = self._data.outputs["g"].reshape(n, -1)
        qp = first._qp.inputs
        self._lbx, self._ubx = np.zeros((n, qp["lbx"].size)), np.zeros((n, qp["ubx"].size))
        self._lba, self._uba = np.zeros((n, qp["lba"].size)), np.zeros((n, qp["uba"].size))
        step = first.max_thrust_change_n / first.model.max_thrust_n
        self._lba[:, first._n_poly :], self._uba[:, first._n_poly :] = -step, step
        self.calls = 0  # steps solved together
        self.interior = 0  # QPs whose unconstrained minimiser met every bound
        self.solver_calls = 0  # QPs with an active bound, each handed to its controller's solver

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
        thrust, a failed solve or a non-finite plan), by index.

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
        self._data()
        first = controllers[0]
        x, inside = first._interior.solve(self._h, self._g, self._lbx, self._ubx, self._lba, self._uba)
        plans = (first.model.max_thrust_n * x).reshape(n, first.horizon, 2)
        special: dict[int, MpcResult] = {}
        for k in np.flatnonzero(solving & ~inside).tolist():  # a bound is active: this vessel's own solve
            call = self._call(k, desired, velocity, water, heading, limit, previous)
            try:
                plans[k] = controllers[k]._solve_qp(call.desired, call.velocity, call.water, call.limit, call.previous)
            except Exception as error:  # as `_solve_call`: the vessel gets its own fallback
                special[k] = controllers[k]._finish(call, error, 0.0)
        self.interior += int(np.count_nonzero(solving & inside))
        self.solver_calls += int(np.count_nonzero(solving & ~inside))
        self.calls += 1
        # A row of finite entries each below 1e300 in size has a finite sum (what `_solve_call` checks); only the
        # other rows need their sum.
        flat = plans.reshape(n, -1)
        finite = np.isfinite(flat).all(axis=1) & (np.abs(flat).max(axis=1) < 1e300)
        for k in np.flatnonzero(~(solving & finite)).tolist():
            if k in special:
                continue
            call = self._call(k, desired, velocity, water, heading, limit, previous)
            if not solving[k]:
                outcome: FloatArray | Exception | None = None
            elif math.isfinite(float(plans[k].sum())):
                outcome = plans[k]
            else:
                outcome = _SolveError("non-finite solution")
            special[k] = controllers[k]._finish(call, outcome, 0.0)
        world = self._within_limits(plans[:, 0, :], previous, limit)
        for k, c, plan, pair, free in zip(range(n), controllers, plans, world.tolist(), inside.tolist(), strict=True):
            if k in special:
                world[k] = special[k].thrust_world_n
            else:  # what _finish keeps of a solved plan
                c.solves += 1
                c.interior_solves += free
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
