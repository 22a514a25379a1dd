"""Cost of one MPC call from Python, and the eBot MPC's linear vs nonlinear forms.

Buoy: `BuoyMpc` drives the SITL's truth dynamics (`sitl.vehicles.dynamics.BuoyDynamics`,
with current, wind and its drift, and the nozzle's slew limit) for --steps
control steps of 0.5 s over a seeded sequence of random desired velocities
(a new one every 10-30 s, up to 0.8 m/s), drifts that change every 60 s, and
occasional weak-battery spells; the velocity and heading it is given carry
estimator-like noise. Timed: the whole `solve()` call from Python (median, p99 of the wall time; and of
the thread's CPU time, which tells a slow call from a preempted one).
Then a profile of that call (the QP-data Function, the conic solver's own wall
time, the rest in Python), the same QP on every available QP plugin, and the
same problem solved by IPOPT (casadi nlpsol, built once) for --ipopt-steps
calls from the same states.

eBot: `DiffDriveMpc` in its linear (QP) and nonlinear (unicycle; IPOPT and
sqpmethod) forms, and the heuristic `DiffDriveController`, in closed loop with
an exact unicycle at dt 0.1 s and 0.2 m/s desired: the desired direction turns
by 90 degrees (from rest, and while driving), reverses (180), and turns by 135;
mean velocity error |v - v_desired| over the 3 s after the change, fallbacks,
and solve time; plus --random-calls random calls for failures.

Also the construction cost of each controller (solver build and warm-up, paid once per process).

Prints a readable report and, last, one JSON line.

    python benchmarks/mpc_solve.py [--steps 2000] [--ipopt-steps 200] [--seed 7]
"""

from __future__ import annotations

import argparse
import json
import math
import time

import casadi as ca
import numpy as np

from bob_autonomy.control.ebot_mpc import DiffDriveMpc, _ebot_qp_functions
from bob_autonomy.control.mpc import BuoyMpc, _buoy_qp_functions
from bob_autonomy.control.qp import QP_PLUGINS
from bob_autonomy.control.velocity_control import BuoyVelocityController, DiffDriveController
from sitl.vehicles.dynamics import BuoyDynamics, BuoyParams

DT_S = 0.5
EBOT_DT_S = 0.1


def buoy_sequence(steps: int, seed: int) -> list[dict[str, np.ndarray | float]]:
    """Per step: desired velocity, current, wind (m/s, world) and the thrust limit (N)."""
    rng = np.random.default_rng(seed)
    full = BuoyParams().max_thrust_n
    out: list[dict[str, np.ndarray | float]] = []
    desired = np.zeros(2)
    current = np.zeros(2)
    wind = np.zeros(2)
    limit = full
    next_desired = 0
    for k in range(steps):
        if k >= next_desired:
            speed = rng.uniform(0.0, 0.8)
            angle = rng.uniform(-math.pi, math.pi)
            desired = speed * np.array((math.cos(angle), math.sin(angle)))
            next_desired = k + int(rng.integers(20, 61))
        if k % 120 == 0:
            current = rng.uniform(0.0, 0.2) * _unit(rng.uniform(-math.pi, math.pi))
            wind = rng.uniform(0.0, 8.0) * _unit(rng.uniform(-math.pi, math.pi))
            limit = full if rng.random() > 0.25 else full * rng.uniform(0.4, 0.8)
        out.append({"desired": desired, "current": current, "wind": wind, "limit": limit})
    return out


def _unit(angle: float) -> np.ndarray:
    return np.array((math.cos(angle), math.sin(angle)))


def run_buoy(steps: int, seed: int, controller: str = "mpc") -> dict[str, object]:
    """Closed loop on the SITL truth dynamics; returns call times, states the MPC saw, and tracking."""
    params = BuoyParams()
    rng = np.random.default_rng(seed + 1)
    body = BuoyDynamics(params, np.zeros((1, 2)), np.zeros(1), np.random.default_rng(seed + 2))
    mpc = BuoyMpc()
    proportional = BuoyVelocityController()
    times, cpu_times, solver_times, inputs, errors = [], [], [], [], []
    previous = None
    solver_before = float(mpc._qp.stats()["t_wall_solver"])
    for step in buoy_sequence(steps, seed):
        velocity = body.velocity_mps[0] + rng.normal(0.0, 0.02, 2)
        heading = float(body.heading_rad[0] + rng.normal(0.0, 0.02))
        water = step["current"] + params.wind_drift_factor * step["wind"]
        limit = float(step["limit"])
        if controller == "mpc":
            start, cpu_start = time.perf_counter(), time.thread_time()
            result = mpc.solve(step["desired"], velocity, water, heading, limit, previous)
            times.append(time.perf_counter() - start)
            cpu_times.append(time.thread_time() - cpu_start)
            solver_total = float(mpc._qp.stats()["t_wall_solver"])  # the conic plugin alone, cumulative
            solver_times.append(solver_total - solver_before)
            solver_before = solver_total
            inputs.append((step["desired"], velocity, water, limit, None if previous is None else previous.copy()))
            previous = result.thrust_world_n
            thrust_body = result.thrust_body_n
        else:
            thrust_body = proportional.thrust(step["desired"][None], velocity[None], np.array([heading]), limit)[0]
        body.step(thrust_body[None], DT_S, step["wind"][None], step["current"][None], limit)
        errors.append(float(np.hypot(*(body.velocity_mps[0] - step["desired"]))))
    return {
        "times": np.array(times),
        "cpu_times": np.array(cpu_times),
        "solver_times": np.array(solver_times),
        "inputs": inputs,
        "errors": np.array(errors),
        "fallbacks": mpc.fallbacks,
        "mpc": mpc,
    }


