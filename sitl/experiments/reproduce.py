"""The paper's experiments over many seeds, and a report of how often each criterion holds.

DESIGN.md lists seven experiments to reproduce; each is one or more packaged scenarios (perimeter
defence at 10, 8, 7 and 5 eBots; the three avoidance outcomes; search in one room and in five).
`reproduce` runs every chosen experiment at every seed through the sweep machinery (in process or on
Dask, a partial file that an interrupted reproduction resumes from) and writes, all or nothing:

- runs.csv: one row per (experiment, seed): every scalar figure and every criterion;
- report.csv: per experiment, each criterion's pass count and rate, and each figure's median,
  quartiles and range over the seeds beside the paper's value;
- report.md: the same as tables, with what ran where and how long it took;
- figures/: each experiment's figures seed by seed against the paper's value, and pass_rates.png.

An experiment reproduces when each of its criteria passes at at least `PASS_RATE` of the seeds (9 of 10).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from sitl.experiments.distributed import check_execution, describe_execution
from sitl.experiments.run_environment import SOURCE_KEY, environment, write_environment
from sitl.experiments.runner import check_output_directory, simulate, write_atomically
from sitl.experiments.scenario import Scenario, ScenarioError, load_scenario
from sitl.experiments.sweep import (
    SweepRun,
    execute_runs,
    failed_row,
    finish_partial,
    metrics_row,
    partial_path,
    write_rows_csv,
)
from sitl.fleets.budget import check_sweep_size
from sitl.radio.channel import TABLE_1

PASS_RATE = 0.9  # a criterion reproduces when it passes at 9 of 10 seeds or better


@dataclass(frozen=True)
class Figure:
    """A scalar figure of a run (a metrics key), and what the paper says of it (`paper` None: no number)."""

    metric: str
    label: str
    paper: float | None = None
    paper_text: str = "-"


@dataclass(frozen=True)
class Experiment:
    """One of DESIGN.md's experiments (its `number`) as a packaged scenario at a swarm size."""

    name: str
    number: int
    scenario: str
    title: str
    figures: tuple[Figure, ...]
    agents: int | None = None
    beyond_paper: bool = False  # run only when named (the paper's variants for other vessels, e.g. motorboats)


def _radio_figures() -> tuple[Figure, ...]:
    return tuple(
        Figure(f"delivery.N{n}_d{d:g}m", f"delivery, {n} buoys {spacing:g} m apart, at {d:g} m", p, f"{100 * p:.0f} %")
        for (n, spacing), table in TABLE_1.items()
        for d, p in table.items()
    )


_PERIMETER = (
    Figure(
        "spread_perimeter_coverage", "walls covered before the removal", None, "covered 'in the best possible manner'"
    ),
    Figure(
        "vacated_recovered_fraction",
        "fraction of the walls only the removed robots covered that the rest cover at the end",
        None,
        "the rest 'try to cover the area removed robots were supposed to cover'",
    ),
    Figure("gap_closed_fraction", "fraction of the removal's largest empty circle closed"),
)
_AVOIDANCE = (
    Figure("arrival_time_s", "mover at its goal, s", None, "reaches its goal"),
    Figure("swarm_max_displacement_m", "largest displacement of the swarm, m"),
    Figure("path_fraction_inside_swarm", "fraction of the path inside the swarm"),
)

_LEADER_FOLLOWER = (
    Figure("leader_path_m", "leader's path, m", 400.0, "about 400 m"),
    Figure("closest_approach_m", "closest two vessels ever came, m", None, "the lattice persists"),
    Figure("final_nn_mean_m", "mean nearest-neighbour distance at the end, m", None, "p0 = 5 m"),
)
_AGGREGATION = (
    Figure("area_before_m2", "hull area before, m2", 125_000.0, "about 125,000 m2"),
    Figure("area_aggregated_m2", "hull area at its tightest, m2", 1_250.0, "1,250 m2"),
    Figure("aggregation_time_s", "time to aggregate, s", 480.0, "just over 8 min"),
    Figure("area_final_m2", "hull area after spreading again, m2", None, "spreads again"),
)

