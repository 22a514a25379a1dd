"""sitl/experiments/runner.py and sitl/cli.py: outputs written all or nothing, determinism, and the bob-sitl command."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

import sitl.experiments.runner
from sitl.cli import main
from sitl.experiments.run_environment import environment
from sitl.experiments.scenario import Scenario, load_scenario, packaged_scenarios, validate_scenario

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def short_consensus(duration_s: float = 2.0, remove: bool = False, **changes: object) -> Scenario:
    """Heading consensus (10 eBots turning in place, all in range) for `duration_s`, logged every 0.5 s;
    with `remove`, agents 2, 5 and 7 are removed at 1.0 s."""
    data = load_scenario("heading-consensus").model_dump(exclude_none=True)
    data.update(
        duration_s=duration_s,
        log_period_s=0.5,
        events=[{"t_s": 1.0, "action": "remove", "agents": [2, 5, 7]}] if remove else [],
    )
    data.update(changes)
    return validate_scenario(data, "short consensus")


def read_rows(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        return list(reader.fieldnames or []), list(reader)


# ---------------------------------------------------------------- run_to_directory


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, sitl.experiments.runner.RunResult, Scenario]:
    out = tmp_path_factory.mktemp("runs") / "consensus"
    scenario = short_consensus()
    return out, sitl.experiments.runner.run_to_directory(scenario, out), scenario


def test_outputs_written(finished_run) -> None:
    out, _, _ = finished_run
    names = sorted(p.name for p in out.iterdir())
    assert names == [
        "environment.json", "headings.png", "metrics.json", "scenario.toml", "trajectories.png", "trajectory.csv"
    ]  # fmt: skip
    assert json.loads((out / "environment.json").read_text()) == environment()
    # No staging directory left beside it.
    assert sorted(p.name for p in out.parent.iterdir()) == ["consensus"]


def test_trajectory_csv_rows(finished_run) -> None:
    out, result, _ = finished_run
    header, rows = read_rows(out / "trajectory.csv")
    assert header[:2] == ["t", "agent"]
    assert {"t", "agent", "x", "y", "heading", "vx", "vy"} <= set(header)
    # Frames every 0.5 s over 2 s (0, 0.5, 1.0, 1.5, 2.0) of 10 agents: 50 rows.
    assert len(rows) == 50
    by_t: dict[float, list[int]] = {}
    for row in rows:
        by_t.setdefault(float(row["t"]), []).append(int(row["agent"]))
    assert by_t == {t: list(range(10)) for t in (0.0, 0.5, 1.0, 1.5, 2.0)}
    assert {row["body"] for row in rows} == {"ebot"}
    assert {row["behavior"] for row in rows} == {"heading-consensus"}
    # The last frame is the fleet's final state (written to 4 and 5 decimals).
    final = [row for row in rows if float(row["t"]) == 2.0]
    bodies = result.fleet.bodies
    np.testing.assert_allclose([[float(r["x"]), float(r["y"])] for r in final], bodies.position, atol=6e-5)
    np.testing.assert_allclose([float(r["heading"]) for r in final], bodies.heading, atol=6e-6)
    # Turning in place: the headings changed, the positions did not.
    first = [row for row in rows if float(row["t"]) == 0.0]
    assert [r["x"] for r in first] == [r["x"] for r in final]
    assert max(abs(float(a["heading"]) - float(b["heading"])) for a, b in zip(first, final, strict=True)) > 0.05


def test_metrics_json(finished_run) -> None:
    out, _, _ = finished_run
    metrics = json.loads((out / "metrics.json").read_text())
    assert isinstance(metrics["criteria"], dict) and metrics["criteria"]
    assert metrics["passed"] is all(metrics["criteria"].values())
    assert (metrics["scenario"], metrics["seed"], metrics["duration_s"]) == ("heading-consensus", 7, 2.0)
    assert metrics["figures"] == ["trajectories.png", "headings.png"]
    # Broadcast every 0.1 s at steps t = 0.0 ... 1.9: 20 rounds of 10 senders, all in range of each other
    # (3 m box, 50 m radio, turning in place): sent 20 * 10 = 200, delivered 20 * 10 * 9 = 1800.
    network = {k: metrics["network"][k] for k in ("sent", "delivered", "dropped")}  # + packet_bytes, mesh
    assert network == {"sent": 200, "delivered": 1800, "dropped": 0}


def test_rows_and_messages_after_removal(tmp_path: Path) -> None:
    out = tmp_path / "removal"
    sitl.experiments.runner.run_to_directory(short_consensus(remove=True, metrics={"kind": "generic"}), out)
    _, rows = read_rows(out / "trajectory.csv")
    # Frames at 0, 0.5 and 1.0 s hold 10 agents (the frame at 1.0 s is taken before that step's removal),
    # those at 1.5 and 2.0 s the 7 left: 3 * 10 + 2 * 7 = 44 rows.
    assert len(rows) == 44
    by_t: dict[float, list[int]] = {}
    for row in rows:
        by_t.setdefault(float(row["t"]), []).append(int(row["agent"]))
    assert by_t[1.0] == list(range(10))
    assert by_t[1.5] == by_t[2.0] == [0, 1, 3, 4, 6, 8, 9]
    metrics = json.loads((out / "metrics.json").read_text())
    # 10 rounds (t = 0.0 ... 0.9) of 10 senders, then 10 rounds (1.0 ... 1.9) of 7:
    # sent 100 + 70 = 170, delivered 10 * 90 + 10 * 42 = 1320.
    network = {k: metrics["network"][k] for k in ("sent", "delivered", "dropped")}  # + packet_bytes, mesh
    assert network == {"sent": 170, "delivered": 1320, "dropped": 0}
    assert metrics["figures"] == ["trajectories.png"]
    assert metrics["passed"] is True and metrics["criteria"] == {}


def test_heading_consensus_run_with_removal_writes_figures(tmp_path: Path) -> None:
    out = tmp_path / "removal"
    sitl.experiments.runner.run_to_directory(short_consensus(remove=True), out)
    assert (out / "headings.png").read_bytes()[:8] == PNG_MAGIC


def test_figures_are_png(finished_run) -> None:
    out, _, _ = finished_run
    for name in ("trajectories.png", "headings.png"):
        data = (out / name).read_bytes()
        assert data[:8] == PNG_MAGIC
        assert len(data) > 1000


def test_scenario_toml_is_the_resolved_scenario(finished_run) -> None:
    out, _, scenario = finished_run
    written = validate_scenario(tomllib.loads((out / "scenario.toml").read_text()), "written")
    assert written == scenario


def test_heading_consensus_metrics_survive_leader_removal() -> None:
    data = load_scenario("heading-consensus").model_dump(exclude_none=True)
    data["duration_s"] = 2.0
    data["events"][0]["t_s"] = 0.5  # agent 0 becomes the leader ...
    data["events"].append({"t_s": 1.0, "action": "remove", "agents": [0]})  # ... and is then removed
    result = sitl.experiments.runner.simulate(validate_scenario(data, "leader removed"))
    assert isinstance(result.metrics["passed"], bool)


def test_failed_run_leaves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(*args, **kwargs):
        raise RuntimeError("plotting failed")

    monkeypatch.setattr(sitl.experiments.runner, "write_figures", broken)
    out = tmp_path / "run"
    with pytest.raises(RuntimeError, match="plotting failed"):
        sitl.experiments.runner.run_to_directory(short_consensus(duration_s=0.5), out)
    assert list(tmp_path.iterdir()) == []


def test_failed_rerun_keeps_previous_output(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "run"
    sitl.experiments.runner.run_to_directory(short_consensus(duration_s=0.5), out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def broken(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(sitl.experiments.runner, "write_figures", broken)
    with pytest.raises(RuntimeError):
        sitl.experiments.runner.run_to_directory(short_consensus(duration_s=1.0), out)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert [p.name for p in tmp_path.iterdir()] == ["run"]


def test_refuses_foreign_non_empty_directory(tmp_path: Path) -> None:
    out = tmp_path / "mine"
    out.mkdir()
    (out / "thesis.tex").write_text("precious")
    with pytest.raises(FileExistsError):
        sitl.experiments.runner.run_to_directory(short_consensus(duration_s=0.5), out)
    assert [p.name for p in out.iterdir()] == ["thesis.tex"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine"]


def test_same_seed_same_bytes_other_seed_differs(tmp_path: Path) -> None:
    scenario = short_consensus(duration_s=1.0)
    sitl.experiments.runner.run_to_directory(scenario, tmp_path / "a")
    sitl.experiments.runner.run_to_directory(scenario, tmp_path / "b")
    sitl.experiments.runner.run_to_directory(scenario.with_overrides(seed=8), tmp_path / "c")
    a, b, c = ((tmp_path / d / "trajectory.csv").read_bytes() for d in "abc")
    assert a == b
    assert a != c
    assert (tmp_path / "a" / "metrics.json").read_bytes() == (tmp_path / "b" / "metrics.json").read_bytes()


# ---------------------------------------------------------------- bob-sitl


def test_cli_list(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    names = [line.split()[0] for line in lines]
    assert names == list(packaged_scenarios())
    assert {"heading-consensus", "perimeter-defense", "search-exploration"} <= set(names)


def test_cli_bad_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "bad"\nduration_s = "long"\n')
    out = tmp_path / "out"
    assert main(["run", str(bad), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "duration_s" in err
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.toml"]


def test_cli_unknown_scenario(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["run", "no-such-scenario", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "no-such-scenario" in err and "heading-consensus" in err
    assert list(tmp_path.iterdir()) == []


def test_cli_bad_override(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert main(["run", "heading-consensus", "--duration", "-1", "--out", str(out), "--quiet"]) == 2
    assert "duration_s" in capsys.readouterr().err
    assert not out.exists()


def test_cli_refuses_foreign_directory(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "notes.txt").write_text("keep")
    assert main(["run", "heading-consensus", "--duration", "0.5", "--out", str(tmp_path), "--quiet"]) == 2
    assert "--out" in capsys.readouterr().err
    assert [p.name for p in tmp_path.iterdir()] == ["notes.txt"]


def test_cli_unknown_behaviour_exits_2(tmp_path: Path) -> None:
    text = (
        'name = "x"\nduration_s = 1.0\n[[groups]]\nname = "g"\ncount = 2\nbody = "buoy"\nbehavior = "warp-drive"\n'
        "start = { box = { min = [0.0, 0.0], max = [1.0, 1.0] } }\n"
    )
    bad = tmp_path / "warp.toml"
    bad.write_text(text)
    assert main(["run", str(bad), "--out", str(tmp_path / "out"), "--quiet"]) == 2


def test_cli_run_writes_outputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "hc"
    status = main(["run", "heading-consensus", "--duration", "3", "--out", str(out), "--quiet"])
    captured = capsys.readouterr()
    metrics = json.loads((out / "metrics.json").read_text())
    assert status == (0 if metrics["passed"] else 1)
    assert metrics["duration_s"] == 3.0
    # stdout: the JSON summary (scalars and criteria, not the time series).
    summary = json.loads(captured.out)
    assert summary["passed"] == metrics["passed"] and summary["criteria"] == metrics["criteria"]
    assert "heading_spread_deg" not in summary and "network" not in summary
    assert str(out) in captured.err
    # log_period 0.1 s over 3 s: 31 frames of 10 agents.
    _, rows = read_rows(out / "trajectory.csv")
    assert len(rows) == 310
    assert (out / "trajectories.png").read_bytes()[:8] == PNG_MAGIC


def test_cli_agents_seed_and_default_out(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)
    status = main(["run", "heading-consensus", "--agents", "3", "--seed", "5", "--duration", "0.5", "--quiet"])
    capsys.readouterr()
    out = tmp_path / "runs" / "heading-consensus"
    assert status in (0, 1)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["seed"] == 5
    _, rows = read_rows(out / "trajectory.csv")
    # 0.5 s logged every 0.1 s: 6 frames of 3 agents.
    assert len(rows) == 18
    assert {int(r["agent"]) for r in rows} == {0, 1, 2}
    written = tomllib.loads((out / "scenario.toml").read_text())
    assert written["seed"] == 5 and written["groups"][0]["count"] == 3


def bob_sitl_command() -> list[str]:
    script = Path(sys.executable).parent / "bob-sitl"
    if script.exists():
        return [str(script)]
    found = shutil.which("bob-sitl")
    return [found] if found else [sys.executable, "-m", "sitl.cli"]


def test_console_script_list(tmp_path: Path) -> None:
    env = {**os.environ, "MPLBACKEND": "Agg"}
    done = subprocess.run(
        [*bob_sitl_command(), "list"], capture_output=True, text=True, timeout=60, cwd=tmp_path, env=env
    )
    assert done.returncode == 0, done.stderr
    names = [line.split()[0] for line in done.stdout.splitlines()]
    assert names == list(packaged_scenarios())
    assert list(tmp_path.iterdir()) == []


def test_fleet_vessel_niceness_out_of_range_is_refused_before_anything_runs(capsys, tmp_path: Path) -> None:
    out = tmp_path / "never"
    assert main(["fleet", "aggregation", "--processes", "--vessel-nice", "20", "--out", str(out)]) == 2
    assert "vessel_nice must be 0..19, got 20" in capsys.readouterr().err
    assert not out.exists()