def profile(inputs: list, repeats: int) -> dict[str, float]:
    """Median microseconds of one solve() and of its pieces, in a tight loop over the recorded states."""
    mpc = BuoyMpc()
    whole, solver = [], []
    before = float(mpc._qp.stats()["t_wall_solver"])
    for k in range(repeats):
        desired, velocity, water, limit, previous = inputs[k % len(inputs)]
        start = time.perf_counter()
        mpc.solve(desired, velocity, water, 0.0, limit, previous)
        whole.append(time.perf_counter() - start)
        total = float(mpc._qp.stats()["t_wall_solver"])
        solver.append(total - before)
        before = total
    pieces = {"solve_us": 1e6 * float(np.median(whole)), "solver_us": 1e6 * float(np.median(solver))}
    for name, call in (("data_function_us", mpc._data), ("conic_call_us", mpc._qp), ("stats_us", mpc._qp.stats)):
        samples = []
        for _ in range(repeats):
            start = time.perf_counter()
            call()
            samples.append(time.perf_counter() - start)
        pieces[name] = 1e6 * float(np.median(samples))
    pieces["python_rest_us"] = (
        pieces["solve_us"] - pieces["data_function_us"] - pieces["conic_call_us"] - pieces["stats_us"]
    )
    return pieces


def plugin_costs(inputs: list, repeats: int) -> dict[str, dict[str, float]]:
    """Median and p99 (ms) of the whole solve() on each available QP plugin, same states."""
    out = {}
    for plugin in QP_PLUGINS:
        if not ca.has_conic(plugin):
            continue
        mpc = BuoyMpc(solver=plugin)
        samples = []
        for desired, velocity, water, limit, previous in inputs[:repeats]:
            start = time.perf_counter()
            mpc.solve(desired, velocity, water, 0.0, limit, previous)
            samples.append(time.perf_counter() - start)
        samples_ms = 1e3 * np.array(samples)
        out[plugin] = {
            "median_ms": float(np.median(samples_ms)),
            "p99_ms": float(np.percentile(samples_ms, 99)),
            "fallbacks": mpc.fallbacks,
        }
    return out


def ipopt_costs(inputs: list, calls: int) -> tuple[np.ndarray, float]:
    """Whole-call times (s) of the same QP by IPOPT (built once), and the largest plan difference vs the QP (N)."""
    reference = BuoyMpc()
    nlp = ca.nlpsol(
        "buoy_mpc_ipopt", "ipopt", reference.problem, {"print_time": False, "ipopt": {"print_level": 0, "sb": "yes"}}
    )
    scale = reference.model.max_thrust_n
    times, worst = [], 0.0
    x0 = np.zeros(2 * reference.horizon)
    for desired, velocity, water, limit, previous in inputs[:calls]:
        start = time.perf_counter()
        prev = reference.into_polygon(np.zeros(2) if previous is None else previous, limit)
        p = np.concatenate((velocity, water, desired, prev / scale))
        solution = nlp(x0=x0, p=p, **reference.qp_bounds(limit, prev))
        x = np.array(solution["x"], dtype=float).ravel()
        times.append(time.perf_counter() - start)
        x0 = np.concatenate((x[2:], x[-2:]))
        reference.solve(desired, velocity, water, 0.0, limit, prev)
        if reference.last_plan_world_n is not None:
            worst = max(worst, float(np.max(np.abs(scale * x.reshape(-1, 2) - reference.last_plan_world_n))))
    return np.array(times), worst


