"""Cost of the buoy and eBot EKFs (bob_autonomy.estimation): per call for one vessel, and per simulated step for
a fleet.

One vessel (microseconds per call, median over --calls calls): each call is timed
on its own (time.perf_counter_ns) inside a realistic stream: every 0.02 s a buoy
predicts with an accelerometer reading (with and, separately, without a thrust
command: with one, the prediction also fuses the drag-balance pseudo-measurement),
then takes a GPS fix (position + ground velocity) and a compass reading at that
same time (so an update's time is the update alone, no prediction to its time).
An eBot reads its encoders every 0.1 s, then takes a compass reading and a
position fix.

A fleet of buoys (milliseconds per simulated step): --buoys buoys (45, the paper's
field tests) holding station against thrust that wanders, simulated by
sitl.vehicles.dynamics with the default sitl.vehicles.sensors suite (GPS 5 Hz with 0.1 s latency;
compass 10 Hz; IMU 50 Hz, i.e. one reading per step when dt > 0.02 s). The
sensor stream is recorded first; then, per step, the bank gets exactly the calls
bob_autonomy.onboard.pipeline.BuoyPipeline makes (predict with the accelerometer and the
world-frame thrust command, gyro, GPS position and velocity, compass with its
measurement time), in measurement-time order as the pipeline feeds them, plus the
controller's estimate() and drift(); the whole step is timed. The baseline, in the
same run: the calls in the order the sensors deliver them, so that every fix comes
after the IMU reading of its step and is fused by replay (what the pipeline did
before it sorted). Reported: median and mean over the steps after the first 10 s,
for each --dt. Only the public BuoyEkfBank API is used, so the same script measures
any version of the filter.

One vessel's filter as `bob-autonomy run` feeds it (CPU ms per simulated second): IMU
at 25 Hz, compass, and GPS fixes dated when ArduPilot read them, about 0.09 s before
they arrive, so each is fused by replay; the baseline, in the same run: the fixes
dated at their arrival.

A fleet of eBots (milliseconds per 0.1 s step): --ebots robots each read their
encoders, then a compass; EbotEkfBank (all robots in one call per kind) against
its reference, one EbotEkf (filterpy) per robot, fed the same readings.

    python benchmarks/ekf_step.py [--calls 5000] [--seed 1] [--buoys 45] [--ebots 14] [--dt 0.5 0.1]
        [--duration 60]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import time

import numpy as np

from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.estimation import BuoyEkf, BuoyEkfBank, EbotEkf, EbotEkfBank
from sitl.vehicles.dynamics import BuoyDynamics, BuoyParams
from sitl.vehicles.sensors import SensorSuite


def timed(call, *args) -> float:
    """Microseconds one call takes."""
    start = time.perf_counter_ns()
    call(*args)
    return (time.perf_counter_ns() - start) / 1000.0


def buoy(calls: int, rng: np.random.Generator, thrust: bool) -> dict[str, float]:
    f = BuoyEkf(position_m=[0.0, 0.0], heading_rad=0.3)
    times: dict[str, list[float]] = {"predict": [], "update_gps": [], "update_compass": []}
    for k in range(calls + 100):  # the first 100 rounds warm up
        t = 0.02 * k
        accel = 0.05 * rng.standard_normal(2)
        cmd = np.array([10.0 * math.cos(0.05 * t), 10.0 * math.sin(0.05 * t)]) if thrust else None
        us_predict = timed(f.predict, t, accel, cmd)
        position, velocity, heading = f.estimate(t)
        xy = position + 0.5 * rng.standard_normal(2)
        us_gps = timed(f.update_gps, t, xy, velocity + 0.05 * rng.standard_normal(2))
        us_compass = timed(f.update_compass, t, heading + 0.02 * rng.standard_normal())
        if k >= 100:
            times["predict"].append(us_predict)
            times["update_gps"].append(us_gps)
            times["update_compass"].append(us_compass)
    assert f.gated + f.rejected + f.failures < calls // 100, "the benchmark stream should be clean"
    return {name: statistics.median(v) for name, v in times.items()}


def vessel_second(age_s: float, seconds: float, seed: int) -> float:
    """CPU ms per simulated second of one vessel's filter as `bob-autonomy run` feeds it from ArduPilot: the IMU
    (with the thrust command) at 25 Hz and the compass at 12.5 Hz, each fused as it arrives, and a 5 Hz GPS whose
    fix is dated age_s before its arrival (when ArduPilot read it, firmware_bridge.autopilot_clock), so that it is
    fused by replaying the IMU rounds after it."""
    rng = np.random.default_rng(seed)
    f = BuoyEkf(position_m=[0.0, 0.0], heading_rad=0.3)
    cpu = 0.0
    for k in range(round(seconds / 0.04)):
        t = 0.04 * k
        accel = 0.05 * rng.standard_normal(2)
        command = np.array([10.0 * math.cos(0.05 * t), 10.0 * math.sin(0.05 * t)])
        position, velocity, heading = f.estimate(t)
        noise = rng.standard_normal(5)
        start = time.process_time()
        f.predict(t, accel, command)
        if k % 2 == 0:
            f.update_compass(t, heading + 0.02 * noise[0])
        if k % 5 == 0:
            f.update_gps(t - age_s, position + 0.5 * noise[1:3], velocity + 0.05 * noise[3:5])
        cpu += time.process_time() - start
    return 1000.0 * cpu / seconds


def ebot(calls: int, rng: np.random.Generator) -> dict[str, float]:
    metres_per_tick = 2.0 * math.pi * 0.03 / 360
    f = EbotEkf([0.0, 0.0], 0.0, 0.1, metres_per_tick)
    times: dict[str, list[float]] = {"predict_encoders": [], "update_compass": [], "update_position": []}
    travel = np.zeros(2)
    for k in range(calls + 100):
        t = 0.1 * k
        travel += np.array([0.019, 0.021]) + 0.001 * rng.standard_normal(2)
        ticks = np.floor(travel / metres_per_tick).astype(np.int64)
        us_enc = timed(f.update_encoders, t, ticks)
        position, _, heading = f.estimate()
        us_compass = timed(f.update_compass, t, heading + 0.02 * rng.standard_normal())
        us_position = timed(f.update_position, t, position + 0.05 * rng.standard_normal(2), 0.1)
        if k >= 100:
            times["predict_encoders"].append(us_enc)
            times["update_compass"].append(us_compass)
            times["update_position"].append(us_position)
    return {name: statistics.median(v) for name, v in times.items()}


def fleet_stream(n: int, dt_s: float, duration_s: float, seed: int) -> list[list[tuple[str, tuple]]]:
    """Per simulated step, the bank calls (method name, arguments) a BuoyPipeline makes for n buoys."""
    rng = np.random.default_rng(seed)
    frame = LocalFrame(43.0, 5.0)
    position = rng.uniform(0.0, 300.0, (n, 2))
    dynamics = BuoyDynamics(BuoyParams(), position, rng.uniform(-math.pi, math.pi, n), rng)
    sensors = SensorSuite(n, frame, rng, encoders=None, ranges=None, light=None)
    wind, current = np.tile([3.0, 2.0], (n, 1)), np.tile([-0.1, 0.05], (n, 1))
    phase = rng.uniform(0.0, 2.0 * math.pi, n)
    steps = []
    for k in range(round(duration_s / dt_s)):
        t = k * dt_s
        # Thrust against the drift with a wandering part, world frame (the EKF's known input).
        angle = phase + 0.3 * t
        thrust_world = np.column_stack((-2.0 + 4.0 * np.cos(angle), -4.0 + 4.0 * np.sin(angle)))
        c, s = np.cos(dynamics.heading_rad), np.sin(dynamics.heading_rad)
        tx, ty = thrust_world[:, 0], thrust_world[:, 1]
        dynamics.step(np.column_stack((c * tx + s * ty, -s * tx + c * ty)), dt_s, wind, current)  # body frame
        d = dynamics
        readings = sensors.sample(
            t + dt_s, d.position_m, d.velocity_mps, d.acceleration_mps2, d.heading_rad, d.yaw_rate_radps
        )
        calls: list[tuple[str, tuple]] = []
        if readings.imu is not None:
            imu = readings.imu
            calls.append(("predict", (imu.agents, imu.t_s, imu.accel_body_mps2, thrust_world[imu.agents])))
            calls.append(("update_gyro", (imu.agents, imu.t_s, imu.gyro_z_radps)))
        if readings.gps is not None:
            fix = readings.gps
            x, y = frame.to_local(fix.lat_deg, fix.lon_deg)
            calls.append(("update_gps", (fix.agents, fix.t_s, np.column_stack((x, y)), fix.velocity_mps)))
        if readings.compass is not None:
            compass = readings.compass
            calls.append(("update_compass", (compass.agents, compass.heading_rad, compass.t_s)))
        steps.append(calls)
    return steps


def in_time_order(calls: list[tuple[str, tuple]]) -> list[tuple[str, tuple]]:
    """A step's calls ordered by their latest measurement time, stable (as BuoyPipeline.feed orders readings)."""
    return sorted(calls, key=lambda call: float(np.max(call[1][2 if call[0] == "update_compass" else 1])))


