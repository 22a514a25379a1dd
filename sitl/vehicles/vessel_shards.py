"""A lockstep fleet's buoy vessels spread over processes: each process runs a contiguous range of buoys, their
estimators and controllers (`BuoyPipeline`) and their MAVLink link with the simulated autopilots
(`MavlinkTransport`).

A buoy's vessel side depends on nothing of another buoy's: its telemetry, its decoder, its EKF row and its MPC
are its own, and every batched stage computes each row by the same operations whatever the batch, so a run split
over processes gives the same bits as one in a single process (tests/test_vessel_shards.py compares whole runs
byte for byte). The fleet process keeps the physics, the radio, the behaviours and the first range of buoys; the
others run in worker processes started with "spawn" (no fork of a process that holds threads). Per step a worker
gets its rows' wishes and answers with their thrust (`command`), then gets their readings and answers with their
pose estimates (`sense`): two round trips of a few kB over a pipe, about 0.1 ms each.

Why: at 45 buoys the vessel side is about 85 % of a full-stack step (docs/performance.md), and it is per vessel
Python; processes are the way to use a second core for it (threads hold the GIL).
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import multiprocessing
import signal
import traceback
import weakref
from dataclasses import dataclass
from multiprocessing.connection import Connection

import numpy as np

from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.estimation.simple_estimator import PoseEstimate
from bob_autonomy.onboard.pipeline import BuoyPipeline
from firmware_bridge.readings import SensorReadings, rows_of
from sitl.vehicles.mavlink_vehicle import BUOY
from sitl.vehicles.vehicle_transport import DirectTransport, MavlinkTransport
from sitl.world.world import FloatArray

STOP_TIMEOUT_S = 5.0  # a worker that has not stopped this long after being asked is terminated


class VesselProcessError(RuntimeError):
    """A vessel worker process failed or vanished; the message names its buoys and carries its traceback."""


@dataclass(frozen=True)
class BuoyShardSpec:
    """What a range of buoy vessels is built from (picklable: a worker builds its own).

    first_row: the first buoy's index among the fleet's buoys (system id first_row + 1); max_thrust_n (count,) N:
    each vessel's thrust limit; full_scale_n: the thrust full RC deflection stands for; options: BuoyPipeline's
    keyword options; link: "mavlink" or "direct"; boot_s: the simulated time the autopilots boot at.
    """

    first_row: int
    max_thrust_n: FloatArray
    frame: LocalFrame
    full_scale_n: float
    options: dict
    link: str
    boot_s: float

    @property
    def count(self) -> int:
        return len(self.max_thrust_n)


class BuoyShard:
    """A range of buoy vessels with their link: what one process runs (the fleet's own range included)."""

    def __init__(self, spec: BuoyShardSpec) -> None:
        self.t = spec.boot_s  # the simulated time the vessels stamp readings with (the last one given)
        self.pipeline = BuoyPipeline(spec.count, spec.frame, spec.max_thrust_n, **spec.options)
        if spec.link == "mavlink":
            self.link: MavlinkTransport | DirectTransport = MavlinkTransport(
                BUOY, spec.count, spec.full_scale_n, lambda: self.t, first_system_id=spec.first_row + 1
            )
        else:
            self.link = DirectTransport()

    def command(self, wish_mps: FloatArray, t_s: float, idle: bool) -> FloatArray:
        """The thrust (count, 2) N the autopilots apply for the wished velocities (count, 2) m/s."""
        self.t = t_s
        return self.link.down(self.pipeline.thrust(wish_mps, t_s, idle=idle), t_s)

    def sense(self, readings: SensorReadings, t_s: float) -> None:
        """Send the readings up the link into the estimators."""
        self.t = t_s
        self.pipeline.feed(self.link.up(readings, t_s))

    def sensed(self, readings: SensorReadings, t_s: float) -> PoseEstimate:
        """`sense`, then the estimates at t_s (what a worker answers, so the fleet needs no second round trip)."""
        self.sense(readings, t_s)
        return self.pipeline.estimate(t_s)

    def estimate(self, t_s: float) -> PoseEstimate:
        return self.pipeline.estimate(t_s)

    def status(self) -> tuple[int, dict[str, int]]:
        """(MPC fallbacks, the link's counters)."""
        return self.pipeline.mpc_fallbacks, self.link.counters()

    def close(self) -> None:
        """Nothing to release: the shard lives in this process (as `ShardedBuoys.close`)."""


def readings_of_rows(readings: SensorReadings, lo: int, hi: int) -> SensorReadings:
    """The readings of agents lo..hi-1, renumbered from 0 (each reading kind's rows picked by agent)."""
    parts = {}
    for field in dataclasses.fields(readings):
        batch = getattr(readings, field.name)
        if batch is None:
            continue
        part = rows_of(batch, (batch.agents >= lo) & (batch.agents < hi))
        parts[field.name] = dataclasses.replace(part, agents=part.agents - lo)
    return SensorReadings(**parts)


def _serve(spec: BuoyShardSpec, conn: Connection) -> None:
    """A worker's loop: build the shard, then answer requests until "stop" (or the fleet's end of the pipe). A
    request that raises is answered with its traceback and the worker goes on, as the shard would in the fleet's
    own process. Ctrl-C reaches the whole process group: the worker leaves it to the fleet process, which stops
    its workers."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        shard = BuoyShard(spec)
    except Exception:
        conn.send(("error", traceback.format_exc()))
        return
    conn.send(("ok", None))
    while True:
        try:
            request = conn.recv()
        except EOFError:  # the fleet process is gone
            return
        verb, args = request[0], request[1:]
        if verb == "stop":
            return
        try:
            answer = ("ok", getattr(shard, verb)(*args))
        except Exception:
            answer = ("error", traceback.format_exc())
        try:
            conn.send(answer)
        except OSError:  # the fleet process is gone
            return


def _stop(workers: list[tuple[multiprocessing.Process, Connection]]) -> None:
    """Ask every worker to stop, wait for it, terminate one that does not (the fleet's finaliser)."""
    for _, conn in workers:
        with contextlib.suppress(OSError):
            conn.send(("stop",))
    for process, conn in workers:
        process.join(STOP_TIMEOUT_S)
        if process.is_alive():
            process.terminate()
            process.join()
        conn.close()


def shard_ranges(n: int, processes: int) -> list[tuple[int, int]]:
    """[lo, hi) of each of min(processes, n) contiguous ranges of n rows, sizes differing by at most one."""
    parts = max(1, min(processes, n))
    bounds = [round(k * n / parts) for k in range(parts + 1)]
    return list(itertools.pairwise(bounds))


class ShardedBuoys:
    """n buoy vessels over `processes` processes: the first range here, the others in workers.

    Same interface as one BuoyShard over all n rows (command, sense, estimate, status), same results; `close`
    stops the workers (also done when the object is collected or the interpreter exits).
    """

    def __init__(self, spec: BuoyShardSpec, processes: int) -> None:
        self.ranges = shard_ranges(spec.count, processes)
        self.n = spec.count
        context = multiprocessing.get_context("spawn")
        self.workers: list[tuple[multiprocessing.Process, Connection]] = []
        self._finalizer = weakref.finalize(self, _stop, self.workers)
        for lo, hi in self.ranges[1:]:
            ours, theirs = context.Pipe()
            process = context.Process(
                target=_serve, args=(self._part(spec, lo, hi), theirs), name=f"bob-buoys-{lo}-{hi - 1}", daemon=True
            )
            process.start()
            theirs.close()
            self.workers.append((process, ours))
        lo, hi = self.ranges[0]
        self.local = BuoyShard(self._part(spec, lo, hi))
        for k in range(len(self.workers)):
            self._answer(k, starting=True)  # built
        self._estimate: tuple[float, PoseEstimate] | None = None

    @staticmethod
    def _part(spec: BuoyShardSpec, lo: int, hi: int) -> BuoyShardSpec:
        return dataclasses.replace(spec, first_row=spec.first_row + lo, max_thrust_n=spec.max_thrust_n[lo:hi])

    def _gone(self, k: int, error: BaseException, starting: bool = False) -> VesselProcessError:
        process, _ = self.workers[k]
        process.join(0.5)
        lo, hi = self.ranges[k + 1]
        said = f"the worker process of buoys {lo}-{hi - 1} ended without answering (exit code {process.exitcode}; "
        if starting:
            self.close()
            return VesselProcessError(
                f"{said}{error!r}) while starting. A worker imports the script that started it again (Python's "
                "'spawn'): a script that builds a fleet with vessel_processes > 1 must do so under "
                '`if __name__ == "__main__":`, and cannot be read from standard input. Its error is printed above.'
            )
        return VesselProcessError(f"{said}{error!r}): killed, or out of memory? The run cannot go on without them.")

    def _answer(self, k: int, starting: bool = False):
        _, conn = self.workers[k]
        try:
            status, value = conn.recv()
        except (EOFError, OSError) as error:
            raise self._gone(k, error, starting) from None
        if status == "error":
            lo, hi = self.ranges[k + 1]
            if starting:
                self.close()
            raise VesselProcessError(f"the worker process of buoys {lo}-{hi - 1} failed:\n{value}")
        return value

    def _ask_all(self, verb: str, per_worker_args, local_result):
        """Send each worker its request, run the local part meanwhile, then gather: [local, worker 1, ...]. Every
        answer is read before a failure is raised, so none is left in a pipe to be taken for the next one's."""
        for k, ((_, conn), args) in enumerate(zip(self.workers, per_worker_args, strict=True)):
            try:
                conn.send((verb, *args))
            except OSError as error:
                raise self._gone(k, error) from None
        results, failure = [], None
        try:
            results.append(local_result())
        except Exception as error:
            failure = error
        for k in range(len(self.workers)):
            try:
                results.append(self._answer(k))
            except VesselProcessError as error:
                failure = failure or error
        if failure is not None:
            raise failure
        return results

    def command(self, wish_mps: FloatArray, t_s: float, idle: bool) -> FloatArray:
        (lo, hi), rest = self.ranges[0], self.ranges[1:]
        self._estimate = None  # a command may change what the estimators hold
        args = [(wish_mps[a:b], t_s, idle) for a, b in rest]
        parts = self._ask_all("command", args, lambda: self.local.command(wish_mps[lo:hi], t_s, idle))
        return np.concatenate(parts)

    def sense(self, readings: SensorReadings, t_s: float) -> PoseEstimate:
        (lo, hi), rest = self.ranges[0], self.ranges[1:]
        args = [(readings_of_rows(readings, a, b), t_s) for a, b in rest]
        parts = self._ask_all("sensed", args, lambda: self.local.sensed(readings_of_rows(readings, lo, hi), t_s))
        estimate = _joined(parts)
        self._estimate = (t_s, estimate)
        return estimate

    def estimate(self, t_s: float) -> PoseEstimate:
        """The estimates at t_s (those of the last `sense` when it was at t_s, else asked of every process)."""
        if self._estimate is not None and self._estimate[0] == t_s:
            return self._estimate[1]
        return _joined(self._ask_all("estimate", [(t_s,)] * len(self.workers), lambda: self.local.estimate(t_s)))

    def status(self) -> tuple[int, dict[str, int]]:
        parts = self._ask_all("status", [()] * len(self.workers), self.local.status)
        totals: dict[str, int] = {}
        for _, counters in parts:
            for name, value in counters.items():
                totals[name] = totals.get(name, 0) + value
        return sum(fallbacks for fallbacks, _ in parts), totals

    def close(self) -> None:
        """Stop the worker processes (idempotent)."""
        self._finalizer()


def _joined(parts: list[PoseEstimate]) -> PoseEstimate:
    """The estimates of consecutive ranges as one."""
    return PoseEstimate(
        *(np.concatenate([getattr(p, f.name) for p in parts]) for f in dataclasses.fields(PoseEstimate))
    )