def unicycle_velocity(heading: float, wheels: np.ndarray, base: float, dt: float) -> tuple[np.ndarray, float]:
    """Mean velocity over the step (exact arc) and the new heading."""
    forward = 0.5 * (wheels[0] + wheels[1])
    turn = (wheels[1] - wheels[0]) / base * dt
    chord = forward * np.sinc(turn / (2.0 * math.pi))
    mid = heading + 0.5 * turn
    return chord * _unit(mid), heading + turn


def ebot_manoeuvre(make, angle: float, from_rest: bool, speed: float = 0.2) -> dict[str, float]:
    """Mean |v - v_desired| (m/s) over 3 s after the desired direction turns by `angle`."""
    controller = make()
    heading = 0.0
    errors, times, fallbacks = [], [], 0
    lead = 0 if from_rest else 10
    for k in range(lead + 30):
        desired = speed * _unit(0.0 if k < lead else angle)
        if isinstance(controller, DiffDriveMpc):
            result = controller.solve(desired, heading)
            wheels = result.wheels_mps
            times.append(result.solve_time_s)
            fallbacks += int(result.fallback)
        else:
            wheels = controller.wheels(desired[None], np.array([np.nan]), np.array([heading]))[0]
        velocity, heading = unicycle_velocity(heading, wheels, 0.1, EBOT_DT_S)
        if k >= lead:
            errors.append(float(np.hypot(*(velocity - desired))))
    return {"mean_error_mps": float(np.mean(errors)), "fallbacks": fallbacks, "times": times}


def ebot_random(make, calls: int, seed: int) -> int:
    """Failures (fallbacks) over random desired velocities, headings and previous wheel speeds."""
    rng = np.random.default_rng(seed)
    controller = make()
    for _ in range(calls):
        desired = rng.uniform(0.0, 0.3) * _unit(rng.uniform(-math.pi, math.pi))
        controller.solve(desired, rng.uniform(-math.pi, math.pi), rng.uniform(-0.2, 0.2, 2))
    return controller.fallbacks


