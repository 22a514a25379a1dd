"""The examples run as documented."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

from sitl.experiments.runner import run_to_directory

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def load_example(name: str):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_custom_scenario_builds_and_runs(tmp_path: Path) -> None:
    example = load_example("custom_scenario")
    scenario = example.scenario.with_overrides(duration_s=5.0)
    assert [g.behavior for g in scenario.groups] == ["perimeter-defense", "heading-consensus"]
    run_to_directory(scenario, tmp_path / "out")
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["agents"] == 10
    rows = (tmp_path / "out" / "trajectory.csv").read_text().splitlines()
    behaviors = {line.split(",")[3] for line in rows[1:]}
    assert behaviors == {"avoid+perimeter-defense", "heading-consensus"}
