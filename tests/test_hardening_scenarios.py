"""Issue #17 item 5: scenario files and `bob-sitl` options that cannot hurt.

Each bad scenario file or option, fed to the real `bob-sitl` main(), must give exit status 2 and one
message naming the file (or option) and the key, and must leave nothing behind: no output, no hidden
staging directory, no parent directory created for it, anywhere under the test's directory. Runs too
large to fit are refused before anything is allocated, with the figures. Interrupted and failed runs
clean up after themselves.
"""

from __future__ import annotations

import copy
import os
import signal
import socket
import subprocess
import sys
import time
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import sitl.experiments.runner
import sitl.experiments.sweep
from sitl.cli import main
from sitl.experiments.runner import STAGING_MARKER, OutputDirectoryError, write_atomically
from sitl.experiments.scenario import ScenarioError, _toml_table, polygon_problem, validate_scenario
from sitl.fleets.budget import MAX_AGENTS, check_run_size, run_size

BASE: dict[str, Any] = {
    "name": "tiny",
    "duration_s": 0.4,
    "dt_s": 0.1,
    "log_period_s": 0.2,
    "world": {"rooms": [{"name": "room", "polygon": [[0.0, 0.0], [5.0, 0.0], [5.0, 5.0], [0.0, 5.0]]}]},
    "groups": [
        {
            "name": "g",
            "count": 3,
            "body": "ebot",
            "behavior": "perimeter-defense",
            "params": {"max_speed": 0.2},
            "start": {"box": {"min": [1.0, 1.0], "max": [2.0, 2.0]}},
        }
    ],
    "events": [{"t_s": 0.2, "action": "remove", "agents": [2]}],
}


def tree(root: Path) -> list[str]:
    """Every path under `root`, hidden ones included, relative and sorted."""
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def scenario_file(tmp_path: Path, data: dict[str, Any] | bytes, name: str = "scenario.toml") -> Path:
    path = tmp_path / name
    path.write_bytes(data if isinstance(data, bytes) else _toml_table(data, []).encode())
    return path


def changed(dotted: str, value: Any, data: dict[str, Any] = BASE) -> dict[str, Any]:
    """A copy of `data` with the value at the dotted key replaced (list indices as numbers)."""
    data = copy.deepcopy(data)
    *parents, last = dotted.split(".")
    node: Any = data
    for key in parents:
        node = node[int(key)] if isinstance(node, list) else node[key]
    if isinstance(node, list):
        node[int(last)] = value
    else:
        node[last] = value
    return data


def assert_refused(tmp_path: Path, capsys, argv: list[str], *expected: str) -> str:
    """main(argv) run in tmp_path exits 2 with one message containing `expected`, and writes nothing."""
    before = tree(tmp_path)
    status = main(argv)
    err = capsys.readouterr().err
    assert status == 2, err
    assert err.startswith("bob-sitl: ") and "Traceback" not in err
    for text in expected:
        assert text in err, f"{text!r} not in {err!r}"
    assert tree(tmp_path) == before, "a refused run must not leave files or (hidden) directories"
    return err


