"""The buoys' vessel side spread over processes (sitl.vehicles.vessel_shards): whole runs give the same bits as in
one process, the readings reach the right rows, and a worker that fails or vanishes stops the run with a message
that names its buoys."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys

import numpy as np
import pytest

from bob_autonomy.core.geodesy import LocalFrame
from firmware_bridge.readings import CompassReading, GpsFix, ImuReading, SensorReadings
from sitl.cli import main
from sitl.experiments.runner import simulate
from sitl.experiments.scenario import load_scenario
from sitl.vehicles.vessel_shards import (
    BuoyShardSpec,
    ShardedBuoys,
    VesselProcessError,
    readings_of_rows,
    shard_ranges,
)


@pytest.mark.parametrize(("n", "processes"), [(45, 2), (45, 3), (7, 4), (3, 5), (1, 2), (10, 1)])
def test_shard_ranges_cover_the_rows_in_order(n: int, processes: int) -> None:
    ranges = shard_ranges(n, processes)
    assert len(ranges) == min(n, processes)
    assert ranges[0][0] == 0 and ranges[-1][1] == n
    assert all(hi == lo for (_, hi), (lo, _) in itertools.pairwise(ranges))
    sizes = [hi - lo for lo, hi in ranges]
    assert min(sizes) >= 1 and max(sizes) - min(sizes) <= 1


def test_readings_of_rows_picks_and_renumbers() -> None:
    agents = np.array([4, 0, 2, 3, 2])
    readings = SensorReadings(
        gps=GpsFix(
            agents,
            np.arange(5.0),
            np.arange(5.0) + 1.0,
            np.arange(5.0) + 2.0,
            velocity_mps=np.arange(10.0).reshape(5, 2),
            accuracy_m=np.array([0.5, np.nan, 0.7, 0.8, 0.9]),
        ),
        compass=CompassReading(np.array([1, 3]), np.array([0.1, 0.2]), np.array([0.3, 0.4])),
        imu=ImuReading(np.array([0]), np.array([0.0]), np.zeros((1, 2)), np.zeros(1)),
    )
    part = readings_of_rows(readings, 2, 4)
    assert part.gps.agents.tolist() == [0, 1, 0]  # agents 2, 3, 2
    assert part.gps.t_s.tolist() == [2.0, 3.0, 4.0]
    assert part.gps.velocity_mps.tolist() == [[4.0, 5.0], [6.0, 7.0], [8.0, 9.0]]
    assert part.gps.accuracy_m.tolist() == [0.7, 0.8, 0.9]
    assert part.gps.speed_accuracy_mps is None  # a field the source did not have stays absent
    assert part.compass.agents.tolist() == [1] and part.compass.heading_rad.tolist() == [0.4]
    assert part.compass.roll_rad is None
    assert part.imu.agents.size == 0  # agent 0 is another range's
    assert part.encoders is None


def _run(name: str, processes: int, **overrides) -> tuple[dict, np.ndarray, np.ndarray]:
    scenario = load_scenario(name).with_overrides(fidelity="physics", **overrides)
    result = simulate(scenario, vessel_processes=processes)
    frames = result.recorder.frames
    truth = np.concatenate([np.column_stack((f.position, f.heading)) for f in frames])
    believed = np.concatenate([f.estimate for f in frames])
    return result.metrics, truth, believed


@pytest.mark.parametrize(
    ("name", "processes", "overrides"),
    [
        ("aggregation", 2, {"agents": 20, "duration_s": 40.0}),
        # a buoy with 40 % thrust (its own limit in its range) and uneven ranges
        ("leader-follower", 3, {"duration_s": 10.0}),
        # buoys among motorboats: the buoys' rows and system ids are not the fleet's
        ("aggregation-mixed", 2, {"duration_s": 10.0}),
    ],
)
def test_a_run_over_processes_is_the_same_bits(name: str, processes: int, overrides: dict) -> None:
    one_metrics, one_truth, one_believed = _run(name, 1, **overrides)
    metrics, truth, believed = _run(name, processes, **overrides)
    assert np.array_equal(truth, one_truth)
    assert np.array_equal(believed, one_believed, equal_nan=True)
    assert json.dumps(metrics, sort_keys=True) == json.dumps(one_metrics, sort_keys=True)
    assert metrics["vehicle_link"]["vessel_decoded"] > 0  # the workers' counters are in the totals


def _spec(n: int) -> BuoyShardSpec:
    options = {"estimator": "ekf", "controller": "mpc", "dt_s": 0.5, "mpc_time_budget_s": np.inf}
    return BuoyShardSpec(0, np.full(n, 20.0), LocalFrame(1.3, 103.8), 20.0, options, "mavlink", 0.0)


def test_a_failing_worker_is_named_with_its_traceback() -> None:
    shards = ShardedBuoys(_spec(4), 2)
    try:
        thrust = shards.command(np.zeros((4, 2)), 0.5, True)
        assert thrust.shape == (4, 2)
        with pytest.raises(VesselProcessError, match=r"(?s)buoys 2-3 failed:.*Traceback.*ValueError"):
            shards.command(np.zeros((3, 2)), 1.0, False)  # a wish short of a row: only the worker's part fails
        assert shards.command(np.ones((4, 2)), 1.5, False).shape == (4, 2)  # no stale answer was left behind
    finally:
        shards.close()


def test_a_killed_worker_stops_the_run_and_close_stops_the_rest() -> None:
    shards = ShardedBuoys(_spec(6), 3)
    processes = [process for process, _ in shards.workers]
    try:
        processes[1].kill()
        processes[1].join()
        with pytest.raises(VesselProcessError, match=r"buoys 4-5 ended without answering \(exit code -9"):
            shards.command(np.zeros((6, 2)), 0.5, True)
    finally:
        shards.close()
        shards.close()  # idempotent
    assert not any(process.is_alive() for process in processes)


def test_cli_refuses_no_vessel_process(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["run", "aggregation", "--vessel-processes", "0", "--out", str(tmp_path / "out"), "--quiet"])
    assert exit_info.value.code == 2
    assert "--vessel-processes: 0 is not at least 1" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_script_without_a_main_guard_is_told_what_to_change(tmp_path) -> None:
    script = tmp_path / "unguarded.py"
    script.write_text(
        "from sitl.experiments.scenario import load_scenario\n"
        "from sitl.fleets.fleet import LockstepFleet\n"
        "LockstepFleet(load_scenario('aggregation').with_overrides(fidelity='physics'), vessel_processes=2)\n"
    )
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode != 0
    last = done.stderr.strip().splitlines()[-1]
    assert "VesselProcessError" in last and "while starting" in last
    assert 'if __name__ == "__main__":' in last
