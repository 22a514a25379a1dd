"""Starting, watching and stopping the autonomy processes of a process fleet (`sitl.fleets.process_fleet`).

Two ways to start them. `exec`: one `bob-autonomy run` per vessel through subprocess (any command, e.g. a
test's fake autonomy). `fork-server` (the default for the real `bob-autonomy`): one `bob-autonomy fork-server`
process imports everything a vessel needs once and forks a child per vessel (`bob_autonomy.cli.serve_forks`):
45 interpreters each importing numpy, scipy, casadi, pymavlink and pydantic cost ~1 s of CPU apiece, which on
2 cores was most of a 33-39 s start. Either way each vessel runs in its own session (its own process group),
its output goes to a file, and it gets SIGTERM if its parent dies (Linux).

Stopping (`stop_all`): SIGTERM to every process group, serve the vehicles while they send their last neutral
commands and exit, SIGKILL for any left after the timeout; how long each took (wall s from the SIGTERM to
its exit) and how many had to be killed are returned. `memory_summary` reads the processes' resident memory
and CPU share.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import signal
import statistics
import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Protocol

from bob_autonomy.cli import die_with_parent, lower_priority

SPAWN_TIMEOUT_S = 60.0  # wall s for the fork server to answer a request (the first waits for its imports)


class SupervisionError(RuntimeError):
    """An autonomy process could not be started; the message says why."""


class Process(Protocol):
    """What the fleet needs of an autonomy process (subprocess.Popen or ForkedProcess)."""

    pid: int
    returncode: int | None

    def poll(self) -> int | None: ...

    def wait(self, timeout: float | None = None) -> int: ...


class ForkedProcess:
    """A child of the fork server, seen from the fleet: like subprocess.Popen's pid, returncode, poll(), wait().

    exited_at: time.monotonic() (system-wide on Linux) when the fork server reaped it, s; None while it runs.
    """

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.returncode: int | None = None
        self.exited_at: float | None = None
        self._done = threading.Event()

    def _exited(self, status: int, at: float) -> None:
        self.returncode, self.exited_at = status, at
        self._done.set()

    def poll(self) -> int | None:
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if not self._done.wait(timeout):
            raise subprocess.TimeoutExpired(f"autonomy process {self.pid}", timeout or 0.0)
        assert self.returncode is not None
        return self.returncode


class ForkServer:
    """A `bob-autonomy fork-server` process and the children it forks (see the module docstring).

    command: how to run `bob-autonomy` (e.g. (sys.executable, "-m", "bob_autonomy.cli")). log: where the fork
    server's own standard error goes. Call close() when every child has been stopped.
    """

    def __init__(self, command: Sequence[str], log: IO[bytes]) -> None:
        env = {**os.environ, "PYTHONUNBUFFERED": "1", "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
        try:
            self.server = subprocess.Popen(
                [*command, "fork-server"],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=log,
                start_new_session=True,  # Ctrl-C reaches the fleet, which stops the children in order
                preexec_fn=die_with_parent,
                env=env,
            )
        except OSError as error:
            raise SupervisionError(f"cannot start the fork server {list(command)}: {error}") from error
        self.children: dict[int, ForkedProcess] = {}
        self._replies: queue.Queue[dict] = queue.Queue()
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, name="fork-server replies", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.server.stdout is not None
        for line in self.server.stdout:
            try:
                message = json.loads(line)
            except ValueError:
                continue
            if "exit" in message:
                with self._lock:
                    child = self.children.get(int(message["exit"]))
                if child is not None:
                    child._exited(int(message["status"]), float(message["t"]))
            else:
                if "pid" in message:
                    with self._lock:  # registered before any exit of it can be read (replies come in order)
                        self.children[int(message["pid"])] = ForkedProcess(int(message["pid"]))
                self._replies.put(message)
        self._replies.put({"error": f"the fork server ended (status {self.server.wait()})"})

    def spawn(self, argv: Sequence[str], out: Path, nice: int = 0) -> ForkedProcess:
        """Fork a child running `bob-autonomy` with argv, its standard output and error to `out`, `nice` added
        to its niceness."""
        assert self.server.stdin is not None
        request = json.dumps({"argv": [str(a) for a in argv], "out": str(out), "nice": nice}) + "\n"
        try:
            self.server.stdin.write(request.encode())
            self.server.stdin.flush()
            reply = self._replies.get(timeout=SPAWN_TIMEOUT_S)
        except (OSError, queue.Empty) as error:
            raise SupervisionError(f"the fork server did not start a vessel: {error or 'no answer'}") from error
        if "pid" not in reply:
            raise SupervisionError(f"the fork server did not start a vessel: {reply.get('error')}")
        with self._lock:
            return self.children[int(reply["pid"])]

    def close(self, timeout_s: float = 5.0) -> None:
        """End of requests: the fork server exits once its children have (it is killed after timeout_s)."""
        with contextlib.suppress(OSError):
            if self.server.stdin is not None:
                self.server.stdin.close()
        try:
            self.server.wait(timeout_s)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.server.pid, signal.SIGKILL)
            self.server.wait()
        self._reader.join(timeout_s)


def start_exec(command: Sequence[str], out: IO[bytes], nice: int = 0) -> subprocess.Popen:
    """Start `command` as its own session, `nice` added to its niceness, output to `out`, SIGTERM when this
    process dies (Linux)."""

    def prepare() -> None:  # after setsid: the new session's own scheduling group
        lower_priority(nice)
        die_with_parent()

    return subprocess.Popen(
        list(command),
        stdin=subprocess.DEVNULL,
        stdout=out,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        preexec_fn=prepare,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


@dataclass
class StopReport:
    """How the autonomy processes stopped: wall s from SIGTERM to exit per process (None: killed or already
    gone), and how many were killed."""

    stop_s: list[float | None] = field(default_factory=list)
    killed: int = 0

    def summary(self) -> dict[str, object]:
        done = [s for s in self.stop_s if s is not None]
        return {
            "stop_s": [None if s is None else round(s, 3) for s in self.stop_s],
            "stop_s_max": round(max(done), 3) if done else None,
            "stop_s_median": round(statistics.median(done), 3) if done else None,
        }


def stop_all(processes: Sequence[Process], timeout_s: float, serve: Callable[[float], None]) -> StopReport:
    """SIGTERM to every running process's group; call serve(wait_s) (wall s) while any runs, up to timeout_s;
    then SIGKILL to what is left; reap them all."""
    report = StopReport(stop_s=[None] * len(processes))
    signalled = time.monotonic()
    running = []
    for i, process in enumerate(processes):
        if process.poll() is None:
            running.append(i)
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(process.pid, signal.SIGTERM)
    deadline = signalled + timeout_s
    while running and time.monotonic() < deadline:
        serve(0.02)
        now = time.monotonic()
        for i in list(running):
            if processes[i].poll() is not None:
                exited = getattr(processes[i], "exited_at", None) or now
                report.stop_s[i] = max(0.0, exited - signalled)
                running.remove(i)
    for i in running:
        if processes[i].poll() is None:
            report.killed += 1
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(processes[i].pid, signal.SIGKILL)
        else:  # exited just now
            exited = getattr(processes[i], "exited_at", None) or time.monotonic()
            report.stop_s[i] = max(0.0, exited - signalled)
    for process in processes:
        process.wait()
    return report


def memory_of(pid: int) -> dict[str, float] | None:
    """Resident memory of a running process, MiB: rss (every page it maps that is in memory, shared ones
    included) and pss (shared pages divided among their sharers: what it adds). None if it is gone or not
    Linux."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        rollup = Path(f"/proc/{pid}/smaps_rollup").read_text()
    except OSError:
        return None
    values = {}
    for text, key, name in ((status, "VmRSS:", "rss"), (rollup, "Pss:", "pss")):
        for line in text.splitlines():
            if line.startswith(key):
                values[name] = round(int(line.split()[1]) / 1024, 1)
                break
    return values if len(values) == 2 else None


