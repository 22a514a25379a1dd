"""Independent simulation runs executed in this process or on a Dask cluster, results handed back as they finish.

A sweep or a reproduction is many runs that share nothing: each is a pure function of its (seeded)
scenario. `run_tasks` calls one picklable function on every payload, either here, one after the
other, or on Dask (https://distributed.dask.org): a local cluster of `workers` processes
(`LocalCluster(processes=True, threads_per_worker=1)`, so that no two runs share an interpreter or
a BLAS thread pool), or an existing cluster whose scheduler address is given (started with Dask's
own `dask scheduler` and `dask worker ADDRESS`, or by dask-jobqueue on a compute cluster; its
workers need this project and the same numerical packages installed for identical results: every worker is
checked when the runs start and with every result it sends (`sitl.experiments.run_environment`), and one that
differs stops the runs with a ClusterError saying what differs).

Results come back to the calling process in the order they finish; the caller records each one as
it arrives (a sweep appends it to its partial file), so an interrupted run keeps what finished.
Ordering the final table is the caller's job (by task index), which is why the results do not
depend on who ran them or in what order.
"""

from __future__ import annotations

import contextlib
import logging
import uuid
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from tqdm import tqdm

from sitl.experiments.run_environment import differences, environment

LOCAL_HOST = "127.0.0.1"  # a local cluster listens on the loopback interface only
CONNECT_TIMEOUT_S = 20.0  # to reach an existing scheduler


class ClusterError(RuntimeError):
    """A Dask cluster that cannot be started or reached; the message says which and what to do."""


def check_execution(workers: int | None, scheduler: str | None) -> None:
    """ClusterError for an impossible choice: both a local cluster and a scheduler, or fewer than 1 worker."""
    if workers is not None and scheduler is not None:
        raise ClusterError("give --workers N (a local Dask cluster) or --scheduler ADDRESS (an existing one), not both")
    if workers is not None and workers < 1:
        raise ClusterError(f"--workers must be at least 1, got {workers}")
    if scheduler is not None and not scheduler.strip():
        raise ClusterError("--scheduler needs an address, e.g. tcp://10.0.0.5:8786 (printed by `dask scheduler`)")


def describe_execution(workers: int | None, scheduler: str | None) -> str:
    """Where the runs go, for messages: 'in process', 'on a local Dask cluster of 2 processes', ..."""
    if scheduler is not None:
        return f"on the Dask cluster at {scheduler}"
    if workers is not None:
        return f"on a local Dask cluster of {workers} process{'es' if workers != 1 else ''}"
    return "in process"


def run_tasks(
    fn: Callable[[Any], Any],
    payloads: Sequence[Any],
    on_done: Callable[[int, Any], None],
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
    desc: str = "runs",
) -> None:
    """Call `fn(payload)` for every payload; `on_done(index, result)` in this process as each finishes.

    In process when neither `workers` nor `scheduler` is given (in order), else on Dask (any order).
    An exception of a task is raised here (the other tasks are cancelled); so is KeyboardInterrupt,
    after cancelling what is still queued and closing the cluster this call started.
    ClusterError when the cluster cannot be started or reached.
    """
    check_execution(workers, scheduler)
    bar = tqdm(total=len(payloads), desc=desc, unit="run", disable=not progress, mininterval=0.5)
    try:
        if workers is None and scheduler is None:
            for index, payload in enumerate(payloads):
                on_done(index, fn(payload))
                bar.update(1)
            return
        if not payloads:
            return
        with _client(workers, scheduler) as client:
            _run_on_dask(client, fn, payloads, on_done, bar)
    finally:
        bar.close()


def _run_on_dask(client: Any, fn: Callable, payloads: Sequence[Any], on_done: Callable, bar: tqdm) -> None:
    from distributed import as_completed

    here = environment()
    try:
        connected = client.run(_worker_environment)  # the workers connected now; later ones with their results
    except Exception as error:  # raised on a worker, e.g. ModuleNotFoundError: this project is not installed there
        raise ClusterError(
            f"cannot ask the Dask workers for their environment ({type(error).__name__}: {error}); is bob-autonomy "
            "installed in the workers' environment (pip install PATH-TO-THIS-CHECKOUT)?"
        ) from None
    for address, there in connected.items():
        _check_worker(address, here, there)
    token = uuid.uuid4().hex[:12]  # unique task keys: one cluster may serve many sweeps at once
    futures = [
        client.submit(_run_reporting_environment, fn, p, key=f"bob-sitl-{token}-{i}", pure=False)
        for i, p in enumerate(payloads)
    ]
    index = {f.key: i for i, f in enumerate(futures)}
    try:
        for future in as_completed(futures):
            address, there, result = future.result()  # a task's exception is raised here
            _check_worker(address, here, there)  # before the result is kept
            on_done(index[future.key], result)
            bar.update(1)
    finally:
        with contextlib.suppress(Exception):
            client.cancel(futures)


def _worker_environment() -> dict[str, str]:
    """On a worker: its `environment()` (asked of every connected worker before the runs start)."""
    return environment()


def _run_reporting_environment(fn: Callable[[Any], Any], payload: Any) -> tuple[str, dict[str, str], Any]:
    """On a worker: (its address, its `environment()`, fn(payload))."""
    from distributed import get_worker

    return get_worker().address, environment(), fn(payload)


def _check_worker(address: str, here: dict[str, str], there: dict[str, str]) -> None:
    """ClusterError when a worker's fingerprint differs from this process's: its results would not be ours."""
    differing = differences(here, there)
    if differing:
        raise ClusterError(
            f"the Dask worker {address} would not give the same results as this process: {'; '.join(differing)}. "
            "Install this same checkout of bob-autonomy and the same package versions in the workers' environment "
            "(pip install PATH-TO-THIS-CHECKOUT), restart the workers, and run the same command with --resume "
            "(it skips the runs already finished)"
        )


@contextlib.contextmanager
def _client(workers: int | None, scheduler: str | None) -> Iterator[Any]:
    try:
        from distributed import Client, LocalCluster
    except ImportError as error:  # a dependency of the package; absent only in a broken install
        raise ClusterError(f"Dask is not installed ({error}): pip install 'dask[distributed]'") from None
    if scheduler is not None:
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError, ValueError, TypeError) as error:
            raise ClusterError(
                f"cannot reach the Dask scheduler at {scheduler!r} ({type(error).__name__}: {error}); "
                "start one with `dask scheduler` and workers with `dask worker ADDRESS`, or use --workers N"
            ) from None
        try:
            if not client.scheduler_info().get("workers"):
                logging.getLogger(__name__).warning("the Dask cluster at %s has no workers yet: runs wait", scheduler)
            yield client
        finally:
            client.close()
        return
    try:
        cluster = LocalCluster(
            n_workers=workers,
            processes=True,
            threads_per_worker=1,
            host=LOCAL_HOST,
            dashboard_address=None,
            scheduler_kwargs={"dashboard_address": f"{LOCAL_HOST}:0"},  # its HTTP server: loopback, any free port
            silence_logs=logging.ERROR,
        )
    except (OSError, TimeoutError, RuntimeError) as error:
        raise ClusterError(f"cannot start a local Dask cluster of {workers} processes: {error}") from None
    try:
        with Client(cluster) as client:
            yield client
    finally:
        cluster.close()