def fleet(n: int, dt_s: float, duration_s: float, seed: int, sort: bool) -> dict[str, float]:
    """Milliseconds per simulated step of a BuoyEkfBank of n buoys (median and mean after the first 10 s); sort:
    each step's calls in measurement-time order, else as the sensors deliver them."""
    steps = fleet_stream(n, dt_s, duration_s, seed)
    if sort:
        steps = [in_time_order(calls) for calls in steps]
    bank = BuoyEkfBank(n)
    per_step = []
    for k, calls in enumerate(steps):
        t = (k + 1) * dt_s
        start = time.perf_counter_ns()
        for name, args in calls:
            getattr(bank, name)(*args)
        bank.estimate(t)
        bank.drift()
        per_step.append((time.perf_counter_ns() - start) / 1e6)
    settled = per_step[round(10.0 / dt_s) :]
    return {"median_ms": round(statistics.median(settled), 2), "mean_ms": round(statistics.fmean(settled), 2)}


def ebot_fleet(n: int, steps: int, seed: int) -> dict[str, float]:
    """Milliseconds per 0.1 s step of n eBots' encoder and compass readings: the bank, and one EbotEkf per robot."""
    rng = np.random.default_rng(seed)
    metres_per_tick = 2.0 * math.pi * 0.03 / 360
    start, heading = rng.uniform(0.0, 5.0, (n, 2)), rng.uniform(-math.pi, math.pi, n)
    bank = EbotEkfBank(start, heading, 0.1, metres_per_tick)
    singles = [EbotEkf(start[i], heading[i], 0.1, metres_per_tick) for i in range(n)]
    agents = np.arange(n)
    travel = np.zeros((n, 2))
    bank_ms, singles_ms = [], []
    for k in range(steps):
        t = 0.1 * k
        travel += rng.uniform(0.0, 0.02, (n, 2))
        ticks = np.floor(travel / metres_per_tick).astype(np.int64)
        compass = heading + 0.02 * k + 0.02 * rng.standard_normal(n)
        begin = time.perf_counter_ns()
        bank.update_encoders(agents, np.full(n, t), ticks)
        bank.update_compass(agents, compass, np.full(n, t))
        bank.estimate(t)
        middle = time.perf_counter_ns()
        for i, f in enumerate(singles):
            f.update_encoders(t, ticks[i])
            f.update_compass(t, compass[i])
            f.estimate()
        bank_ms.append((middle - begin) / 1e6)
        singles_ms.append((time.perf_counter_ns() - middle) / 1e6)
    bank_median, singles_median = statistics.median(bank_ms[100:]), statistics.median(singles_ms[100:])
    return {
        "ebots": n,
        "bank_ms": round(bank_median, 3),
        "one_filterpy_ekf_per_robot_ms": round(singles_median, 3),
        "ratio_bank_to_per_robot": round(bank_median / singles_median, 3),
    }