EXPERIMENTS: tuple[Experiment, ...] = (
    Experiment(
        "radio-table", 7, "radio-table", "The radio: delivery against distance and density (Table 1)", _radio_figures()
    ),
    Experiment(
        "heading-consensus",
        1,
        "heading-consensus",
        "Heading consensus of 10 eBots, then a leader",
        (
            Figure("consensus_time_s", "agreed within 5 deg, s", 11.0, "about 11 s"),
            Figure("follow_time_s", "following the leader within 5 deg, s", None, "follows after t = 22 s"),
        ),
    ),
    *(
        Experiment(
            "perimeter-defense" if n == 10 else f"perimeter-defense-{n}",
            2,
            "perimeter-defense",
            f"Perimeter defence of {n} eBots in a 13.5 m x 6.2 m room, robots removed",
            _PERIMETER,
            None if n == 10 else n,
        )
        for n in (10, 8, 7, 5)
    ),
    Experiment(
        "search-exploration",
        3,
        "search-exploration",
        "Search and rendezvous of 10 eBots at a light source",
        (
            Figure("first_detection_s", "first sight of the light, s", None, "speed rises with N (figure)"),
            Figure("all_arrived_s", "all within 1 m of the light, s", None, "speed rises with N (figure)"),
        ),
    ),
    Experiment(
        "five-rooms",
        3,
        "five-rooms",
        "Exploration of five rooms by 14 eBots (physics)",
        (Figure("all_rooms_visited_s", "every room visited, s", None, "all five explored (video)"),),
    ),
    *(
        Experiment(
            f"avoidance-{kind}",
            6,
            f"avoidance-{kind}",
            f"Avoidance: the mover crosses a swarm of 16 buoys ({kind}; physics)",
            _AVOIDANCE,
        )
        for kind in ("yield", "through", "around")
    ),
    Experiment(
        "leader-follower",
        5,
        "leader-follower",
        "Leader-follower of 45 buoys, p0 = 5 m, a weak buoy (physics)",
        _LEADER_FOLLOWER,
    ),
    Experiment(
        "aggregation",
        4,
        "aggregation",
        "Aggregation of 45 buoys in wind, p0 50 m -> 5 m -> 50 m (physics)",
        _AGGREGATION,
    ),
)


_AGGREGATION_WANDER = Figure("wander_rms_m_settled", "RMS wander about each vessel's 60 s mean spot, m")
_MOTORBOAT_EXPERIMENTS: tuple[Experiment, ...] = (
    Experiment(
        "aggregation-motorboats",
        4,
        "aggregation-motorboats",
        "Aggregation of 45 motorboats in wind (hull of 60 s mean positions; physics)",
        (*_AGGREGATION, _AGGREGATION_WANDER),
        beyond_paper=True,
    ),
    Experiment(
        "aggregation-mixed",
        4,
        "aggregation-mixed",
        "Aggregation of 25 buoys and 20 motorboats together (hull of 60 s mean positions; physics)",
        (*_AGGREGATION, _AGGREGATION_WANDER),
        beyond_paper=True,
    ),
    Experiment(
        "leader-follower-motorboats",
        5,
        "leader-follower-motorboats",
        "Leader-follower of 45 motorboats, a weak one (physics)",
        _LEADER_FOLLOWER,
        beyond_paper=True,
    ),
)
EXPERIMENTS = EXPERIMENTS + _MOTORBOAT_EXPERIMENTS


def experiment_names() -> list[str]:
    return [e.name for e in EXPERIMENTS]


def select_experiments(names: Sequence[str]) -> list[Experiment]:
    """The experiments named (a name, or DESIGN.md's number for all its variants), in the report's
    order; all the paper's when `names` is empty (variants beyond the paper, such as motorboats, run when
    named). ScenarioError naming an unknown one and the known ones."""
    if not names:
        return [e for e in EXPERIMENTS if not e.beyond_paper]
    chosen: set[str] = set()
    for name in names:
        hits = [e.name for e in EXPERIMENTS if e.name == name or (str(e.number) == name and not e.beyond_paper)]
        if not hits:
            raise ScenarioError(
                f"no experiment {name!r}; give DESIGN.md's number (1 to 7) or a name: {', '.join(experiment_names())}"
            )
        chosen.update(hits)
    return [e for e in EXPERIMENTS if e.name in chosen]


