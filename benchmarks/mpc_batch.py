"""The 45 buoy MPC solves of one lockstep step: one by one, through casadi's `map`, as one block-diagonal QP
(issue 13 asks which pays), or as a lockstep fleet solves them today: the unconstrained minimisers first.

Every option solves the same QPs: 45 `BuoyMpc` controllers of one tuning (dt 0.5 s, horizon 10, 16-sided
thrust polygon), at --steps seeded random states per vessel (velocity, desired velocity, water velocity,
thrust limit 20-45 N). Timed per step of 45 solves (median over the steps, ms):

    solve        BuoyMpc.solve() per vessel, as BuoyPipeline.thrust calls it: Python around each solve
                 (inputs checked, polygon, warm start, limits, result) and the two casadi calls
    calls        BuoyMpc._solve_qp per vessel: its buffers filled and the QP-data Function and the DAQP conic
                 called, without the rest of solve()
    map_serial   the data Function and the conic mapped over the 45 vessels (Function.map, "serial"): one
                 call each per step
    map_thread   the same with casadi's "thread" map over 2 threads
    block_osqp   one QP of 900 variables, the 45 blocks on the diagonal, solved by OSQP (sparse)
    block_daqp   the same by DAQP (dense; --block-steps steps only)
    interior     the data Function mapped, the 45 unconstrained minimisers in one stacked solve, and the DAQP
                 conic for those that break a bound (bob_autonomy.control.qp_interior, what BuoyMpcBatch does)

The references `solve` and `calls` always call DAQP (the controllers' interior path switched off). The mapped
plans are checked equal to theirs bit for bit (the same solver on the same data); the block-diagonal and
interior ones are reported as their largest difference from them (N), with the interior share of the QPs.

    python benchmarks/mpc_batch.py [--steps 100] [--block-steps 2] [--seed 3]
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from collections.abc import Callable

import casadi as ca
import numpy as np

from bob_autonomy.control.mpc import BuoyMpc, _buoy_qp_functions
from bob_autonomy.control.qp import _PLUGIN_OPTIONS, _BufferedCall
from bob_autonomy.control.qp_interior import InteriorMinimiser

VESSELS = 45


def random_states(steps: int, seed: int) -> list[np.ndarray]:
    """Per step, (45, 7): desired velocity (2), velocity (2), water velocity (2) m/s, thrust limit N."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(steps):
        state = np.empty((VESSELS, 7))
        state[:, 0:2] = rng.uniform(-0.8, 0.8, (VESSELS, 2))
        state[:, 2:4] = rng.uniform(-0.8, 0.8, (VESSELS, 2))
        state[:, 4:6] = rng.normal(0.0, 0.1, (VESSELS, 2))
        state[:, 6] = rng.uniform(20.0, 45.0, VESSELS)
        out.append(state)
    return out


def timed(step: Callable[[np.ndarray], np.ndarray], states: list[np.ndarray]) -> tuple[float, list[np.ndarray]]:
    """Median ms per step, and each step's (45, 20) plans."""
    times, plans = [], []
    for state in states:
        start = time.perf_counter()
        plans.append(step(state))
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times), plans


