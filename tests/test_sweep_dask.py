"""bob-sitl sweep on Dask: the same sweep in process and on a local cluster of 2 worker processes gives the
same sweep.csv, byte for byte (seeded runs, rows in a fixed order whoever finishes first).

One test starts a cluster (worker start-up takes seconds on 2 cores); its sweep runs the buoys at
both fidelities, so their dynamics, sensors, EKF and MPC are covered as well as the kinematic model.
Others start a cluster as a user does, with Dask's own command line, and check that a worker whose
environment differs from ours (another numpy, another checkout) is refused, before the runs and with
every result.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import cloudpickle
import pytest
from distributed import Client

import sitl.experiments.distributed
from sitl.cli import main
from sitl.experiments.distributed import ClusterError, run_tasks
from sitl.experiments.run_environment import SOURCE_KEY, differences, environment

# The helpers below run on workers started from the command line, which cannot import this test module: Dask
# sends them by value.
cloudpickle.register_pickle_by_value(sys.modules[__name__])


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


# -- an existing cluster, started with Dask's own command line (`dask scheduler`, `dask worker`) --------------------


@pytest.fixture(scope="module")
def dask_cli_cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A scheduler and one single-threaded worker process started as a user starts them (`python -m dask scheduler`
    and `python -m dask worker`, loopback only, no dashboards); yields the scheduler's address."""
    where = tmp_path_factory.mktemp("dask-cli")
    scheduler_file = where / "scheduler.json"
    scheduler = subprocess.Popen(
        [sys.executable, "-m", "dask", "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
         "--scheduler-file", str(scheduler_file)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=where,
    )  # fmt: skip
    worker = None
    try:
        deadline = time.monotonic() + 60.0
        while not scheduler_file.exists() or not scheduler_file.read_text().strip():
            assert scheduler.poll() is None and time.monotonic() < deadline, "dask scheduler did not start"
            time.sleep(0.1)
        time.sleep(0.2)  # the file is written in one go, but let a slow writer finish
        address = json.loads(scheduler_file.read_text())["address"]
        worker = subprocess.Popen(
            [sys.executable, "-m", "dask", "worker", "--scheduler-file", str(scheduler_file), "--nworkers", "1",
             "--nthreads", "1", "--no-dashboard", "--local-directory", str(where)],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=where,
        )  # fmt: skip
        with Client(address, timeout=30) as client:
            client.wait_for_workers(1, timeout=60)
        yield address
    finally:
        for process in (worker, scheduler):
            if process is not None:
                process.terminate()
                try:
                    process.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    process.kill()


def _pretend_another_numpy() -> None:
    """On a worker: report numpy 1.0.0 from now on (as a worker with an old environment would)."""
    from sitl.experiments import run_environment

    run_environment._ENVIRONMENT = {**run_environment.environment(), "numpy": "1.0.0"}


def _forget_the_pretence() -> None:
    from sitl.experiments import run_environment

    run_environment._ENVIRONMENT = None


def _pretend_another_numpy_then_square(x: int) -> int:
    _pretend_another_numpy()
    return x * x


@pytest.mark.xdist_group("realtime")
def test_a_sweep_on_a_cluster_started_with_dasks_command_line_equals_the_sweep_in_process(
    dask_cli_cluster: str, tmp_path: Path
) -> None:
    argv = ["sweep", "aggregation", "--agents", "3", "--duration", "5", "--runs", "2", "--quiet"]
    argv += ["--param", "fidelity=physics"]
    assert main([*argv, "--out", str(tmp_path / "here")]) == 0
    assert main([*argv, "--scheduler", dask_cli_cluster, "--out", str(tmp_path / "there")]) == 0
    here = (tmp_path / "here" / "sweep.csv").read_bytes()
    assert len(here.decode().splitlines()) == 1 + 2
    assert (tmp_path / "there" / "sweep.csv").read_bytes() == here


@pytest.mark.xdist_group("realtime")
def test_a_worker_with_another_environment_is_refused_before_any_run(
    dask_cli_cluster: str, tmp_path: Path, capsys
) -> None:
    with Client(dask_cli_cluster, timeout=30) as client:
        client.run(_pretend_another_numpy)
        try:
            argv = ["sweep", "heading-consensus", "--agents", "3", "--duration", "2", "--runs", "1", "--quiet"]
            assert main([*argv, "--scheduler", dask_cli_cluster, "--out", str(tmp_path / "out")]) == 2
        finally:
            client.run(_forget_the_pretence)
    err = capsys.readouterr().err
    assert "would not give the same results as this process: numpy 1.0.0 there, " in err
    assert "Install this same checkout" in err
    assert not (tmp_path / "out").exists()  # refused before the first run: nothing written


@pytest.mark.xdist_group("realtime")
def test_a_result_from_a_worker_whose_environment_changed_is_refused_and_the_earlier_ones_kept(
    dask_cli_cluster: str,
) -> None:
    got: list[tuple[int, int]] = []
    with Client(dask_cli_cluster, timeout=30) as client:
        try:
            # The single worker runs the tasks in turn; each reports its environment before running, so the first
            # reports the real one and the second the one the first left behind.
            with pytest.raises(ClusterError, match=r"numpy 1\.0\.0 there"):
                run_tasks(
                    lambda x: _pretend_another_numpy_then_square(x),  # a lambda: Dask sends the task by value
                    [3, 4], lambda i, r: got.append((i, r)), scheduler=dask_cli_cluster, progress=False,
                )  # fmt: skip
        finally:
            client.run(_forget_the_pretence)
    assert got == [(0, 9)]


def _without_this_project() -> dict[str, str]:
    raise ModuleNotFoundError("No module named 'sitl'")


@pytest.mark.xdist_group("realtime")
def test_workers_without_this_project_are_a_clear_error(dask_cli_cluster: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sitl.experiments.distributed, "_worker_environment", _without_this_project)
    with pytest.raises(ClusterError, match=r"ModuleNotFoundError: No module named 'sitl'.*is bob-autonomy installed"):
        run_tasks(_square, [1], lambda i, r: None, scheduler=dask_cli_cluster, progress=False)


def test_fingerprints_say_what_differs() -> None:
    here = environment()
    assert set(here) >= {"python", "numpy", "casadi", SOURCE_KEY} and len(here[SOURCE_KEY]) == 16
    assert differences(here, dict(here)) == []
    there = {**here, "scipy": "0.1", SOURCE_KEY: "0" * 16}
    assert differences(here, there) == [
        f"scipy 0.1 there, {here['scipy']} here",
        f"{SOURCE_KEY} {'0' * 16} there, {here[SOURCE_KEY]} here",
    ]
    assert differences({"a": "1"}, {"b": "2"}) == ["a unknown there, 1 here", "b 2 there, unknown here"]
