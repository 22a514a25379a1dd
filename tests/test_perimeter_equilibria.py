"""Why 5 eBots do not always cover 0.7 of the walls: eq. (3) settles in one of several local minima.

Eq. (3) negated moves each robot along -grad of U = -sum_{i<j} log |p_i - p_j| (plus the walls' push), so
the swarm stops in a local minimum of U, not necessarily the best one. In the 13.5 m x 6.2 m room three
minima for 5 robots are reached from the packaged corner start (docs/perimeter-defense.md): A, four
corners and the middle of a long wall (0.76 of the walls within 2.5 m); B, four corners and the middle of
a short wall (0.66); C, three on the left wall and two on the bottom wall's right end (0.58). Placed
there, the packaged model stays there: none is a transient that more time would resolve.
"""

from __future__ import annotations

import numpy as np
import pytest

from sitl.experiments.runner import simulate
from sitl.experiments.scenario import load_scenario, validate_scenario

# Positions (m) where the packaged runs settled at t = 149 s: seed 101 (A), 103 (B) and 108 (C), 5 eBots.
SETTLED = {
    "A": ([(1.04, 1.10), (1.09, 5.17), (6.46, 1.32), (12.35, 5.12), (12.43, 1.15)], 0.76),
    "B": ([(1.08, 0.86), (1.07, 5.33), (1.41, 3.04), (12.33, 5.06), (12.37, 1.10)], 0.66),
    "C": ([(1.07, 0.90), (1.10, 5.38), (1.27, 3.33), (9.36, 1.42), (12.53, 1.36)], 0.58),
}


def placed_run(positions: list[tuple[float, float]], duration_s: float = 150.0) -> dict:
    """The packaged scenario with one eBot in a 2 cm box at each position, no removal; its metrics."""
    data = load_scenario("perimeter-defense").model_dump()
    group = data["groups"][0]
    data["groups"] = [
        {
            **group,
            "name": f"ebot{k}",
            "count": 1,
            "start": {**group["start"], "box": {"min": [x - 0.01, y - 0.01], "max": [x + 0.01, y + 0.01]}},
        }
        for k, (x, y) in enumerate(positions)
    ]
    data["events"] = []
    data["duration_s"] = duration_s
    data["resize_group"] = None
    return simulate(validate_scenario(data, "settled start")).metrics


@pytest.mark.parametrize("name", sorted(SETTLED))
def test_each_settled_configuration_is_a_stable_equilibrium(name: str) -> None:
    positions, coverage = SETTLED[name]
    m = placed_run(positions)
    assert m["initial_perimeter_coverage"] == pytest.approx(coverage, abs=0.01)
    # 150 s later the robots have not left the minimum: coverage unchanged within 0.02.
    assert m["final_perimeter_coverage"] == pytest.approx(coverage, abs=0.02)


def test_the_minima_are_ordered_by_the_rules_potential() -> None:
    """U = -sum log d_ij is lowest at A: eq. (3)'s own best is also the best covering of the three."""
    potential = {}
    for name, (positions, _) in SETTLED.items():
        p = np.array(positions)
        d = np.hypot(*(p[:, None] - p[None]).transpose(2, 0, 1))[np.triu_indices(len(p), 1)]
        potential[name] = -np.log(d).sum()
    assert potential["A"] < potential["B"] < potential["C"]


def test_an_unsettled_configuration_does_move() -> None:
    """The control: 5 robots 1 m apart in the middle of the room spread to the walls within the same 150 s."""
    m = placed_run([(4.75 + k, 3.1) for k in range(5)])
    assert m["initial_perimeter_coverage"] < 0.1
    assert m["final_perimeter_coverage"] > 0.55
