"""bob-sitl sweep: runs over sizes and seeds, one CSV row each, a figure."""

from __future__ import annotations

import csv
from pathlib import Path

from sitl.cli import main
from sitl.experiments.scenario import load_scenario
from sitl.experiments.sweep import run_sweep


def test_sweep_writes_one_row_per_run(tmp_path: Path) -> None:
    scenario = load_scenario("heading-consensus").with_overrides(duration_s=12.0)
    rows = run_sweep(scenario, [3, 5], [1, 2], tmp_path / "out", ["consensus_time_s"], progress=False)
    assert [(r["agents"], r["seed"]) for r in rows] == [(3, 1), (3, 2), (5, 1), (5, 2)]
    with open(tmp_path / "out" / "sweep.csv", encoding="utf-8") as handle:
        table = list(csv.DictReader(handle))
    assert [int(r["agents"]) for r in table] == [3, 3, 5, 5]
    assert all(float(r["spread_at_consensus_deadline_deg"]) <= 5.0 for r in table)
    assert (tmp_path / "out" / "sweep.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_sweep_command_rejects_an_unknown_scenario(tmp_path: Path, capsys) -> None:
    assert main(["sweep", "no-such-scenario", "--agents", "2", "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "no-such-scenario" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
