"""The parameters each metric kind reads (`[metrics] params` of a scenario), checked before a run starts.

The metrics run once the whole run is over (`sitl.experiments.metrics`), so a misspelt threshold would be
silently replaced by its default, and a leader or weak agent that does not exist, or a missing goal, would
fail only after the run's hours, losing it. `metric_params_problem` finds those when the scenario is read.
"""

from __future__ import annotations

import difflib
import math

NUMBER = "a number"
AGENT = "an agent index"
AGENTS = "a list of agent indices"
OUTCOME = "one of 'yield', 'through', 'around'"

# kind -> parameter -> what it must be; the metrics of `generic` read none, and accept any (free-form notes).
PARAMS: dict[str, dict[str, str]] = {
    "heading-consensus": dict.fromkeys(
        ("tolerance_deg", "consensus_by_s", "follow_by_s", "min_leader_offset_deg"), NUMBER
    ),
    "perimeter-defense": dict.fromkeys(("cover_radius_m", "min_coverage", "min_recovered", "grid_m"), NUMBER),
    "search-exploration": {"arrival_radius_m": NUMBER},
    "aggregation": dict.fromkeys(
        ("factor", "average_window_s", "start_area_m2", "end_area_m2", "aggregation_time_s"), NUMBER
    ),
    "leader-follower": {
        "leader": AGENT,
        "weak_agents": AGENTS,
        **dict.fromkeys(("arrival_radius_m", "min_separation_m", "min_path_m"), NUMBER),
    },
    "avoidance": {
        "mover": AGENT,
        "expected": OUTCOME,
        **dict.fromkeys(
            ("goal_x_m", "goal_y_m", "arrival_radius_m", "through_depth_m", "yield_displacement_m"), NUMBER
        ),
    },
    "exploration": {},
    "radio-table": dict.fromkeys(("tolerance_pp", "rounds", "bin_halfwidth_m"), NUMBER),
}
REQUIRED: dict[str, tuple[str, ...]] = {"avoidance": ("goal_x_m", "goal_y_m")}
POSITIVE = ("grid_m", "rounds", "bin_halfwidth_m")  # a grid spacing, a count, a bin: zero or less cannot be run


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _agent_problem(value: object, n_agents: int) -> str | None:
    if not _is_number(value) or not float(value).is_integer():
        return f"must be an agent index (a whole number), got {value!r}"
    if not 0 <= int(value) < n_agents:
        return f"names agent {int(value)}, which does not exist (agents 0..{n_agents - 1})"
    return None


def _value_problem(name: str, what: str, value: object, n_agents: int) -> str | None:
    if what == AGENT:
        return _agent_problem(value, n_agents)
    if what == AGENTS:
        if not isinstance(value, list):
            return f"must be {AGENTS}, got {value!r}"
        return next((p for p in (_agent_problem(v, n_agents) for v in value) if p), None)
    if what == OUTCOME:
        return None if value in ("yield", "through", "around") else f"must be {OUTCOME}, got {value!r}"
    if not _is_number(value) or not math.isfinite(value):
        return f"must be {NUMBER}, got {value!r}"
    if name in POSITIVE and value <= 0:
        return f"must be positive, got {value!r}"
    return None


def metric_params_problem(kind: str, params: dict[str, object], n_agents: int) -> str | None:
    """What is wrong with the `[metrics] params` of a scenario whose metrics are `kind` and whose fleet has
    `n_agents` agents, in words that name the key and what to write instead; None when nothing is."""
    known = PARAMS.get(kind)
    if known is None:
        return None
    for name, value in params.items():
        if name not in known:
            close = difflib.get_close_matches(name, list(known), n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            names = ", ".join(sorted(known)) or "none"
            return f"{name!r} is not a parameter of the {kind} metrics ({hint}they read: {names})"
        problem = _value_problem(name, known[name], value, n_agents)
        if problem:
            return f"{name!r} {problem}"
    missing = [name for name in REQUIRED.get(kind, ()) if name not in params]
    if missing:
        return f"the {kind} metrics need {' and '.join(repr(m) for m in missing)}"
    return None
