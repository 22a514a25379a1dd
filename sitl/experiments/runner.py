"""Run a scenario to completion and write its outputs, all or nothing.

Outputs go to a hidden staging directory beside the output directory, moved into place only when
complete. Every failure (an exception, Ctrl-C, SIGTERM turned into KeyboardInterrupt by `bob-sitl`)
removes the staging directory and any parent directory the run created; a staging directory left by
a killed process (SIGKILL, power cut) is recognised by the marker file inside it (host and pid of its
writer) and removed by the next run into the same place once that process is gone. The output
directory is checked before anything runs: not a file, not under a file, not a foreign non-empty
directory (one without the `marker` file of a previous output), in a directory we can write.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import socket
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np
from tqdm import tqdm

from behaviors.collision_avoidance import collision_layer
from sitl.experiments.metrics import METRICS, step_watch
from sitl.experiments.plots import write_figures
from sitl.experiments.recorder import Frame, Recorder
from sitl.experiments.run_environment import write_environment
from sitl.experiments.scenario import Scenario, scenario_to_toml
from sitl.fleets.budget import check_run_size
from sitl.fleets.fleet import LockstepFleet
from sitl.radio.mesh_security import add_mesh_criteria

T = TypeVar("T")
logger = logging.getLogger(__name__)

STAGING_MARKER = ".bob-sitl-staging"  # in a staging directory while it is being written: "<host> <pid>"


class OutputDirectoryError(FileExistsError):
    """The output directory cannot be used; the message names it and says what to change."""


@dataclass
class RunResult:
    """What a run produced: the fleet at the end, its recording and its metrics."""

    fleet: LockstepFleet
    recorder: Recorder
    metrics: dict


def simulate(scenario: Scenario, progress: bool = False, force: bool = False, vessel_processes: int = 1) -> RunResult:
    """Step a lockstep fleet through the scenario, recording ground truth; no files.

    ScenarioError before anything is allocated when the run exceeds `sitl.fleets.budget`'s limits (unless `force`).
    vessel_processes: processes the buoys' vessel side runs in (physics; the same results, sooner on more cores).
    """
    check_run_size(scenario, f"scenario {scenario.name!r}", force=force)
    fleet = LockstepFleet(scenario, vessel_processes=vessel_processes)
    try:
        for name, problem in hearing_problems(fleet):
            logger.warning("scenario %r, %s: %s (network.broadcast_period_s)", scenario.name, name, problem)
        return _simulated(fleet, progress)
    finally:
        fleet.close()  # after the metrics, which count the vessels' links


def _simulated(fleet: LockstepFleet, progress: bool) -> RunResult:
    scenario = fleet.scenario
    recorder = Recorder(
        scenario.log_period_s, [str(k) for k in _body_names(fleet)], watch=step_watch(scenario.metrics.kind, fleet)
    )
    steps = round(scenario.duration_s / scenario.dt_s)
    bar = tqdm(total=steps, desc=scenario.name, unit="step", disable=not progress, mininterval=0.5)
    for _ in range(steps + 1):
        if recorder.due(fleet.t):
            recorder.record(_frame(fleet))
        recorder.observe_step(fleet.t, fleet.active, fleet.bodies.position)
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
    avoidance = collision_counters(fleet)
    if avoidance:
        metrics["collision_avoidance"] = avoidance
    medium = fleet.medium
    metrics["network"] = medium.counters()  # sent, delivered, dropped, packet_bytes, mesh rejections
    add_mesh_criteria(metrics)  # with intruders on the air: every packet of theirs refused
    return RunResult(fleet, recorder, metrics)


def _behavior_names(fleet: LockstepFleet) -> list[str]:
    """The name of each of `fleet.behaviors`: its group's, or event-K for the K-th set-behavior event's."""
    groups = fleet.group_names
    return [groups[k] if k < len(groups) else f"event-{k - len(groups)}" for k in range(len(fleet.behaviors))]


def hearing_problems(fleet: LockstepFleet) -> list[tuple[str, str]]:
    """(group or event, why) for each collision avoidance layer that the scenario's broadcasts are too slow for."""
    period = fleet.scenario.network.broadcast_period_s
    layers = [(name, collision_layer(b)) for name, b in zip(_behavior_names(fleet), fleet.behaviors, strict=True)]
    problems = [(name, layer.hearing_problem(period)) for name, layer in layers if layer is not None]
    return [(name, problem) for name, problem in problems if problem]


def collision_counters(fleet: LockstepFleet) -> dict[str, dict[str, int]]:
    """Per group (or set-behavior event) with collision avoidance: how many agent-updates it changed the wish
    (`interventions`) of how many (`updates`); {} when no behaviour has it."""
    out = {}
    for name, behavior in zip(_behavior_names(fleet), fleet.behaviors, strict=True):
        layer = collision_layer(behavior)
        if layer is not None:
            out[name] = {"interventions": layer.interventions, "updates": layer.updates}
    return out


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