def run_experiment(task: tuple[Scenario, bool]) -> dict[str, Any]:
    """Simulate one (scenario, force): its metrics row, with Table 1's measured entries as delivery.N*_d*m."""
    scenario, force = task
    try:
        metrics = simulate(scenario, force=force).metrics
    except ScenarioError as error:  # e.g. a seed whose start cannot be placed: a failed run, the others go on
        return failed_row(error)
    row = metrics_row(metrics)
    for entry in metrics.get("table", []):
        row[f"delivery.N{entry['agents']}_d{entry['distance_m']:g}m"] = float(entry["measured"])
    return row


def experiment_runs(
    experiments: Sequence[Experiment], seeds: Sequence[int], duration_s: float | None = None
) -> list[SweepRun]:
    """Every (experiment, seed) in the report's order; `duration_s` caps each scenario's duration (for
    smoke tests: the criteria of a shortened run mean little). ScenarioError for a bad seed or duration."""
    runs = []
    for experiment in experiments:
        base = load_scenario(experiment.scenario)
        cap = None if duration_s is None else min(duration_s, base.duration_s)
        base = base.with_overrides(agents=experiment.agents, duration_s=cap)
        for seed in seeds:
            columns = {"experiment": experiment.name, "agents": base.n_agents, "seed": int(seed)}
            runs.append(SweepRun(columns, base.with_overrides(seed=int(seed))))
    return runs


def reproduce(
    names: Sequence[str],
    seeds: Sequence[int],
    out: Path,
    *,
    duration_s: float | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    resume: bool = False,
    progress: bool = True,
    force: bool = False,
) -> list[dict[str, Any]]:
    """Run the chosen experiments at every seed; write the report to `out` (all or nothing).

    Returns report.csv's rows. ScenarioError, OutputDirectoryError, PartialSweepError or ClusterError
    before the first run.
    """
    if not seeds:
        raise ScenarioError("reproduce: give at least one seed (--seeds N)")
    check_execution(workers, scheduler)
    experiments = select_experiments(names)
    if duration_s is not None and not (math.isfinite(duration_s) and duration_s > 0):
        raise ScenarioError(f"--duration must be a positive number of seconds, got {duration_s}")
    runs = experiment_runs(experiments, seeds, duration_s)
    for k in range(0, len(runs), len(seeds)):  # each experiment's runs, one scenario at a time
        check_sweep_size([runs[k].scenario], len(seeds), f"reproduce {runs[k].columns['experiment']!r}", force=force)
    check_output_directory(out, "report.md")
    partial = partial_path(out)
    started = time.monotonic()
    rows = execute_runs(
        runs,
        partial,
        run_experiment,
        force=force,
        resume=resume,
        workers=workers,
        scheduler=scheduler,
        progress=progress,
        desc="reproduce",
    )
    wall_s = time.monotonic() - started
    experiments = sorted(experiments, key=lambda e: e.number)  # run cheap ones first, report in DESIGN.md's order
    report = summarise(experiments, rows)
    where = describe_execution(workers, scheduler)

    def write(staging: Path) -> None:
        write_rows_csv(rows, staging / "runs.csv", ["experiment", "agents", "seed", "passed"])
        write_rows_csv(report, staging / "report.csv", REPORT_COLUMNS)
        write_environment(staging)
        (staging / "figures").mkdir()
        for experiment in experiments:
            _figure_plot(experiment, rows, staging / "figures" / f"{experiment.name}.png")
        _pass_rate_plot(report, staging / "figures" / "pass_rates.png")
        text = markdown(experiments, report, seeds, where, wall_s, duration_s)
        (staging / "report.md").write_text(text, encoding="utf-8")

    write_atomically(out, write, marker="report.md")
    finish_partial(partial)
    return report


REPORT_COLUMNS = [
    "experiment",
    "number",
    "scenario",
    "agents",
    "item",
    "name",
    "runs",
    "passed",
    "pass_rate",
    "median",
    "q25",
    "q75",
    "min",
    "max",
    "paper",
    "paper_text",
    "seeds",
]


def _stats(values: list[float]) -> dict[str, float]:
    v = np.asarray(values, dtype=float)
    q25, median, q75 = np.percentile(v, [25, 50, 75])
    return {"median": float(median), "q25": float(q25), "q75": float(q75), "min": float(v.min()), "max": float(v.max())}