def _vessel_seconds(seconds: float, seed: int) -> dict[str, float]:
    """`vessel_second` with fixes dated at their arrival (the baseline, no replay) and 0.09 s before it (what
    Rover SITL's fixes were: 77-100 ms), alternated three times; the medians and their ratio."""
    runs: dict[float, list[float]] = {0.0: [], 0.09: []}
    for _ in range(3):
        for age in runs:
            runs[age].append(vessel_second(age, seconds, seed))
    at_arrival, dated = statistics.median(runs[0.0]), statistics.median(runs[0.09])
    return {
        "fixes_at_arrival": round(at_arrival, 1),
        "fixes_dated_0.09_s_back": round(dated, 1),
        "ratio": round(dated / at_arrival, 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=5000, help="timed calls of each kind (one vessel)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--buoys", type=int, default=45, help="buoys in the fleet benchmark")
    parser.add_argument("--ebots", type=int, default=14, help="eBots in the eBot fleet benchmark")
    parser.add_argument("--dt", type=float, nargs="+", default=[0.5, 0.1], help="simulated steps, s")
    parser.add_argument("--duration", type=float, default=60.0, help="simulated time per fleet run, s")
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    with_thrust = buoy(args.calls, rng, thrust=True)
    accel_only = buoy(args.calls, rng, thrust=False)
    result = {
        "benchmark": "ekf_step",
        "unit": "us_per_call_median",
        "calls": args.calls,
        "buoy": {
            "predict_accel_us": round(accel_only["predict"], 1),
            "predict_accel_thrust_us": round(with_thrust["predict"], 1),
            "update_gps_pos_vel_us": round(with_thrust["update_gps"], 1),
            "update_compass_us": round(with_thrust["update_compass"], 1),
        },
        "ebot": {name + "_us": round(v, 1) for name, v in ebot(args.calls, rng).items()},
        "vessel_cpu_ms_per_simulated_s": _vessel_seconds(args.duration, args.seed),
        "fleet": {
            "buoys": args.buoys,
            "ms_per_step": {
                f"dt_{dt:g}_s": {
                    "in_time_order": fleet(args.buoys, dt, args.duration, args.seed, sort=True),
                    "as_delivered_with_replay": fleet(args.buoys, dt, args.duration, args.seed, sort=False),
                }
                for dt in args.dt
            },
        },
        "ebot_fleet": ebot_fleet(args.ebots, 600, args.seed),
        "python": platform.python_version(),
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
