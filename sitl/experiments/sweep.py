"""Sweeps: one scenario over swarm sizes, any scenario parameters and seeds, as the paper's scalability figures need.

The runs are the product of the swarm sizes, the values of every swept parameter (`--param PATH=V1,V2`,
a dotted path into the scenario: `network.range_m`, `groups.0.params.p0`, `environment.wind.speed_mps`)
and the seeds, in that order. Every run's scalar metrics (nested ones with dotted names, criteria as
`criteria.NAME`) go to sweep.csv, one row per run in that fixed order whoever ran them; the chosen
metrics are plotted against the swarm size or a swept parameter (`x`) as mean and standard deviation
over the seeds (sweep.png). Runs write no per-run outputs.

Where the runs go is `sitl.experiments.distributed`'s job: in process, on a local Dask cluster or an existing one.
Each finished run's row is appended at once to a partial file beside the output directory
(`.NAME.partial.jsonl`, one JSON line per run, keyed by a digest of the run's resolved scenario), so an
interrupted sweep keeps what finished and `resume` skips it; the outputs are written all or nothing
(`sitl.experiments.runner.write_atomically`) and the partial file removed only then.

Before the first run, every swarm size and every parameter value is validated (the scenario file's
errors, naming the option and the key), the whole sweep is checked against `sitl.fleets.budget`'s limits and
the output directory is checked, so that a sweep does not fail after hours of running.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import itertools
import json
import math
import os
import re
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from sitl.experiments.distributed import check_execution, run_tasks
from sitl.experiments.run_environment import differences, environment, write_environment
from sitl.experiments.runner import _make_directories, check_output_directory, simulate, write_atomically
from sitl.experiments.scenario import Scenario, ScenarioError, validate_scenario
from sitl.fleets.budget import check_sweep_size

PATH_SYNTAX = re.compile(r"[A-Za-z0-9_-]+(\.[A-Za-z0-9_-]+)*")
RESERVED_PATHS = {"seed": "the seeds are --runs", "name": "the name names the output, not a run"}
LEADING_COLUMNS = ("agents", "seed", "passed")


class PartialSweepError(FileExistsError):
    """Finished rows of an earlier, interrupted sweep are waiting and `resume` was not asked for."""


# ---------------------------------------------------------------- parameter grids


def _split_values(text: str) -> list[str]:
    """'1,2,[3,4]' -> ['1', '2', '[3,4]']: commas inside brackets or quotes do not split."""
    parts, depth, quote, start = [], 0, "", 0
    for k, char in enumerate(text):
        if quote:
            quote = "" if char == quote else quote
        elif char in "\"'":
            quote = char
        elif char in "[{":
            depth += 1
        elif char in "]}":
            depth -= 1
        elif char == "," and depth == 0:
            parts.append(text[start:k])
            start = k + 1
    parts.append(text[start:])
    return [p.strip() for p in parts]


def _parse_value(text: str) -> Any:
    """A TOML value (50, 2.5, true, "mpc", [1, 2]), or the bare text as a string (mpc)."""
    try:
        value = tomllib.loads(f"v = {text}")["v"]
    except (tomllib.TOMLDecodeError, ValueError, RecursionError):
        return text
    if not _plain(value):  # dates and times: not a scenario's kind of value
        return text
    return value


def _plain(value: Any) -> bool:
    if isinstance(value, list):
        return all(_plain(v) for v in value)
    return isinstance(value, bool | int | float | str)


def parse_param(text: str) -> tuple[str, list[Any]]:
    """'PATH=V1,V2,...' -> (PATH, [values]); ScenarioError naming the option when it is not that."""
    path, equals, values = text.partition("=")
    path = path.strip()
    if not equals or not PATH_SYNTAX.fullmatch(path):
        raise ScenarioError(
            f"--param {text!r}: give PATH=V1,V2,... with PATH a dotted path into the scenario "
            "(e.g. network.range_m=100,300 or groups.0.params.p0=5,50)"
        )
    if path in RESERVED_PATHS:
        raise ScenarioError(f"--param {text!r}: {path!r} cannot be swept ({RESERVED_PATHS[path]})")
    items = _split_values(values)
    if any(not v for v in items):
        raise ScenarioError(f"--param {text!r}: an empty value; give PATH=V1,V2,... with no empty item")
    parsed = [_parse_value(v) for v in items]
    if len({json.dumps(v) for v in parsed}) != len(parsed):
        raise ScenarioError(f"--param {text!r}: a value is given twice")
    return path, parsed


def apply_param(data: dict[str, Any], path: str, value: Any) -> None:
    """Set `value` at dotted `path` in scenario data (a model_dump), in place.

    Tables on the way that are absent or null are created (e.g. network.radio.ple); list items are
    addressed by index (groups.0). ScenarioError when the path runs into a number, a string or past a
    list's end. Whether the key exists and the value fits is the scenario validation's to say.
    """
    keys = path.split(".")
    node: Any = data
    for depth, key in enumerate(keys):
        where = ".".join(keys[: depth + 1])
        last = depth == len(keys) - 1
        if isinstance(node, dict):
            if last:
                node[key] = value
            else:
                if node.get(key) is None:
                    node[key] = {}
                node = node[key]
        elif isinstance(node, list):
            if not key.isdigit() or int(key) >= len(node):
                raise ScenarioError(
                    f"--param {path}: {'.'.join(keys[:depth]) or 'the scenario'} is a list of {len(node)} item(s); "
                    f"{key!r} is not an index of it (0 to {len(node) - 1})"
                )
            if last:
                node[int(key)] = value
            else:
                node = node[int(key)]
        else:
            parent = ".".join(keys[:depth])
            raise ScenarioError(f"--param {path}: {parent} is {_shown(node)}, not a table; {where} does not exist")


def _shown(value: Any) -> str:
    return f"the {type(value).__name__} {value!r}"[:80]


def with_params(scenario: Scenario, assignments: Sequence[tuple[str, Any]], source: str) -> Scenario:
    """`scenario` with each (path, value) set, validated as a scenario file is (ScenarioError names them)."""
    if not assignments:
        return scenario
    data = scenario.model_dump()
    for path, value in assignments:
        apply_param(data, path, value)
    given = ", ".join(f"{p}={json.dumps(v)}" for p, v in assignments)
    return validate_scenario(data, f"{source} with --param {given}")


# ---------------------------------------------------------------- the runs of a sweep


@dataclass(frozen=True)
class SweepRun:
    """One run: the columns that identify it in the table (agents, swept values, seed) and its scenario."""

    columns: dict[str, Any]
    scenario: Scenario


def sweep_points(
    scenario: Scenario,
    agents: Sequence[int] | None,
    params: Sequence[tuple[str, list[Any]]] = (),
    source: str = "",
) -> list[SweepRun]:
    """One run per (size, parameter values), seeds not yet set, in the fixed order: sizes x values.
    Every scenario is built and validated here (ScenarioError naming the option and key)."""
    source = source or f"sweep of {scenario.name!r}"
    paths = [p for p, _ in params]
    if len(set(paths)) != len(paths):
        raise ScenarioError(f"{source}: --param {sorted(p for p in paths if paths.count(p) > 1)[0]} is given twice")
    for path, values in params:  # each value alone first, so that an error names the one at fault
        for value in values:
            with_params(scenario, [(path, value)], source)
    points = []
    for n in [None] if agents is None else list(agents):
        for combo in itertools.product(*(values for _, values in params)):
            assignments = list(zip(paths, combo, strict=True))
            point = with_params(scenario, assignments, source)
            if n is not None:
                point = point.with_overrides(agents=n)
            points.append(SweepRun({"agents": point.n_agents, **dict(assignments)}, point))
    return points


def with_seeds(points: Sequence[SweepRun], seeds: Sequence[int]) -> list[SweepRun]:
    """Every point at every seed, seeds innermost: the sweep's runs in their fixed order."""
    return [
        SweepRun({**p.columns, "seed": int(seed)}, p.scenario.with_overrides(seed=int(seed)))
        for p in points
        for seed in seeds
    ]