def summarise(experiments: Sequence[Experiment], rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """report.csv's rows: per experiment, 'all criteria', each criterion's passes, each figure's statistics.

    A criterion a run does not report (e.g. no removal happened in a shortened run) is not counted
    for it: `runs` says how many did; a run that could not be simulated at all (`error`) counts as
    failing every criterion of its experiment. A figure a run could not measure (None: never happened) is
    left out of the statistics: `runs` says how many had a value.
    """
    out = []
    for e in experiments:
        mine = [r for r in rows if r["experiment"] == e.name]
        base = {
            "experiment": e.name,
            "number": e.number,
            "scenario": e.scenario,
            "agents": mine[0]["agents"] if mine else "",
        }
        passed = sum(bool(r.get("passed")) for r in mine)
        out.append(
            {
                **base,
                "item": "all",
                "name": "all criteria",
                "runs": len(mine),
                "passed": passed,
                "pass_rate": passed / len(mine) if mine else "",
            }
        )
        criteria = sorted({k for r in mine for k in r if k.startswith("criteria.")})
        for key in criteria:
            have = [bool(r.get(key)) for r in mine if key in r or "error" in r]  # a run that failed fails each
            out.append(
                {
                    **base,
                    "item": "criterion",
                    "name": key.removeprefix("criteria."),
                    "runs": len(have),
                    "passed": sum(have),
                    "pass_rate": sum(have) / len(have),
                }
            )
        errors: dict[str, list[int]] = {}
        for r in mine:
            if "error" in r:
                errors.setdefault(str(r["error"]), []).append(int(r["seed"]))
        for text, seeds in errors.items():
            out.append({**base, "item": "error", "name": text, "runs": len(seeds), "seeds": " ".join(map(str, seeds))})
        for figure in e.figures:
            values = [float(r[figure.metric]) for r in mine if _is_number(r.get(figure.metric))]
            entry = {
                **base,
                "item": "figure",
                "name": figure.metric,
                "runs": len(values),
                "paper": "" if figure.paper is None else figure.paper,
                "paper_text": figure.paper_text,
            }
            if values:
                entry.update(_stats(values))
            out.append(entry)
    return out


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def reproduced(report: Sequence[dict[str, Any]]) -> bool:
    """Every criterion of every experiment passed at at least PASS_RATE of its runs."""
    return all(r["pass_rate"] >= PASS_RATE - 1e-12 for r in report if r["item"] == "criterion")


def _g(value: Any) -> str:
    if value == "" or value is None:
        return "-"
    v = float(value)
    return f"{v:,.0f}" if abs(v) >= 1000 else f"{v:.3g}"


def markdown(
    experiments: Sequence[Experiment],
    report: Sequence[dict[str, Any]],
    seeds: Sequence[int],
    where: str,
    wall_s: float,
    duration_s: float | None,
) -> str:
    """report.md: a summary table, then per experiment its criteria and figures beside the paper's."""
    seeds = list(seeds)
    env = environment()
    span = f"{seeds[0]}-{seeds[-1]}" if seeds == list(range(seeds[0], seeds[-1] + 1)) else ", ".join(map(str, seeds))
    lines = [
        "# The paper's experiments over many seeds",
        "",
        f"Seeds {span} ({len(seeds)} per experiment), run {where}; wall time of this invocation "
        f"{wall_s:,.0f} s (runs resumed from a partial file are not in it).",
        f"A criterion reproduces when it passes at at least {PASS_RATE:.0%} of the seeds.",
        f"Code: bob-autonomy source {env[SOURCE_KEY]}; Python {env['python']}, numpy {env['numpy']}, scipy "
        f"{env['scipy']}, casadi {env['casadi']} (all in environment.json).",
    ]
    if duration_s is not None:
        lines.append(f"**Durations capped at {duration_s:g} s: a smoke test, not a reproduction.**")
    lines += [
        "",
        "| experiment | DESIGN.md | runs | all criteria passed | worst criterion | reproduced |",
        "|---|---|---|---|---|---|",
    ]
    for e in experiments:
        mine = [r for r in report if r["experiment"] == e.name]
        total = next(r for r in mine if r["item"] == "all")
        crit = [r for r in mine if r["item"] == "criterion"]
        worst = min(crit, key=lambda r: r["pass_rate"]) if crit else None
        ok = all(r["pass_rate"] >= PASS_RATE - 1e-12 for r in crit)
        worst_text = f"{worst['name']} {worst['passed']}/{worst['runs']}" if worst else "-"
        lines.append(
            f"| {e.name} | {e.number} | {total['runs']} | {total['passed']}/{total['runs']} | {worst_text} | "
            f"{'yes' if ok else '**no**'} |"
        )
    for e in experiments:
        mine = [r for r in report if r["experiment"] == e.name]
        lines += [
            "",
            f"## {e.name}: {e.title}",
            "",
            f"Scenario `{e.scenario}`, {mine[0]['agents']} agents; DESIGN.md experiment {e.number}.",
            "",
            "| criterion | passed | rate |",
            "|---|---|---|",
        ]
        for r in mine:
            if r["item"] in ("all", "criterion"):
                lines.append(f"| {r['name']} | {r['passed']}/{r['runs']} | {r['pass_rate']:.0%} |")
        for r in mine:
            if r["item"] == "error":
                lines += ["", f"{r['runs']} run(s) could not be simulated (seeds {r['seeds']}): {r['name']}"]
        lines += ["", "| figure | median | quartiles | range | runs | paper |", "|---|---|---|---|---|---|"]
        labels = {f.metric: f.label for f in e.figures}
        for r in mine:
            if r["item"] == "figure":
                name = f"{labels[r['name']]} (`{r['name']}`)"
                if "median" in r:
                    lines.append(
                        f"| {name} | {_g(r['median'])} | {_g(r['q25'])} - {_g(r['q75'])} | "
                        f"{_g(r['min'])} - {_g(r['max'])} | {r['runs']} | {r['paper_text']} |"
                    )
                else:
                    lines.append(f"| {name} | - | - | - | 0 | {r['paper_text']} |")
        lines += ["", f"![{e.name}](figures/{e.name}.png)"]
    return "\n".join(lines) + "\n"


def _figure_plot(experiment: Experiment, rows: Sequence[dict[str, Any]], path: Path) -> None:
    """Each figure seed by seed (dots), its median (bar) and the paper's value (dashed), one panel each."""
    mine = [r for r in rows if r["experiment"] == experiment.name]
    figures = experiment.figures
    fig, axes = plt.subplots(1, len(figures), figsize=(3.2 * len(figures) + 1, 3.6), squeeze=False)
    for ax, figure in zip(axes[0], figures, strict=True):
        points = [(r["seed"], float(r[figure.metric])) for r in mine if _is_number(r.get(figure.metric))]
        if points:
            values = [v for _, v in points]
            jitter = np.linspace(-0.15, 0.15, len(values)) if len(values) > 1 else np.zeros(1)
            ax.scatter(jitter, values, s=18, color="tab:blue", label="seeds")
            ax.hlines(np.median(values), -0.3, 0.3, color="tab:blue", linewidth=2, label="median")
        if figure.paper is not None:
            ax.axhline(figure.paper, color="tab:red", linestyle="--", label="paper")
        ax.set_xlim(-0.5, 0.5)
        ax.set_xticks([])
        ax.set_title(figure.label, fontsize="small")
        ax.text(0.02, 0.02, f"{len(points)}/{len(mine)} runs", transform=ax.transAxes, fontsize="x-small")
    axes[0][0].legend(fontsize="x-small")
    fig.suptitle(f"{experiment.name}: over {len(mine)} seeds", fontsize="medium")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _pass_rate_plot(report: Sequence[dict[str, Any]], path: Path) -> None:
    """Every criterion's pass rate, experiment by experiment, against the PASS_RATE line."""
    crit = [r for r in report if r["item"] == "criterion"]
    fig, ax = plt.subplots(figsize=(8, 0.28 * len(crit) + 1.2))
    labels = [f"{r['experiment']}: {r['name']}" for r in crit]
    rates = [r["pass_rate"] for r in crit]
    colors = ["tab:green" if r >= PASS_RATE - 1e-12 else "tab:red" for r in rates]
    ax.barh(range(len(crit)), rates, color=colors)
    for k, r in enumerate(crit):
        ax.text(min(r["pass_rate"], 0.9) + 0.01, k, f"{r['passed']}/{r['runs']}", va="center", fontsize="x-small")
    ax.set_yticks(range(len(crit)), labels, fontsize="x-small")
    ax.invert_yaxis()
    ax.axvline(PASS_RATE, color="black", linestyle="--", linewidth=1)
    ax.set_xlim(0, 1)
    ax.set_xlabel("fraction of seeds passing")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
