"""How large a run may be: refused before anything is allocated, with the figures, unless forced.

A lockstep run holds every agent's state and steps it `duration_s / dt_s` times; its recording keeps
one row per active agent per logged frame. A scenario with `count = 1e11`, `--agents 10000000` or
`--duration 1e300` would otherwise allocate until the machine runs out of memory, or step for
centuries. The limits, far above every packaged scenario (at most 45 agents, 1.6e5 agent-steps and
1.7e4 trajectory rows):

- agents: at most `MAX_AGENTS` (200,000);
- agent-steps (agents x steps): at most 1e9 at kinematic fidelity (about half an hour at the
  5e5 agent-steps/s `benchmarks/fleet_step.py` measures) and 1e8 at physics fidelity, whose steps
  cost some 40 times more (MPC and EKF per vessel; `benchmarks/aggregation_speed.py`);
- trajectory rows (agents x logged frames): at most `MAX_TRAJECTORY_ROWS` (2e7, about 2.5 GB of
  trajectory.csv and as much memory while recording).

`bob-sitl run|sweep|fleet --force` runs a scenario beyond these limits (the user's memory and time).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sitl.experiments.scenario import Scenario, ScenarioError

MAX_AGENTS = 200_000
MAX_AGENT_STEPS = {"kinematic": 1e9, "physics": 1e8}
MAX_TRAJECTORY_ROWS = 2e7
AGENT_STEPS_PER_S = {"kinematic": 5e5, "physics": 1.3e4}  # measured on one core, for the messages only


@dataclass(frozen=True)
class RunSize:
    """What a run will cost: agents, steps, agents x steps and trajectory rows (floats: may be huge)."""

    agents: int
    steps: float
    agent_steps: float
    trajectory_rows: float


def run_size(scenario: Scenario) -> RunSize:
    """The size of a lockstep run of `scenario`, computed in floating point (never allocates)."""
    agents = scenario.n_agents
    steps = scenario.duration_s / scenario.dt_s
    frames = min(steps, scenario.duration_s / scenario.log_period_s) + 1  # at most one frame per step
    return RunSize(agents, steps, float(agents) * steps, float(agents) * frames)


def _n(x: float) -> str:
    return f"{x:,.0f}" if x < 1e12 else f"{x:.3g}"


def check_run_size(scenario: Scenario, source: str, *, force: bool = False) -> RunSize:
    """ScenarioError naming `source`, the keys and the figures when a run of `scenario` exceeds a limit.

    `force` skips the limits (but a run whose step count is not even finite is always refused).
    """
    size = run_size(scenario)
    if not math.isfinite(size.agent_steps):
        raise ScenarioError(
            f"{source}: duration_s {scenario.duration_s:g} s / dt_s {scenario.dt_s:g} s is too many steps to count "
            "(the agent-steps overflow): shorten duration_s (--duration) or raise dt_s"
        )
    if force:
        return size
    fidelity = scenario.fidelity
    if size.agents > MAX_AGENTS:
        k = max(range(len(scenario.groups)), key=lambda i: scenario.groups[i].count)
        raise ScenarioError(
            f"{source}: {_n(size.agents)} agents (key 'groups.{k}.count' = {_n(scenario.groups[k].count)}, or "
            f"--agents): at most {_n(MAX_AGENTS)} fit in memory and time; use fewer, or --force to try anyway"
        )
    total = size.agent_steps
    limit = MAX_AGENT_STEPS[fidelity]
    if total > limit:
        hours = total / AGENT_STEPS_PER_S[fidelity] / 3600
        raise ScenarioError(
            f"{source}: {_n(size.agents)} agents x {_n(size.steps)} steps (duration_s {scenario.duration_s:g} s / "
            f"dt_s {scenario.dt_s:g} s) = {_n(total)} agent-steps, about {hours:,.3g} hours; at most "
            f"{_n(limit)} at {fidelity} fidelity: shorten duration_s (--duration), raise dt_s, use fewer agents "
            "(--agents), or --force to run it anyway"
        )
    if size.trajectory_rows > MAX_TRAJECTORY_ROWS:
        raise ScenarioError(
            f"{source}: {_n(size.agents)} agents logged every {max(scenario.log_period_s, scenario.dt_s):g} s "
            f"for {scenario.duration_s:g} s = {_n(size.trajectory_rows)} trajectory rows; at most "
            f"{_n(MAX_TRAJECTORY_ROWS)}: raise log_period_s, shorten duration_s, or --force to run it anyway"
        )
    return size


def check_sweep_size(scenarios: list[Scenario], runs: int, source: str, *, force: bool = False) -> float:
    """Each of `scenarios` (one per swarm size) run `runs` times: each within the limits, and the whole
    sweep's agent-steps within the per-run limit too (a sweep is one command). Returns the total."""
    total = 0.0
    for scenario in scenarios:
        total += check_run_size(scenario, source, force=force).agent_steps * runs
    fidelity = scenarios[0].fidelity if scenarios else "kinematic"
    limit = MAX_AGENT_STEPS[fidelity]
    if not force and total > limit:
        hours = total / AGENT_STEPS_PER_S[fidelity] / 3600
        raise ScenarioError(
            f"{source}: the sweep runs {_n(total)} agent-steps in all ({len(scenarios)} sizes x {runs} runs), about "
            f"{hours:,.3g} hours; at most {_n(limit)} at {fidelity} fidelity: fewer sizes or --runs, or --force"
        )
    return total


__all__ = [
    "MAX_AGENTS",
    "MAX_AGENT_STEPS",
    "MAX_TRAJECTORY_ROWS",
    "RunSize",
    "check_run_size",
    "check_sweep_size",
    "run_size",
]