def metrics_row(metrics: dict[str, Any]) -> dict[str, Any]:
    """The scalar figures of a run's metrics as one flat row: nested tables as dotted keys (criteria.NAME,
    network.sent), time series and lists left out; numpy scalars as Python's (exact through JSON)."""
    row: dict[str, Any] = {}
    stack: list[tuple[str, Any]] = [("", metrics)]
    while stack:
        prefix, table = stack.pop()
        for key, value in table.items():
            name = f"{prefix}{key}"
            if isinstance(value, dict):
                if "t_s" not in value:  # a time series {t_s: [...], value: [...]} is not a figure
                    stack.append((f"{name}.", value))
            elif isinstance(value, bool | np.bool_):
                row[name] = bool(value)
            elif isinstance(value, int | np.integer):
                row[name] = int(value)
            elif isinstance(value, float | np.floating):
                row[name] = float(value)
            elif isinstance(value, str):
                row[name] = value
    return row


def run_point(task: tuple[Scenario, bool]) -> dict[str, Any]:
    """Simulate one (scenario, force) and return its metrics row. Runs on a Dask worker or here.

    A run that its seed makes impossible (ScenarioError while setting up, e.g. agents that cannot be
    placed apart in their start box) is a failed run, not the end of the sweep: its row says why
    (`error`) and `passed` is False.
    """
    scenario, force = task
    try:
        metrics = simulate(scenario, force=force).metrics
    except ScenarioError as error:
        return failed_row(error)
    return metrics_row(metrics)


