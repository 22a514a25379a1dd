"""Starting and stopping a process fleet's autonomy processes (sitl/fleets/process_supervision.py, the
`bob-autonomy fork-server` of bob_autonomy/cli.py, sitl/fleets/process_fleet.py).

(a) the fork server starts `bob-autonomy` children from one interpreter and reports each one's exit status;
(b) stop_all reports how long each process took to stop after SIGTERM, and kills (and counts) one that
ignores it; (c) end to end: SIGTERM to `bob-sitl fleet --processes` stops every vessel by itself, with the
stop times and the vessels' memory in metrics.json, and nothing left running.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from pathlib import Path

import pytest

from sitl.fleets.process_fleet import AUTONOMY_COMMAND
from sitl.fleets.process_supervision import ForkServer, SupervisionError, memory_of, start_exec, stop_all
from sitl.fleets.vessel_logs import stopped_summary
from sitl.vehicles.vehicle_server import vehicle_port
from tests.test_process_fleet import _bindable, gone, start_fleet_cli

# Real time, sockets and processes: in one xdist worker with the other process-fleet tests.
pytestmark = pytest.mark.xdist_group("realtime")


def test_fork_server_runs_bob_autonomy_children_and_reports_their_exit(tmp_path: Path) -> None:
    with open(tmp_path / "fork-server.out", "wb") as log:
        forks = ForkServer(AUTONOMY_COMMAND, log)
        try:
            listing = forks.spawn(["behaviors"], tmp_path / "behaviors.out")
            bad = forks.spawn(["run", "--system-id", "1"], tmp_path / "bad.out")  # no --vehicle: exit 2
            assert listing.wait(30.0) == 0 and bad.wait(30.0) == 2
            with pytest.raises(SupervisionError, match=r"nice must be 0\.\.19, got 25"):
                forks.spawn(["behaviors"], tmp_path / "never.out", nice=25)
            assert listing.exited_at is not None and listing.pid != bad.pid
        finally:
            forks.close()
    assert "bob-rule" in (tmp_path / "behaviors.out").read_text()
    assert "missing required setting(s): --vehicle" in (tmp_path / "bad.out").read_text()
    assert forks.server.returncode == 0 and gone(listing.pid) and gone(bad.pid)


def test_stop_all_times_each_stop_and_kills_what_ignores_sigterm(tmp_path: Path) -> None:
    up = "print('up', flush=True)\ntime.sleep(60)\n"
    polite = "import signal, sys, time\nsignal.signal(signal.SIGTERM, lambda *_: sys.exit(0))\n" + up
    stubborn = "import signal, time\nsignal.signal(signal.SIGTERM, signal.SIG_IGN)\n" + up
    outs = [open(tmp_path / f"{k}.out", "wb") for k in range(2)]  # noqa: SIM115 - closed below
    try:
        codes = (polite, stubborn)
        processes = [start_exec([sys.executable, "-c", code], out) for code, out in zip(codes, outs, strict=True)]
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline and not all("up" in (tmp_path / f"{k}.out").read_text() for k in (0, 1)):
            time.sleep(0.05)  # until both have set their handlers
        memory = memory_of(processes[0].pid)
        assert memory is not None and 0 < memory["pss"] <= memory["rss"]
        served = []
        report = stop_all(processes, 1.0, lambda wait: (served.append(wait), time.sleep(wait)))
    finally:
        for out in outs:
            out.close()
    assert report.killed == 1 and [p.returncode for p in processes] == [0, -signal.SIGKILL]
    assert report.stop_s[0] is not None and 0.0 <= report.stop_s[0] < 1.0 and report.stop_s[1] is None
    assert served and all(gone(p.pid) for p in processes)
    assert report.summary()["stop_s_max"] == report.summary()["stop_s_median"] == round(report.stop_s[0], 3)


def test_vessels_run_at_a_lower_priority_in_their_own_session(tmp_path: Path) -> None:
    report = "import os\ngroup = '/proc/self/autogroup'\n"
    report += "print(os.nice(0), os.getsid(0) == os.getpid(), open(group).read() if os.path.exists(group) else '-')"
    with open(tmp_path / "nice.out", "wb") as out:
        assert start_exec([sys.executable, "-c", report], out, nice=3).wait(30.0) == 0
    niceness, own_session, autogroup = (tmp_path / "nice.out").read_text().split(maxsplit=2)
    assert int(niceness) == os.nice(0) + 3 and own_session == "True"
    if "nice" in autogroup:  # Linux with sched_autogroup: the session's group is lowered too
        assert autogroup.split()[-1] == "3"


def descendants(pid: int) -> list[int]:
    """PIDs of every process below `pid` (Linux /proc)."""
    from tests.test_process_fleet import fleet_children

    found, todo = [], [pid]
    while todo:
        children = fleet_children(todo.pop())
        found += children
        todo += children
    return found


def test_sigterm_stops_every_vessel_by_itself_and_reports_stop_times_and_memory(tmp_path: Path) -> None:
    cli, out, base, mesh, _ = start_fleet_cli(tmp_path, 3)
    try:
        assert cli.poll() is None, cli.stderr.read() if cli.stderr else ""
        time.sleep(1.0)
        running = descendants(cli.pid)
        assert len(running) == 4  # the fork server and its three vessels
        cli.send_signal(signal.SIGTERM)
        _, stderr = cli.communicate(timeout=30)
    finally:
        if cli.poll() is None:
            cli.kill()
    assert cli.returncode == 1, stderr  # written, but an interrupted run does not pass
    processes = json.loads((out / "metrics.json").read_text())["processes"]
    assert processes["exit_codes"] == [0, 0, 0] and processes["killed"] == 0
    assert processes["launcher"] == "fork-server"
    assert len(processes["stop_s"]) == 3 and all(0.0 < t < 6.0 for t in processes["stop_s"])
    assert processes["stop_s_max"] == max(processes["stop_s"])
    memory = processes["memory"]
    assert memory["measured"] == 3 and 0 < memory["pss_mib_median"] <= memory["rss_mib_median"]
    summaries = [stopped_summary(p) for p in sorted(out.glob("vessel-0*.log"))]  # each vessel's own stop line
    assert len(summaries) == 3 and all(s is not None and s["mpc_fallbacks"] >= 0 for s in summaries)
    assert all(gone(pid) for pid in running)
    assert all(_bindable(vehicle_port(i, base)) for i in range(3)) and _bindable(mesh)