class Batch:
    """The QP data of 45 vessels written into one set of arrays (vessel-major), for the mapped and
    block-diagonal solves: parameters p (v0, water, desired, previous z = 0) and the bounds of one limit each."""

    def __init__(self, mpc: BuoyMpc, data: _BufferedCall, qp: _BufferedCall, constraint_values: np.ndarray) -> None:
        self.mpc, self.data, self.qp = mpc, data, qp
        self.scale = mpc.model.max_thrust_n
        qp.inputs["a"][:] = np.resize(constraint_values, qp.inputs["a"].size)
        self.n_poly = mpc._n_poly
        step = mpc.max_thrust_change_n / self.scale
        self.lba, self.uba = qp.inputs["lba"].reshape(VESSELS, -1), qp.inputs["uba"].reshape(VESSELS, -1)
        self.lba[:, self.n_poly :], self.uba[:, self.n_poly :] = -step, step
        self.lbx, self.ubx = qp.inputs["lbx"].reshape(VESSELS, -1), qp.inputs["ubx"].reshape(VESSELS, -1)
        self.p = data.inputs["p"].reshape(VESSELS, 8)

    def write(self, state: np.ndarray) -> None:
        step = self.mpc.max_thrust_change_n / self.scale
        box = state[:, 6] / self.scale
        self.p[:, 0:2], self.p[:, 2:4], self.p[:, 4:6], self.p[:, 6:8] = (
            state[:, 2:4],
            state[:, 4:6],
            state[:, 0:2],
            0.0,
        )
        self.lbx[:], self.ubx[:] = -box[:, None], box[:, None]
        self.lbx[:, :2] = np.maximum(-box, -step)[:, None]
        self.ubx[:, :2] = np.minimum(box, step)[:, None]
        self.uba[:, : self.n_poly] = (box * self.mpc.inradius_ratio)[:, None]
        self.lba[:, : self.n_poly] = (box * self.mpc.polygon_lower_ratio)[:, None]


def per_vessel_calls(mpcs: list[BuoyMpc]) -> Callable[[np.ndarray], np.ndarray]:
    def step(state: np.ndarray) -> np.ndarray:
        out = np.empty((VESSELS, 2 * mpcs[0].horizon))
        for k, mpc in enumerate(mpcs):
            mpc._solve_qp(tuple(state[k, 0:2]), tuple(state[k, 2:4]), tuple(state[k, 4:6]), state[k, 6], (0.0, 0.0))
            out[k] = mpc._qp.outputs["x"]
        return out

    return step


def solve_calls(mpcs: list[BuoyMpc]) -> Callable[[np.ndarray], np.ndarray]:
    def step(state: np.ndarray) -> np.ndarray:
        for k, mpc in enumerate(mpcs):
            mpc.reset()
            mpc.solve(state[k, 0:2], state[k, 2:4], state[k, 4:6], 0.0, state[k, 6])
        return np.array([mpc._qp.outputs["x"] for mpc in mpcs])

    return step


def mapped(mpc: BuoyMpc, data: ca.Function, conic: ca.Function, values: np.ndarray, threads: int) -> Callable:
    how = ("serial",) if threads == 1 else ("thread", threads)
    data_call = _BufferedCall(data.map(VESSELS, *how))
    qp_call = _BufferedCall(conic.map(VESSELS, *how), data_call.outputs)
    batch = Batch(mpc, data_call, qp_call, values)

    def step(state: np.ndarray) -> np.ndarray:
        batch.write(state)
        data_call()
        qp_call()
        return qp_call.outputs["x"].reshape(VESSELS, -1).copy()

    return step


def interior_first(mpc: BuoyMpc, data: ca.Function, conic: ca.Function, values: np.ndarray, share: list) -> Callable:
    """What BuoyMpcBatch does: minimisers at once, DAQP (one vessel's conic) for those breaking a bound. `share`
    collects the interior fraction of each step."""
    data_call = _BufferedCall(data.map(VESSELS, "serial"))
    bounds = _BufferedCall(conic.map(VESSELS, "serial"), data_call.outputs)  # its arrays only hold the bounds
    batch = Batch(mpc, data_call, bounds, values)
    one = _BufferedCall(conic)
    one.inputs["a"][:] = values
    minimiser = InteriorMinimiser(data.sparsity_out("h"), conic.sparsity_in(conic.index_in("a")), values)

    def step(state: np.ndarray) -> np.ndarray:
        batch.write(state)
        data_call()
        h, g = data_call.outputs["h"].reshape(VESSELS, -1), data_call.outputs["g"].reshape(VESSELS, -1)
        x, inside = minimiser.solve(h, g, batch.lbx, batch.ubx, batch.lba, batch.uba)
        for k in np.flatnonzero(~inside).tolist():
            for name, rows in (("h", h), ("g", g), ("lbx", batch.lbx), ("ubx", batch.ubx), ("lba", batch.lba),
                               ("uba", batch.uba)):  # fmt: skip
                one.inputs[name][:] = rows[k]
            one()
            x[k] = one.outputs["x"]
        share.append(float(inside.mean()))
        return x

    return step