def cpu_share_of(pid: int) -> float | None:
    """Share of one core a running process has used since it started (user + system CPU s per wall s); None if
    it is gone or not Linux."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        uptime_s = float(Path("/proc/uptime").read_text().split()[0])
    except (OSError, IndexError, ValueError):
        return None
    ticks = os.sysconf("SC_CLK_TCK")
    cpu_s = (int(fields[11]) + int(fields[12])) / ticks  # utime, stime (fields 14 and 15 of stat)
    alive_s = uptime_s - int(fields[19]) / ticks  # starttime (field 22)
    return cpu_s / alive_s if alive_s > 0 else None


def memory_summary(processes: Sequence[Process]) -> dict[str, float | None]:
    """Median and maximum RSS and PSS (MiB) and CPU share (of one core, since each started) over the processes
    still running."""
    running = [p.pid for p in processes if p.poll() is None]
    seen: list[dict[str, float]] = []
    for pid in running:
        memory, cpu = memory_of(pid), cpu_share_of(pid)
        if memory is not None and cpu is not None:
            seen.append({**memory, "cpu_share": cpu})
    out: dict[str, float | None] = {}
    for name in ("cpu_share",):
        values = [m[name] for m in seen]
        out[f"{name}_median"] = round(statistics.median(values), 4) if values else None
        out[f"{name}_max"] = round(max(values), 4) if values else None
    for name in ("rss", "pss"):
        values = [m[name] for m in seen]
        out[f"{name}_mib_median"] = round(statistics.median(values), 1) if values else None
        out[f"{name}_mib_max"] = max(values) if values else None
    out["measured"] = len(seen)
    return out
