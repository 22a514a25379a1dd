"""Run a scenario to completion and write its outputs, all or nothing."""

from __future__ import annotations

import json
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np
from tqdm import tqdm

from sitl.fleet import LockstepFleet
from sitl.metrics import METRICS
from sitl.plots import write_figures
from sitl.recorder import Frame, Recorder
from sitl.scenario import Scenario, scenario_to_toml

T = TypeVar("T")


@dataclass
class RunResult:
    """What a run produced: the fleet at the end, its recording and its metrics."""

    fleet: LockstepFleet
    recorder: Recorder
    metrics: dict


def simulate(scenario: Scenario, progress: bool = False) -> RunResult:
    """Step a lockstep fleet through the scenario, recording ground truth; no files."""
    fleet = LockstepFleet(scenario)
    recorder = Recorder(scenario.log_period_s, [str(k) for k in _body_names(fleet)])
    steps = round(scenario.duration_s / scenario.dt_s)
    bar = tqdm(total=steps, desc=scenario.name, unit="step", disable=not progress, mininterval=0.5)
    for _ in range(steps + 1):
        if recorder.due(fleet.t):
            recorder.record(_frame(fleet))
        if fleet.step_index == steps:
            break
        fleet.step()
        bar.update(1)
    bar.close()
    metrics = METRICS[scenario.metrics.kind](fleet, recorder, dict(scenario.metrics.params))
    metrics = {"scenario": scenario.name, "seed": scenario.seed, "duration_s": scenario.duration_s, **metrics}
    if scenario.fidelity == "physics":
        metrics["estimation"] = estimation_errors(recorder)
        metrics["vehicle_link"] = fleet.bodies.link_counters()
    medium = fleet.medium
    metrics["network"] = medium.counters()  # sent, delivered, dropped, packet_bytes, mesh rejections
    return RunResult(fleet, recorder, metrics)


def estimation_errors(recorder: Recorder) -> dict:
    """How far what the agents believed was from the truth, over every logged frame, per body kind.

    position_rms_m, heading_rms_deg, and position_max_m.
    """
    out: dict = {}
    for kind in sorted(set(recorder.body_names)):
        errors, heading_errors = [], []
        for f in recorder.frames:
            rows = [k for k, a in enumerate(f.agents.tolist()) if recorder.body_names[a] == kind]
            if not rows or f.estimate is None:
                continue
            est = f.estimate[rows]
            errors.append(np.hypot(*(est[:, :2] - f.position[rows]).T))
            heading_errors.append(np.mod(est[:, 2] - f.heading[rows] + np.pi, 2 * np.pi) - np.pi)
        if errors:
            e, h = np.concatenate(errors), np.concatenate(heading_errors)
            out[kind] = {
                "position_rms_m": float(np.sqrt(np.mean(e**2))),
                "position_max_m": float(e.max()),
                "heading_rms_deg": float(np.degrees(np.sqrt(np.mean(h**2)))),
            }
    return out


def _body_names(fleet: LockstepFleet) -> list[str]:
    names = {g.name: g.body for g in fleet.scenario.groups}
    return [names[fleet.group_names[k]] for k in fleet.group_of]


def _frame(fleet: LockstepFleet) -> Frame:
    active = fleet.active.nonzero()[0]
    bodies = fleet.bodies
    wind, current = bodies.environment_at()
    believed_position, believed_heading, _ = bodies.believed()
    return Frame(
        t=round(fleet.t, 9),
        agents=active,
        position=bodies.position[active].copy(),
        heading=bodies.heading[active].copy(),
        velocity=bodies.velocity[active].copy(),
        behavior=fleet.behavior_names(),
        light_seen=fleet.light_seen(),
        wind=wind[active].copy(),
        current=current[active].copy(),
        estimate=np.column_stack((believed_position[active], believed_heading[active])),
    )


def run_to_directory(scenario: Scenario, out: Path, progress: bool = False) -> RunResult:
    """Simulate and write trajectory.csv, metrics.json, figures and scenario.toml to `out`.

    Everything is written to a temporary directory beside `out` and moved in
    place only when complete, so a failed run leaves no half-written output.
    """
    out = Path(out)
    if out.exists() and any(out.iterdir()) and not (out / "metrics.json").exists():
        raise FileExistsError(f"{out} exists, is not empty and is not a previous run's output; choose another --out")

    def write(staging: Path) -> RunResult:
        result = simulate(scenario, progress)
        result.recorder.write_csv(staging / "trajectory.csv")
        result.metrics["figures"] = write_figures(result.fleet, result.recorder, result.metrics, staging)
        (staging / "metrics.json").write_text(json.dumps(result.metrics, indent=2) + "\n")
        (staging / "scenario.toml").write_text(scenario_to_toml(scenario))
        return result

    return write_atomically(out, write)


def write_atomically(out: Path, write: Callable[[Path], T]) -> T:
    """Call `write(staging)` on a fresh directory beside `out`, then move it to `out` (replacing it).

    A failure anywhere leaves neither a half-written `out` nor the staging directory.
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        value = write(staging)
        if out.exists():
            shutil.rmtree(out)
        staging.rename(out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return value