def block_diagonal(mpc: BuoyMpc, data: ca.Function, conic: ca.Function, values: np.ndarray, plugin: str) -> Callable:
    hessian = ca.diagcat(*[data.sparsity_out(0)] * VESSELS)
    constraints = ca.diagcat(*[conic.sparsity_in(conic.index_in("a"))] * VESSELS)
    big = ca.conic(f"block_{plugin}", plugin, {"h": hessian, "a": constraints}, dict(_PLUGIN_OPTIONS.get(plugin, {})))
    data_call = _BufferedCall(data.map(VESSELS, "serial"))
    qp_call = _BufferedCall(big)
    batch = Batch(mpc, data_call, qp_call, values)

    def step(state: np.ndarray) -> np.ndarray:
        batch.write(state)
        data_call()
        qp_call.inputs["h"][:] = data_call.outputs["h"]  # the blocks' nonzeros, column by column: the same order
        qp_call.inputs["g"][:] = data_call.outputs["g"]
        qp_call()
        return qp_call.outputs["x"].reshape(VESSELS, -1).copy()

    return step


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--block-steps", type=int, default=2, help="steps for the block-diagonal DAQP solve (slow)")
    parser.add_argument("--seed", type=int, default=3)
    args = parser.parse_args()
    states = random_states(args.steps, args.seed)
    mpcs = [BuoyMpc(time_budget_s=math.inf) for _ in range(VESSELS)]
    for mpc in mpcs:
        mpc._interior = None  # the references call DAQP for every QP
    m = mpcs[0]
    tuning = (m.model, m.dt_s, m.horizon, m.polygon_sides, m.tracking_weight, m.input_change_weight, m.solver)
    _, data, conic, values = _buoy_qp_functions(*tuning)

    ms: dict[str, float] = {}
    ms["solve"], _ = timed(solve_calls(mpcs), states)
    ms["calls"], reference = timed(per_vessel_calls(mpcs), states)
    checks: dict[str, float] = {}
    for name, threads in (("map_serial", 1), ("map_thread", 2)):
        ms[name], plans = timed(mapped(m, data, conic, values, threads), states)
        checks[name] = max(float(np.max(np.abs(a - b))) for a, b in zip(plans, reference, strict=True))
    for name, plugin, steps in (("block_osqp", "osqp", args.steps), ("block_daqp", "daqp", args.block_steps)):
        if not ca.has_conic(plugin):
            continue
        ms[name], plans = timed(block_diagonal(m, data, conic, values, plugin), states[:steps])
        checks[name] = m.model.max_thrust_n * max(
            float(np.max(np.abs(a - b))) for a, b in zip(plans, reference, strict=False)
        )
    share: list[float] = []
    ms["interior"], plans = timed(interior_first(m, data, conic, values, share), states)
    checks["interior"] = m.model.max_thrust_n * max(
        float(np.max(np.abs(a - b))) for a, b in zip(plans, reference, strict=True)
    )
    for name, value in ms.items():
        print(f"{name:>11}: {value:8.2f} ms per step of {VESSELS} solves ({value / ms['solve']:.2f} x solve())")
    print(f"mapped plans equal to the per-vessel ones: {checks['map_serial'] == checks['map_thread'] == 0.0}")
    print(f"interior: {100 * statistics.mean(share):.1f} % of the QPs had no active bound")
    figures = {"ms_per_step": ms, "max_difference": checks, "interior_share": statistics.mean(share)}
    print(json.dumps({"benchmark": "mpc_batch", "vessels": VESSELS, **figures}))


if __name__ == "__main__":
    main()