def run_to_directory(
    scenario: Scenario, out: Path, progress: bool = False, force: bool = False, vessel_processes: int = 1
) -> RunResult:
    """Simulate and write trajectory.csv, metrics.json, figures, scenario.toml and environment.json to `out`.

    Everything is written to a temporary directory beside `out` and moved in
    place only when complete, so a failed run leaves no half-written output.
    ScenarioError (too large, see `sitl.fleets.budget`) or OutputDirectoryError before the run starts.
    """
    check_run_size(scenario, f"scenario {scenario.name!r}", force=force)

    def write(staging: Path) -> RunResult:
        result = simulate(scenario, progress, force=force, vessel_processes=vessel_processes)
        result.recorder.write_csv(staging / "trajectory.csv")
        result.metrics["figures"] = write_figures(result.fleet, result.recorder, result.metrics, staging)
        (staging / "metrics.json").write_text(json.dumps(result.metrics, indent=2) + "\n")
        (staging / "scenario.toml").write_text(scenario_to_toml(scenario))
        write_environment(staging)
        return result

    return write_atomically(out, write)


def check_output_directory(out: Path, marker: str = "metrics.json") -> None:
    """OutputDirectoryError unless `out` can receive outputs: a named directory (not '', '.' or '..') that
    does not exist, is empty, or holds a previous output (its `marker` file); not under a file; in a
    directory this process may write."""
    out = Path(out)
    if out.name in ("", ".", ".."):
        raise OutputDirectoryError(f"{out}: give a new directory to write the outputs to (--out DIR)")
    try:
        if os.path.lexists(out):
            if not out.is_dir():
                raise OutputDirectoryError(f"{out} exists and is not a directory; choose another --out")
            if any(out.iterdir()) and not (out / marker).is_file():
                raise OutputDirectoryError(
                    f"{out} exists, is not empty and is not a previous run's output; choose another --out"
                )
        ancestor = out.parent
        while not os.path.lexists(ancestor) and ancestor != ancestor.parent:
            ancestor = ancestor.parent
        if not ancestor.is_dir():
            raise OutputDirectoryError(f"{out}: {ancestor} is a file, not a directory; choose another --out")
        if not os.access(ancestor, os.W_OK | os.X_OK):
            raise OutputDirectoryError(f"{out}: the directory {ancestor} is not writable; choose another --out")
    except OSError as error:
        if isinstance(error, OutputDirectoryError):
            raise
        raise OutputDirectoryError(f"{out}: cannot be used as an output directory: {error}") from None


def write_atomically(out: Path, write: Callable[[Path], T], marker: str = "metrics.json") -> T:
    """Call `write(staging)` on a fresh directory beside `out`, then move it to `out` (replacing it).

    `out` must pass `check_output_directory(out, marker)` (checked before `write` is called and again
    before replacing). A failure anywhere, KeyboardInterrupt included, leaves neither a half-written
    `out`, nor the staging directory, nor a parent directory created for it.
    """
    out = Path(out)
    check_output_directory(out, marker)
    created = _make_directories(out.parent, out)
    try:
        _remove_stale_staging(out)
        try:
            staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
        except OSError as error:
            raise OutputDirectoryError(f"{out}: cannot create a directory in {out.parent}: {error}") from None
        try:
            (staging / STAGING_MARKER).write_text(f"{socket.gethostname()} {os.getpid()}\n")
            value = write(staging)
            (staging / STAGING_MARKER).unlink()
            _move_into_place(staging, out, marker)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
    except BaseException:
        for directory in reversed(created):
            with contextlib.suppress(OSError):
                directory.rmdir()  # only if still empty
        raise
    return value


def _make_directories(directory: Path, out: Path) -> list[Path]:
    """Create `directory` and its missing parents; the ones created, outermost first."""
    missing: list[Path] = []
    while not os.path.lexists(directory) and directory != directory.parent:
        missing.append(directory)
        directory = directory.parent
    created: list[Path] = []
    for path in reversed(missing):
        try:
            path.mkdir()
        except OSError as error:
            for done in reversed(created):
                with contextlib.suppress(OSError):
                    done.rmdir()
            raise OutputDirectoryError(f"{out}: cannot create the directory {path}: {error}") from None
        created.append(path)
    return created


def _move_into_place(staging: Path, out: Path, marker: str) -> None:
    """Rename `staging` to `out`; a previous output there is renamed aside first and removed after, so a
    failure between the two renames puts it back."""
    if not os.path.lexists(out):
        staging.rename(out)
        return
    check_output_directory(out, marker)  # it may have appeared while the run was going
    old = staging.with_name(staging.name + ".old")
    out.rename(old)
    try:
        staging.rename(out)
    except BaseException:
        old.rename(out)
        raise
    if old.is_symlink():
        old.unlink()
    else:
        shutil.rmtree(old, ignore_errors=True)


def _remove_stale_staging(out: Path) -> None:
    """Remove staging directories for `out` left by processes of this host that are gone (killed)."""
    host = socket.gethostname()
    prefix = f".{out.name}."
    try:
        entries = [e for e in os.scandir(out.parent) if e.name.startswith(prefix)]
    except OSError:
        return
    for entry in entries:
        if entry.is_symlink() or not entry.is_dir():
            continue
        try:
            writer_host, pid = (Path(entry.path) / STAGING_MARKER).read_text().split()
            if writer_host != host or _alive(int(pid)):
                continue
        except (OSError, ValueError):
            continue  # not ours, or not readable: leave it
        shutil.rmtree(entry.path, ignore_errors=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True