def construction_ms(repeats: int = 10) -> dict[str, float]:
    """Median wall ms to construct a BuoyMpc and a DiffDriveMpc: building the QP's casadi Functions and one
    warm-up solve (what every autonomy process pays once at start, and a buoy again when the autopilot reports
    its top speed), and another controller of the same tuning in the same process, which shares the Functions
    (a lockstep fleet's 45 buoys)."""
    out = {}
    makers = (
        ("buoy", lambda: BuoyMpc(dt_s=0.1), _buoy_qp_functions),
        ("ebot", lambda: DiffDriveMpc(), _ebot_qp_functions),
    )
    for name, make, functions in makers:
        make()  # the first loads casadi's plugin libraries
        for kind, clear in (("", True), ("_shared", False)):
            times = []
            for _ in range(repeats):
                if clear:
                    functions.cache_clear()
                start = time.perf_counter()
                make()
                times.append(time.perf_counter() - start)
            out[name + kind] = 1e3 * float(np.median(times))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--ipopt-steps", type=int, default=200)
    parser.add_argument("--random-calls", type=int, default=200)
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()

    build_ms = construction_ms()
    print(
        f"construction (formulate, build the casadi Functions, one warm-up solve), median of 10: buoy "
        f"{build_ms['buoy']:.1f} ms, eBot {build_ms['ebot']:.1f} ms (once per vessel: no cache on disk needed); "
        f"another of the same tuning in the same process (shared Functions): buoy {build_ms['buoy_shared']:.1f} ms, "
        f"eBot {build_ms['ebot_shared']:.1f} ms"
    )
    run = run_buoy(args.steps, args.seed)
    times_ms = 1e3 * run["times"]
    solver_ms = 1e3 * run["solver_times"]
    median, p99 = float(np.median(times_ms)), float(np.percentile(times_ms, 99))
    baseline = run_buoy(args.steps, args.seed, controller="proportional")
    settled = slice(args.steps // 10, None)
    print(f"buoy MPC ({run['mpc'].solver}), {args.steps} calls of solve() from Python:")
    print(f"  median {median:.3f} ms, p99 {p99:.3f} ms, max {times_ms.max():.3f} ms, fallbacks {run['fallbacks']}")
    cpu_ms = 1e3 * run["cpu_times"]
    print(
        f"  CPU time of this thread in the call: median {np.median(cpu_ms):.3f} ms, "
        f"p99 {np.percentile(cpu_ms, 99):.3f} ms (wall minus CPU: time the thread was not running)"
    )
    print(f"  conic solver alone: median {np.median(solver_ms):.3f} ms, p99 {np.percentile(solver_ms, 99):.3f} ms")
    pieces = profile(run["inputs"], 2000)
    print(
        "  profile, tight loop over the same states (median us): solve() {solve_us:.1f} = QP-data Function "
        "{data_function_us:.1f} + conic call {conic_call_us:.1f} (solver alone {solver_us:.1f}) + stats "
        "{stats_us:.1f} + Python {python_rest_us:.1f}".format(**pieces)
    )
    print(
        f"  tracking |v - v_desired| on the SITL truth: mean {run['errors'].mean():.3f} m/s "
        f"(proportional controller {baseline['errors'].mean():.3f} m/s)"
    )
    plugins = plugin_costs(run["inputs"], 1000)
    for plugin, cost in plugins.items():
        print(f"  plugin {plugin:8s} median {cost['median_ms']:.3f} ms, p99 {cost['p99_ms']:.3f} ms")
    ipopt_times, ipopt_gap = ipopt_costs(run["inputs"], args.ipopt_steps)
    ipopt_ms = 1e3 * ipopt_times
    ipopt_median = float(np.median(ipopt_ms))
    print(
        f"  IPOPT, same QP, {args.ipopt_steps} calls: median {ipopt_median:.3f} ms, "
        f"p99 {np.percentile(ipopt_ms, 99):.3f} ms; ratio IPOPT/QP {ipopt_median / median:.1f}; "
        f"largest plan difference {ipopt_gap:.1e} N"
    )

    forms = {
        "heuristic": lambda: DiffDriveController(),
        "linear_qp": lambda: DiffDriveMpc(form="linear"),
        "nonlinear_ipopt": lambda: DiffDriveMpc(form="nonlinear", nlp_solver="ipopt"),
        "nonlinear_sqp": lambda: DiffDriveMpc(form="nonlinear", nlp_solver="sqpmethod"),
    }
    manoeuvres = {
        "turn90_from_rest": (math.pi / 2, True),
        "turn90_driving": (math.pi / 2, False),
        "reverse180_driving": (math.pi, False),
        "turn135_driving": (0.75 * math.pi, False),
    }
    ebot: dict[str, dict[str, object]] = {}
    print(f"eBot MPC, mean |v - v_desired| (m/s) over 3 s after the change, dt {EBOT_DT_S} s, 0.2 m/s:")
    for name, make in forms.items():
        row: dict[str, object] = {}
        all_times: list[float] = []
        fallbacks = 0
        for label, (angle, from_rest) in manoeuvres.items():
            outcome = ebot_manoeuvre(make, angle, from_rest)
            row[label] = round(outcome["mean_error_mps"], 4)
            all_times += outcome["times"]
            fallbacks += outcome["fallbacks"]
        if name != "heuristic":
            ms = 1e3 * np.array(all_times)
            row["solve_median_ms"] = round(float(np.median(ms)), 3)
            row["solve_p99_ms"] = round(float(np.percentile(ms, 99)), 3)
            row["manoeuvre_fallbacks"] = fallbacks
            row["random_fallbacks"] = ebot_random(make, args.random_calls, args.seed)
        ebot[name] = row
        print(f"  {name:16s} " + ", ".join(f"{k} {v}" for k, v in row.items()))

    print(
        json.dumps(
            {
                "benchmark": "mpc_solve",
                "qp_plugin": run["mpc"].solver,
                "calls": args.steps,
                "qp_median_ms": round(median, 4),
                "qp_p99_ms": round(p99, 4),
                "qp_max_ms": round(float(times_ms.max()), 4),
                "qp_cpu_median_ms": round(float(np.median(cpu_ms)), 4),
                "qp_cpu_p99_ms": round(float(np.percentile(cpu_ms, 99)), 4),
                "conic_solver_median_ms": round(float(np.median(solver_ms)), 4),
                "profile_us": {k: round(v, 1) for k, v in pieces.items()},
                "buoy_fallbacks": run["fallbacks"],
                "tracking_mean_error_mps": round(float(run["errors"][settled].mean()), 4),
                "proportional_mean_error_mps": round(float(baseline["errors"][settled].mean()), 4),
                "plugins": {k: {kk: round(vv, 4) for kk, vv in v.items()} for k, v in plugins.items()},
                "ipopt_calls": args.ipopt_steps,
                "ipopt_median_ms": round(ipopt_median, 4),
                "ipopt_p99_ms": round(float(np.percentile(ipopt_ms, 99)), 4),
                "ipopt_over_qp": round(ipopt_median / median, 1),
                "ipopt_plan_gap_n": ipopt_gap,
                "ebot": ebot,
                "construction_ms": {k: round(v, 2) for k, v in build_ms.items()},
            }
        )
    )


if __name__ == "__main__":
    main()
