"""Sweeps: one scenario over swarm sizes and seeds, as the paper's scalability figures need.

Every run's scalar metrics go to sweep.csv (one row per run); the chosen
metrics are plotted against the number of agents as mean and standard
deviation over the seeds (sweep.png). Runs write no per-run outputs.

Before the first run, every swarm size is validated, the whole sweep is
checked against `sitl.budget`'s limits and the output directory is checked,
so that a sweep does not fail after hours of running.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from tqdm import tqdm

from sitl.budget import check_sweep_size
from sitl.runner import check_output_directory, simulate, write_atomically
from sitl.scenario import Scenario, ScenarioError


def run_sweep(
    scenario: Scenario,
    agents: list[int],
    seeds: Sequence[int],
    out: Path,
    plot_keys: list[str],
    progress: bool = True,
    force: bool = False,
) -> list[dict]:
    """Run every (agents, seed) pair; write sweep.csv and sweep.png to `out` (all or nothing).

    ScenarioError (a bad size, no seeds, too large) or OutputDirectoryError before the first run.
    """
    if not agents or not seeds:
        raise ScenarioError(f"sweep of {scenario.name!r}: give at least one swarm size and one run")
    sized = {n: scenario.with_overrides(agents=n) for n in dict.fromkeys(agents)}
    check_sweep_size([sized[n] for n in agents], len(seeds), f"sweep of {scenario.name!r}", force=force)
    check_output_directory(out, "sweep.csv")
    rows: list[dict] = []
    pairs = [(n, s) for n in agents for s in seeds]
    for n, seed in tqdm(pairs, desc=f"sweep {scenario.name}", disable=not progress):
        metrics = simulate(sized[n].with_overrides(seed=seed), force=force).metrics
        row = {"agents": n, "seed": seed, "passed": metrics["passed"]}
        row.update({k: v for k, v in metrics.items() if isinstance(v, int | float) and not isinstance(v, bool)})
        rows.append(row)

    def write(staging: Path) -> None:
        columns = sorted({k for r in rows for k in r}, key=lambda k: (k not in ("agents", "seed", "passed"), k))
        with open(staging / "sweep.csv", "w", newline="", encoding="utf-8") as handle:
            writer = csv.DictWriter(handle, fieldnames=columns)
            writer.writeheader()
            writer.writerows(rows)
        _plot(rows, agents, plot_keys, scenario.name, staging / "sweep.png")

    write_atomically(out, write, marker="sweep.csv")
    return rows


def _plot(rows: list[dict], agents: list[int], keys: list[str], name: str, path: Path) -> None:
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for key in keys:
        means, stds = [], []
        for n in agents:
            values = [r[key] for r in rows if r["agents"] == n and r.get(key) is not None]
            means.append(np.mean(values) if values else np.nan)
            stds.append(np.std(values) if values else np.nan)
        ax.errorbar(agents, means, yerr=stds, marker="o", capsize=3, label=key)
    ax.set_xlabel("number of agents")
    ax.set_title(f"{name}: mean and std over seeds")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
