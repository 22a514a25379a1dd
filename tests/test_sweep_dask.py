"""bob-sitl sweep on Dask: the same sweep in process and on a local cluster of 2 worker processes gives the
same sweep.csv, byte for byte (seeded runs, rows in a fixed order whoever finishes first).

One test starts a cluster (worker start-up takes seconds on 2 cores); its sweep runs the buoys at
both fidelities, so their dynamics, sensors, EKF and MPC are covered as well as the kinematic model.
"""

from __future__ import annotations

from pathlib import Path

import pytest

import sitl.experiments.distributed
from sitl.cli import main
from sitl.experiments.distributed import ClusterError, run_tasks


def _square(x: int) -> int:
    return x * x


@pytest.mark.xdist_group("realtime")
def test_a_sweep_on_a_2_worker_local_cluster_equals_the_sweep_in_process(tmp_path: Path, capsys) -> None:
    argv = ["sweep", "aggregation", "--agents", "3", "4", "--duration", "5", "--runs", "2", "--quiet"]
    argv += ["--param", "fidelity=kinematic,physics", "--plot", "area_final_m2"]
    assert main([*argv, "--out", str(tmp_path / "here")]) == 0
    assert main([*argv, "--workers", "2", "--out", str(tmp_path / "dask")]) == 0
    here = (tmp_path / "here" / "sweep.csv").read_bytes()
    lines = here.decode().splitlines()
    assert len(lines) == 1 + 8 and lines[0].startswith("agents,fidelity,seed,passed,")
    assert [line.split(",")[:3] for line in lines[1:]] == [
        [n, f, s] for n in ("3", "4") for f in ("kinematic", "physics") for s in ("1", "2")
    ]
    assert "estimation.buoy.position_rms_m" in lines[0]  # the physics runs' own figures are there
    assert (tmp_path / "dask" / "sweep.csv").read_bytes() == here
    assert capsys.readouterr().out.count("8 runs") == 2


def test_in_process_tasks_come_back_in_order_and_errors_propagate() -> None:
    got: list[tuple[int, int]] = []
    run_tasks(_square, [3, 1, 2], lambda i, r: got.append((i, r)), progress=False)
    assert got == [(0, 9), (1, 1), (2, 4)]
    with pytest.raises(TypeError):
        run_tasks(_square, ["a"], lambda i, r: None, progress=False)


def test_an_unreachable_scheduler_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sitl.experiments.distributed, "CONNECT_TIMEOUT_S", 0.5)
    with pytest.raises(ClusterError, match=r"cannot reach the Dask scheduler at 'tcp://127\.0\.0\.1:9'"):
        run_tasks(_square, [1], lambda i, r: None, scheduler="tcp://127.0.0.1:9", progress=False)