def failed_row(error: Exception) -> dict[str, Any]:
    """The row of a run that could not be simulated: passed False and the reason, on one line."""
    return {"passed": False, "error": " ".join(str(error).split())}


# ---------------------------------------------------------------- the partial file


def partial_path(out: Path) -> Path:
    """Where the finished rows of an unfinished sweep into `out` wait: a hidden file beside it."""
    out = Path(out)
    return out.parent / f".{out.name}.partial.jsonl"


def run_digest(scenario: Scenario, fn: Callable) -> str:
    """What identifies a run's result: the resolved scenario (seed included) and the function that ran it."""
    text = f"{fn.__module__}.{fn.__qualname__}\n{scenario.model_dump_json()}"
    return hashlib.sha256(text.encode()).hexdigest()


def read_partial(path: Path) -> dict[str, dict[str, Any]]:
    """digest -> row of every complete line of a partial file (a line cut short by a kill is ignored)."""
    return _rows_by_run(_partial_entries(path))


def _rows_by_run(entries: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """digest -> row of partial-file entries (a later line for the same run wins)."""
    return {entry["run"]: dict(entry["row"]) for entry in entries}


def _partial_entries(path: Path) -> list[dict[str, Any]]:
    """The complete lines of a partial file: {"run": digest, "environment": {...}, "row": {...}}."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        return []
    except (OSError, UnicodeDecodeError) as error:
        raise PartialSweepError(f"{path}: cannot read the partial sweep ({error}); remove it to start again") from None
    entries = []
    for line in text.splitlines():
        try:
            entry = json.loads(line)
            if isinstance(entry, dict) and isinstance(entry["row"], dict):
                entries.append({**entry, "run": str(entry["run"])})
        except (ValueError, KeyError, TypeError):
            continue
    return entries


def _check_partial_environment(path: Path, entries: list[dict[str, Any]]) -> None:
    """PartialSweepError when runs kept in a partial file were made with other code or libraries than this
    process's (`run_environment.environment`): resuming would mix results of two versions in one table."""
    here = environment()
    for entry in entries:
        there = entry.get("environment")
        differing = differences(here, there) if isinstance(there, dict) else ["no record of the code that made them"]
        if differing:
            raise PartialSweepError(
                f"{path}: its finished runs were made with other code or libraries ({'; '.join(differing)}), so "
                "resuming would mix two versions' results: remove the file to run them all again, or resume with "
                "the code and packages that made them"
            )


class _PartialWriter:
    """Appends one JSON line per finished run, flushed to disk at once; creates the file and its
    directories only at the first row, and removes what it created when no row was ever written."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.handle: Any = None
        self.created: list[Path] = []
        self.existed = os.path.lexists(self.path)

    def append(self, digest: str, row: dict[str, Any]) -> None:
        if self.handle is None:
            self.created = _make_directories(self.path.parent, self.path.parent)
            self.handle = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 (closed in close())
        self.handle.write(json.dumps({"run": digest, "environment": environment(), "row": row}) + "\n")
        self.handle.flush()
        os.fsync(self.handle.fileno())

    def close(self) -> None:
        if self.handle is not None:
            self.handle.close()
        if self.handle is None and not self.existed:
            return
        if not read_partial(self.path) and os.path.lexists(self.path):
            with contextlib.suppress(OSError):
                self.path.unlink()
            for directory in reversed(self.created):
                with contextlib.suppress(OSError):
                    directory.rmdir()


def execute_runs(
    runs: Sequence[SweepRun],
    partial: Path,
    fn: Callable[[tuple[Scenario, bool]], dict[str, Any]] = run_point,
    *,
    force: bool = False,
    resume: bool = False,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
    desc: str = "sweep",
) -> list[dict[str, Any]]:
    """Every run's row (its columns, then `fn`'s row), in the order of `runs`.

    Runs already in the `partial` file (same digest) are taken from it when `resume`; without
    `resume` a partial file is refused (PartialSweepError), so that forgetting the option never
    throws finished runs away. Each new row is appended there as it arrives. An interrupt or a
    failed run leaves the file with what finished; the caller removes it once the outputs are written.
    """
    check_execution(workers, scheduler)
    done: dict[str, dict[str, Any]] = {}
    if os.path.lexists(partial):
        entries = _partial_entries(partial)
        done = _rows_by_run(entries)
        if not resume:
            raise PartialSweepError(
                f"{partial} holds {len(done)} finished run(s) of an interrupted sweep: add --resume to continue it "
                "(those runs are skipped), or remove the file to start again"
            )
        _check_partial_environment(partial, entries)
    digests = [run_digest(r.scenario, fn) for r in runs]
    rows: list[dict[str, Any] | None] = [
        {**done[d], **r.columns} if d in done else None for d, r in zip(digests, runs, strict=True)
    ]
    todo = [i for i, row in enumerate(rows) if row is None]
    writer = _PartialWriter(partial)

    def finished(k: int, row: dict[str, Any]) -> None:
        i = todo[k]
        writer.append(digests[i], row)
        rows[i] = {**row, **runs[i].columns}

    try:
        run_tasks(
            fn,
            [(runs[i].scenario, force) for i in todo],
            finished,
            workers=workers,
            scheduler=scheduler,
            progress=progress,
            desc=desc,
        )
    finally:
        writer.close()
    return [row for row in rows if row is not None]


def finish_partial(partial: Path) -> None:
    """Remove the partial file once the outputs it fed are in place."""
    with contextlib.suppress(FileNotFoundError):
        Path(partial).unlink()


# ---------------------------------------------------------------- the sweep


def run_sweep(
    scenario: Scenario,
    agents: list[int] | None,
    seeds: Sequence[int],
    out: Path,
    plot_keys: list[str],
    progress: bool = True,
    force: bool = False,
    *,
    params: Sequence[tuple[str, list[Any]]] = (),
    x: str | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    resume: bool = False,
) -> list[dict]:
    """Run every (size, parameter values, seed); write sweep.csv and sweep.png to `out` (all or nothing).

    `agents` None: the scenario's own size. `params`: (dotted path, values) pairs. `x`: the plot's
    axis, "agents" or a swept path (default: agents when several sizes are swept, else the first
    swept path). ScenarioError (a bad size, path, value or axis, no seeds, too large),
    OutputDirectoryError, PartialSweepError or ClusterError before the first run.
    """
    source = f"sweep of {scenario.name!r}"
    if (agents is not None and not agents) or not seeds:
        raise ScenarioError(f"sweep of {scenario.name!r}: give at least one swarm size and one run")
    check_execution(workers, scheduler)
    paths = [p for p, _ in params]
    axis = x or ("agents" if (agents and len(set(agents)) > 1) or not paths else paths[0])
    if axis not in ("agents", *paths):
        raise ScenarioError(f"--x {axis}: not swept; give agents or one of the --param paths ({', '.join(paths)})")
    points = sweep_points(scenario, agents, params, source)
    check_sweep_size([p.scenario for p in points], len(seeds), source, force=force)
    check_output_directory(out, "sweep.csv")
    runs = with_seeds(points, seeds)
    partial = partial_path(out)
    rows = execute_runs(
        runs,
        partial,
        force=force,
        resume=resume,
        workers=workers,
        scheduler=scheduler,
        progress=progress,
        desc=f"sweep {scenario.name}",
    )
    swept = ["agents", *paths]

    def write(staging: Path) -> None:
        write_rows_csv(rows, staging / "sweep.csv", ["agents", *paths, "seed", "passed"])
        write_environment(staging)
        _plot(rows, axis, [c for c in swept if c != axis], plot_keys, scenario.name, staging / "sweep.png")

    write_atomically(out, write, marker="sweep.csv")
    finish_partial(partial)
    return rows


def write_rows_csv(rows: list[dict], path: Path, leading: Sequence[str]) -> None:
    """One row per run: the `leading` columns first, then every other key sorted; blank where absent."""
    keys = {k for r in rows for k in r}
    columns = [c for c in leading if c in keys] + sorted(keys - set(leading))
    with open(path, "w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _plot(rows: list[dict], axis: str, others: list[str], keys: list[str], name: str, path: Path) -> None:
    """Each metric in `keys` against `axis`, one line per combination of the other swept columns that
    vary; mean and standard deviation over the seeds. A non-numeric axis is plotted as categories."""
    varying = [c for c in others if len({json.dumps(r.get(c)) for r in rows}) > 1]
    xs = list(dict.fromkeys(json.dumps(r.get(axis)) for r in rows))
    values = [json.loads(v) for v in xs]
    numeric = all(_number(v) for v in values)
    positions = values if numeric else list(range(len(values)))
    fig, ax = plt.subplots(figsize=(7, 4.5))
    groups = list(dict.fromkeys(tuple(json.dumps(r.get(c)) for c in varying) for r in rows))
    for key in keys:
        for group in groups:
            means, stds = [], []
            for x in xs:
                picked = [
                    r[key]
                    for r in rows
                    if json.dumps(r.get(axis)) == x
                    and tuple(json.dumps(r.get(c)) for c in varying) == group
                    and _number(r.get(key))
                ]
                means.append(np.mean(picked) if picked else np.nan)
                stds.append(np.std(picked) if picked else np.nan)
            label = key + (
                " (" + ", ".join(f"{c}={v}" for c, v in zip(varying, group, strict=True)) + ")" if varying else ""
            )
            order = np.argsort(positions, kind="stable") if numeric else np.arange(len(xs))
            ax.errorbar(
                np.asarray(positions, dtype=float)[order],
                np.asarray(means)[order],
                yerr=np.asarray(stds)[order],
                marker="o",
                capsize=3,
                label=label,
            )
    if not numeric:
        ax.set_xticks(positions, [str(v) for v in values])
    ax.set_xlabel("number of agents" if axis == "agents" else axis)
    ax.set_title(f"{name}: mean and std over seeds")
    if keys:
        ax.legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