@pytest.fixture
def in_tmp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Work in tmp_path/work, so that the default runs/NAME and any escape from it stay under tmp_path."""
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    return tmp_path


def test_the_base_scenario_runs(in_tmp: Path, capsys) -> None:
    path = scenario_file(in_tmp, BASE)
    assert main(["run", str(path), "--quiet"]) in (0, 1)
    assert sorted(p.name for p in (in_tmp / "work" / "runs").iterdir()) == ["tiny"]
    assert not any(p.name.startswith(".") for p in (in_tmp / "work" / "runs").iterdir())


# ---------------------------------------------------------------- bad scenario files

DEEP = 100_000
BAD_FILES: dict[str, tuple[dict[str, Any] | bytes, tuple[str, ...]]] = {
    # name: (file contents, what the message must say besides the file's name)
    "name climbs out of runs/": (changed("name", "../../x"), ("key 'name'", "single file name")),
    "name is an absolute path": (changed("name", "/tmp/bob-sitl-escape"), ("key 'name'",)),
    "name has a slash": (changed("name", "a/b"), ("key 'name'",)),
    "name is ..": (changed("name", ".."), ("key 'name'",)),
    "name is hidden": (changed("name", ".staging"), ("key 'name'",)),
    "name is empty": (changed("name", ""), ("key 'name'",)),
    "name is a backslash path": (changed("name", "..\\..\\x"), ("key 'name'",)),
    "name too long": (changed("name", "x" * 101), ("key 'name'",)),
    "dt_s inf": (changed("dt_s", float("inf")), ("key 'dt_s'", "finite")),
    "duration_s nan": (changed("duration_s", float("nan")), ("key 'duration_s'", "finite")),
    "log_period_s -inf": (changed("log_period_s", float("-inf")), ("key 'log_period_s'", "finite")),
    "behaviour parameter nan": (changed("groups.0.params.max_speed", float("nan")), ("groups.0.params.max_speed",)),
    "start box infinite": (changed("groups.0.start.box.max", [float("inf"), 2.0]), ("groups.0.start.box.max.0",)),
    "start box beyond 1e7 m": (changed("groups.0.start.box.max", [1e300, 2.0]), ("groups.0.start.box.max.0",)),
    "heading nan": (changed("groups.0.start.heading_deg", float("nan")), ("groups.0.start.heading_deg",)),
    "event time inf": (changed("events.0.t_s", float("inf")), ("events.0.t_s",)),
    "room vertex nan": (changed("world.rooms.0.polygon.2", [float("nan"), 5.0]), ("world.rooms.0.polygon.2.0",)),
    "wind nan": (changed("environment", {"wind": {"speed_mps": float("nan")}}), ("environment.wind.speed_mps",)),
    "current grid inf": (
        changed("environment", {"current": {"grid": {"u_mps": [[float("inf")]]}}}),
        ("environment.current.grid.u_mps.0.0",),
    ),
    "sensor nan": (changed("sensors", {"gps": {"noise_m": float("nan")}}), ("sensors.gps.noise_m",)),
    "radio inf": (changed("network", {"radio": {"a": float("inf")}}), ("network.radio.a",)),
    "metric threshold nan": (changed("metrics", {"params": {"x": float("nan")}}), ("metrics.params.x",)),
    # The metrics run after the whole run: what they would trip on is refused before it starts.
    "metric parameter misspelt": (
        changed("metrics", {"kind": "perimeter-defense", "params": {"min_coverag": 0.7}}),
        ("metrics.params", "'min_coverag'", "did you mean 'min_coverage'?"),
    ),
    "metric names a missing leader": (
        changed("metrics", {"kind": "leader-follower", "params": {"leader": 3}}),
        ("metrics.params", "'leader'", "agent 3", "agents 0..2"),
    ),
    "metric names a missing weak agent": (
        changed("metrics", {"kind": "leader-follower", "params": {"weak_agents": [1.0, 44.0]}}),
        ("'weak_agents'", "agent 44"),
    ),
    "metric without its goal": (
        changed("metrics", {"kind": "avoidance", "params": {"goal_x_m": 1.0}}),
        ("metrics.params", "need 'goal_y_m'"),
    ),
    "metric outcome unknown": (
        changed("metrics", {"kind": "avoidance", "params": {"goal_x_m": 1.0, "goal_y_m": 1.0, "expected": "over"}}),
        ("'expected'", "'yield', 'through', 'around'"),
    ),
    "metric grid of zero": (
        changed("metrics", {"kind": "perimeter-defense", "params": {"grid_m": 0.0}}),
        ("'grid_m'", "positive"),
    ),
    "self-intersecting room": (
        changed("world.rooms.0.polygon", [[0.0, 0.0], [5.0, 5.0], [5.0, 0.0], [0.0, 5.0]]),
        ("key 'world.rooms.0.polygon'", "crosses itself"),
    ),
    "zero-area room": (
        changed("world.rooms.0.polygon", [[0.0, 0.0], [5.0, 0.0], [10.0, 0.0]]),
        ("key 'world.rooms.0.polygon'", "zero area"),
    ),
    "room folding back": (
        changed("world.rooms.0.polygon", [[0.0, 0.0], [5.0, 0.0], [2.0, 0.0], [2.0, 5.0]]),
        ("key 'world.rooms.0.polygon'", "fold back"),
    ),
    "room with a repeated vertex": (
        changed("world.rooms.0.polygon", [[0.0, 0.0], [5.0, 0.0], [5.0, 0.0], [0.0, 5.0]]),
        ("key 'world.rooms.0.polygon'", "same point"),
    ),
    "room with two vertices": (changed("world.rooms.0.polygon", [[0.0, 0.0], [5.0, 0.0]]), ("world.rooms.0.polygon",)),
    "wall of no length": (changed("world", {"walls": [[[1.0, 1.0], [1.0, 1.0]]]}), ("key 'world.walls'",)),
    "event names a missing agent": (changed("events.0.agents", [7]), ("events.0.agents", "agent 7")),
    "event names a negative agent": (changed("events.0.agents", [-1]), ("events.0.agents.0",)),
    "negative seed": (changed("seed", -1), ("key 'seed'",)),
    "seed beyond 64 bits": (changed("seed", 2**70), ("key 'seed'",)),
    "count 1e11": (changed("groups.0.count", 1e11), ("'groups.0.count' = 100,000,000,000", "200,000")),
    "duration 1e300": (changed("duration_s", 1e300), ("agent-steps", "duration_s", "at most 1,000,000,000")),
    "dt_s 1e-300": (changed("dt_s", 1e-300), ("agent-steps", "dt_s")),
    "physics agent-steps": (
        {**changed("duration_s", 1e7), "fidelity": "physics"},  # 3e8: fine kinematic, not physics
        ("agent-steps", "at most 100,000,000 at physics fidelity"),
    ),
    "trajectory rows": (
        {**changed("groups.0.count", 100_000), "duration_s": 5000.0, "dt_s": 1.0, "log_period_s": 1.0},
        ("trajectory rows", "log_period_s"),
    ),
    "nested 100,000 deep": (b"a = " + b"[" * DEEP + b"]" * DEEP, ("nested too deeply",)),
    "integer of 5000 digits": (b"seed = 1" + b"0" * 5000, ("not valid TOML", "digits")),
    "not UTF-8": (b'name = "caf\xe9"\n', ("not valid TOML", "UTF-8")),
}


@pytest.mark.parametrize("content, expected", BAD_FILES.values(), ids=BAD_FILES)
def test_a_bad_scenario_file_exits_2_naming_file_and_key(in_tmp: Path, capsys, content, expected) -> None:
    path = scenario_file(in_tmp, content)
    err = assert_refused(in_tmp, capsys, ["run", str(path), "--quiet"], str(path), *expected)
    assert len(err) < 2000


def test_an_absolute_name_writes_nothing_there(in_tmp: Path, capsys) -> None:
    target = in_tmp / "escaped"
    path = scenario_file(in_tmp, changed("name", str(target)))
    assert_refused(in_tmp, capsys, ["run", str(path), "--quiet"], "key 'name'")
    assert not target.exists()


def test_a_thousand_bad_keys_make_a_short_message(in_tmp: Path, capsys) -> None:
    data = copy.deepcopy(BASE)
    data["events"] = [{"t_s": -1.0, "action": "remove", "agents": [0]}] * 1000
    path = scenario_file(in_tmp, data)
    err = assert_refused(in_tmp, capsys, ["run", str(path), "--quiet"], "key 'events.0.t_s'", "and 980 more")
    assert err.count("\n") < 25


@pytest.mark.parametrize(
    "make, expected",
    [
        (lambda p: p.mkdir(), "not a regular file but a directory"),
        (lambda p: os.mkfifo(p), "not a regular file"),
        (lambda p: p.write_bytes(b"#" * (16 << 20) + b"\n"), "at most 16,777,216"),
        (lambda p: None, "no such scenario file"),
    ],
    ids=["directory", "fifo", "over 16 MiB", "missing"],
)
def test_a_scenario_path_that_is_not_a_small_file_exits_2(in_tmp: Path, capsys, make, expected) -> None:
    path = in_tmp / "scenario.toml"
    make(path)
    assert_refused(in_tmp, capsys, ["run", str(path), "--quiet"], str(path), expected)


def test_a_name_too_long_for_the_file_system_exits_2(in_tmp: Path, capsys) -> None:
    assert_refused(in_tmp, capsys, ["run", "x" * 5000, "--quiet"], "cannot be a scenario file")


def test_a_packaged_name_cannot_reach_other_files(in_tmp: Path, capsys) -> None:
    assert_refused(in_tmp, capsys, ["run", "../scenarios/heading-consensus", "--quiet"], "no scenario named")


# ---------------------------------------------------------------- bad options

BAD_OPTIONS = {
    "--agents 0": (["--agents", "0"], ("--agents must be at least 1, got 0",)),
    "--agents -5": (["--agents", "-5"], ("--agents must be at least 1",)),
    "--agents 10000000": (["--agents", "10000000"], ("10,000,000 agents", "at most 200,000", "--force")),
    "--duration 1e300": (["--duration", "1e300"], ("agent-steps", "--duration", "--force")),
    "--duration nan": (["--duration", "nan"], ("key 'duration_s'", "finite")),
    "--duration inf": (["--duration", "inf"], ("key 'duration_s'", "finite")),
    "--duration -1": (["--duration", "-1"], ("key 'duration_s'",)),
    "--seed -1": (["--seed", "-1"], ("key 'seed'",)),
}


@pytest.mark.parametrize("options, expected", BAD_OPTIONS.values(), ids=BAD_OPTIONS)
def test_a_bad_option_exits_2_with_its_figure(in_tmp: Path, capsys, options, expected) -> None:
    path = scenario_file(in_tmp, BASE)
    assert_refused(in_tmp, capsys, ["run", str(path), "--quiet", *options], *expected)


def test_the_size_limits_are_checked_before_anything_is_allocated(in_tmp: Path, capsys, monkeypatch) -> None:
    def no_fleet(*args, **kwargs):
        raise AssertionError("the fleet was built")

    monkeypatch.setattr(sitl.experiments.runner, "LockstepFleet", no_fleet)
    path = scenario_file(in_tmp, BASE)
    start = time.perf_counter()
    assert_refused(in_tmp, capsys, ["run", str(path), "--agents", str(10**15)], "at most 200,000")
    assert_refused(in_tmp, capsys, ["run", str(path), "--duration", "1e308"], "agent-steps")
    assert time.perf_counter() - start < 2.0


def test_force_lifts_the_limits(in_tmp: Path, capsys) -> None:
    scenario = validate_scenario({**changed("duration_s", 1e8), "log_period_s": 1e5}, "big")
    with pytest.raises(ScenarioError, match="agent-steps"):
        check_run_size(scenario, "big")
    assert check_run_size(scenario, "big", force=True).agent_steps == pytest.approx(3e9)
    assert run_size(validate_scenario(changed("groups.0.count", MAX_AGENTS), "x")).agents == MAX_AGENTS


@pytest.mark.parametrize(
    "out, expected",
    [
        ("afile", "afile exists and is not a directory"),
        ("afile/sub", "afile is a file, not a directory"),
        ("afile/sub/deeper", "afile is a file, not a directory"),
        (".", "give a new directory"),
        ("..", "give a new directory"),
        ("precious", "is not a previous run's output"),
    ],
)
def test_a_bad_output_directory_exits_2_before_running(in_tmp: Path, capsys, monkeypatch, out, expected) -> None:
    work = in_tmp / "work"
    (work / "afile").write_text("keep me")
    (work / "precious").mkdir()
    (work / "precious" / "thesis.tex").write_text("keep me")
    monkeypatch.setattr(sitl.experiments.runner, "LockstepFleet", lambda *a: pytest.fail("ran before checking --out"))
    path = scenario_file(in_tmp, BASE)
    assert_refused(in_tmp, capsys, ["run", str(path), "--quiet", "--out", out], expected)
    assert (work / "afile").read_text() == "keep me"


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write into a read-only directory")
def test_a_read_only_output_directory_exits_2(in_tmp: Path, capsys) -> None:
    locked = in_tmp / "work" / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        path = scenario_file(in_tmp, BASE)
        assert_refused(in_tmp, capsys, ["run", str(path), "--out", str(locked / "run")], "not writable")
    finally:
        locked.chmod(0o755)


# ---------------------------------------------------------------- failures leave nothing behind


def test_ctrl_c_during_a_run_leaves_nothing_and_exits_130(in_tmp: Path, capsys, monkeypatch) -> None:
    steps = {"n": 0}
    real_step = sitl.experiments.runner.LockstepFleet.step

    def interrupted(self):
        steps["n"] += 1
        if steps["n"] == 3:
            raise KeyboardInterrupt
        return real_step(self)

    monkeypatch.setattr(sitl.experiments.runner.LockstepFleet, "step", interrupted)
    path = scenario_file(in_tmp, BASE)
    before = tree(in_tmp)
    assert main(["run", str(path), "--quiet", "--out", "deep/new/run"]) == 130
    assert "interrupted; nothing written to deep/new/run" in capsys.readouterr().err
    assert steps["n"] == 3
    assert tree(in_tmp) == before  # no staging directory, and no deep/new/ created for it


def test_a_failed_write_leaves_nothing_and_keeps_the_previous_output(in_tmp: Path, capsys, monkeypatch) -> None:
    path = scenario_file(in_tmp, BASE)
    assert main(["run", str(path), "--quiet", "--out", "run"]) in (0, 1)
    before = {p.name: p.read_bytes() for p in (in_tmp / "work" / "run").iterdir()}
    snapshot = tree(in_tmp)

    def disk_full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(sitl.experiments.runner, "write_figures", disk_full)
    assert main(["run", str(path), "--quiet", "--out", "run", "--seed", "3"]) == 2
    assert "cannot write the outputs to run: [Errno 28] No space left on device" in capsys.readouterr().err
    assert tree(in_tmp) == snapshot
    assert {p.name: p.read_bytes() for p in (in_tmp / "work" / "run").iterdir()} == before


def test_a_rerun_replaces_the_previous_output_and_leaves_no_hidden_directory(in_tmp: Path, capsys) -> None:
    path = scenario_file(in_tmp, BASE)
    for seed in ("1", "2"):
        assert main(["run", str(path), "--quiet", "--out", "run", "--seed", seed]) in (0, 1)
    assert sorted(p.name for p in (in_tmp / "work").iterdir()) == ["run"]
    assert '"seed": 2' in (in_tmp / "work" / "run" / "metrics.json").read_text()
    assert not (in_tmp / "work" / "run" / STAGING_MARKER).exists()


def test_a_staging_directory_of_a_killed_run_is_removed_by_the_next_run(tmp_path: Path) -> None:
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    host = socket.gethostname()
    stale = tmp_path / ".run.abc12345"
    stale.mkdir()
    (stale / STAGING_MARKER).write_text(f"{host} {dead.pid}\n")
    (stale / "trajectory.csv").write_text("half")
    live = tmp_path / ".run.live0000"
    live.mkdir()
    (live / STAGING_MARKER).write_text(f"{host} {os.getpid()}\n")
    foreign = tmp_path / ".run.nomarker"
    foreign.mkdir()
    other_host = tmp_path / ".run.otherhost"
    other_host.mkdir()
    (other_host / STAGING_MARKER).write_text(f"not-{host} {dead.pid}\n")
    write_atomically(tmp_path / "run", lambda staging: (staging / "metrics.json").write_text("{}"))
    assert sorted(p.name for p in tmp_path.iterdir()) == [".run.live0000", ".run.nomarker", ".run.otherhost", "run"]


def test_write_atomically_refuses_to_replace_what_is_not_its_own(tmp_path: Path) -> None:
    home = tmp_path / "home"
    home.mkdir()
    (home / "notes.txt").write_text("precious")
    with pytest.raises(OutputDirectoryError, match="not a previous run's output"):
        write_atomically(home, lambda staging: None, marker="sweep.csv")
    assert (home / "notes.txt").read_text() == "precious"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["home"]


def test_sigterm_during_a_run_leaves_nothing_and_exits_130(in_tmp: Path) -> None:
    path = scenario_file(in_tmp, {**changed("duration_s", 3000.0), "log_period_s": 10.0})
    work = in_tmp / "work"
    process = subprocess.Popen(
        [sys.executable, "-m", "sitl.cli", "run", str(path), "--quiet", "--out", "out/run"],
        cwd=work, stderr=subprocess.PIPE, text=True, env={**os.environ, "MPLBACKEND": "Agg"},
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while not any(p.name.startswith(".run.") for p in (work / "out").glob(".*")):
            assert time.monotonic() < deadline and process.poll() is None, "the run never started"
            time.sleep(0.05)
        process.send_signal(signal.SIGTERM)
        _, err = process.communicate(timeout=60)
    finally:
        process.kill()
    assert process.returncode == 130, err
    assert "interrupted; nothing written to out/run" in err
    assert tree(work) == []


# ---------------------------------------------------------------- sweep and fleet


@pytest.mark.parametrize(
    "options, expected",
    [
        (["--agents", "0"], "--agents must be at least 1, got 0"),
        (["--agents", "3", "10000000"], "10,000,000 agents"),
        (["--agents", "3", "--runs", "0"], "--runs must be at least 1"),
        (["--agents", "3", "--runs", str(10**12)], "the sweep runs"),
        (["--agents", "3", "--out", "afile/sub"], "afile is a file"),
    ],
)
def test_a_bad_sweep_exits_2_before_the_first_run(in_tmp: Path, capsys, monkeypatch, options, expected) -> None:
    (in_tmp / "work" / "afile").write_text("")
    monkeypatch.setattr(sitl.experiments.sweep, "simulate", lambda *a, **k: pytest.fail("a run started"))
    path = scenario_file(in_tmp, BASE)
    assert_refused(in_tmp, capsys, ["sweep", str(path), "--quiet", *options], expected)


def test_a_sweep_will_not_replace_a_foreign_directory(in_tmp: Path, capsys, monkeypatch) -> None:
    (in_tmp / "work" / "mine").mkdir()
    (in_tmp / "work" / "mine" / "notes.txt").write_text("precious")
    monkeypatch.setattr(sitl.experiments.sweep, "simulate", lambda *a, **k: pytest.fail("a run started"))
    path = scenario_file(in_tmp, BASE)
    assert_refused(in_tmp, capsys, ["sweep", str(path), "--agents", "3", "--out", "mine"], "previous run's output")


@pytest.mark.parametrize(
    "options, expected",
    [(["--agents", "0"], "--agents must be at least 1"), (["--agents", "10000000"], "at most 200,000")],
)
def test_a_bad_fleet_exits_2_before_starting_processes(in_tmp: Path, capsys, options, expected) -> None:
    path = scenario_file(in_tmp, BASE)
    assert_refused(in_tmp, capsys, ["fleet", str(path), "--processes", "--quiet", *options], expected)


# ---------------------------------------------------------------- property tests


def _exact_simple(points: list[tuple[int, int]]) -> bool:
    """Reference: a simple polygon with exact arithmetic, edge pair by edge pair (slow, obvious)."""
    n = len(points)
    p = [(Fraction(x), Fraction(y)) for x, y in points]

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    def on(a, b, q):
        return min(a[0], b[0]) <= q[0] <= max(a[0], b[0]) and min(a[1], b[1]) <= q[1] <= max(a[1], b[1])

    def meet(a, b, c, d):
        d1, d2, d3, d4 = cross(c, d, a), cross(c, d, b), cross(a, b, c), cross(a, b, d)
        if ((d1 > 0) != (d2 > 0)) and d1 and d2 and ((d3 > 0) != (d4 > 0)) and d3 and d4:
            return True
        touching = (d1 == 0 and on(c, d, a)) or (d2 == 0 and on(c, d, b))
        return touching or (d3 == 0 and on(a, b, c)) or (d4 == 0 and on(a, b, d))

    edges = [(p[k], p[(k + 1) % n]) for k in range(n)]
    if any(a == b for a, b in edges):
        return False
    for i in range(n):
        for j in range(i + 1, n):
            (a, b), (c, d) = edges[i], edges[j]
            if j == i + 1 or (i == 0 and j == n - 1):  # adjacent: they may share only their common vertex
                shared, other_i, other_j = (b, a, d) if j == i + 1 else (a, b, c)
                dot = (shared[0] - other_i[0]) * (other_j[0] - shared[0]) + (shared[1] - other_i[1]) * (
                    other_j[1] - shared[1]
                )
                if cross(other_i, shared, other_j) == 0 and dot < 0:  # folds back along itself
                    return False
            elif meet(a, b, c, d):
                return False
    area = sum(p[k][0] * p[(k + 1) % n][1] - p[(k + 1) % n][0] * p[k][1] for k in range(n))
    return area != 0


@settings(max_examples=400, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 4), st.integers(0, 4)), min_size=3, max_size=7))
def test_the_polygon_check_agrees_with_exact_arithmetic(points: list[tuple[int, int]]) -> None:
    assert (polygon_problem(points) is None) == _exact_simple(points), polygon_problem(points)


NUMBERS = st.floats(allow_nan=True, allow_infinity=True) | st.integers(-(2**70), 2**70)
NUMERIC_KEYS = [
    "duration_s", "dt_s", "log_period_s", "seed", "groups.0.count", "groups.0.params.max_speed",
    "groups.0.start.box.max.0", "groups.0.start.box.min.1", "groups.0.start.min_separation_m",
    "world.rooms.0.polygon.1.0", "events.0.t_s", "events.0.agents.0", "groups.0.thrust_fraction",
]  # fmt: skip


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(NUMERIC_KEYS), NUMBERS), min_size=1, max_size=4))
def test_any_numbers_anywhere_give_a_scenario_error_or_a_sized_scenario(changes) -> None:
    data = copy.deepcopy(BASE)
    for key, value in changes:
        data = changed(key, value, data)
    try:
        scenario = validate_scenario(data, "fuzzed.toml")
        size = check_run_size(scenario, "fuzzed.toml")
    except ScenarioError as error:
        assert str(error).startswith("fuzzed.toml")
        return
    assert np.isfinite([size.steps, size.agent_steps, size.trajectory_rows]).all()
    assert size.agents <= MAX_AGENTS


def test_every_metric_kind_says_which_parameters_it_reads() -> None:
    """A kind missing from metric_params.PARAMS would take any parameter unchecked (as `generic` does on purpose)."""
    from sitl.experiments.metric_params import PARAMS
    from sitl.experiments.metrics import METRICS

    assert set(PARAMS) == set(METRICS) - {"generic"}
