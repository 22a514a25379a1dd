"""The perimeter-defence metric's re-spread criterion on hand-made frames (walls only removed robots covered)."""

from __future__ import annotations

import numpy as np
import pytest

from sitl.experiments.metrics import perimeter_defense_metrics
from sitl.experiments.recorder import Frame, Recorder
from sitl.experiments.scenario import load_scenario
from sitl.fleets.fleet import LockstepFleet

CORNER_LEFT, CORNER_RIGHT, MIDDLE = (1.0, 1.0), (12.5, 1.0), (6.75, 3.1)


def metrics_of(frames: list[list[tuple[float, float]]], removed: list[int], removal_t_s: float = 1.0) -> dict:
    """Metrics of a 13.5 m x 6.2 m room run logged once a second: frame k holds the positions of the
    agents still active (agent indices kept in order); `removed` leave at `removal_t_s` (s)."""
    fleet = LockstepFleet(load_scenario("perimeter-defense").with_overrides(agents=3))
    fleet.events_log = [{"t_s": removal_t_s, "action": "remove", "agents": removed}]
    rec = Recorder(1.0, ["ebot"] * 3)
    for k, positions in enumerate(frames):
        agents = np.arange(3) if k * 1.0 <= removal_t_s else np.setdiff1d(np.arange(3), removed)
        n = len(positions)
        assert n == agents.size
        rec.record(Frame(float(k), agents, np.array(positions), np.zeros(n), np.zeros((n, 2)), ["pd"] * n))
    return perimeter_defense_metrics(fleet, rec, {"cover_radius_m": 2.5, "min_coverage": 0.7, "min_recovered": 0.3})


def test_a_survivor_taking_the_removed_robots_place_recovers_all_it_vacated() -> None:
    before = [CORNER_LEFT, CORNER_RIGHT, MIDDLE]
    m = metrics_of([before, before, [CORNER_LEFT, MIDDLE], [CORNER_LEFT, CORNER_RIGHT]], removed=[1])
    # Only (12.5, 1) covered the bottom wall for x in [12.5 - sqrt(2.5^2 - 1), 13.5] = [10.21, 13.5] and the
    # right wall for y in [0, 1 + 2.29]: 6.58 m of the 39.4 m of wall ((1, 1) reaches x = 3.29; (6.75, 3.1) is
    # 3.1 m from the long walls and 6.75 m from the short ones, beyond 2.5 m).
    assert m["vacated_wall_fraction"] == pytest.approx(6.58 / 39.4, abs=0.01)
    assert m["vacated_recovered_fraction"] == pytest.approx(1.0)
    assert m["criteria"]["respread_recovers_0.3_of_vacated_walls"]


def test_survivors_that_stay_put_recover_nothing_and_fail() -> None:
    before = [CORNER_LEFT, CORNER_RIGHT, MIDDLE]
    m = metrics_of([before, before, [CORNER_LEFT, MIDDLE], [CORNER_LEFT, MIDDLE]], removed=[1])
    assert m["vacated_recovered_fraction"] == 0.0
    assert not m["criteria"]["respread_recovers_0.3_of_vacated_walls"]
    assert not m["passed"]


def test_partial_recovery_is_the_covered_share_of_the_vacated_walls() -> None:
    before = [CORNER_LEFT, CORNER_RIGHT, MIDDLE]
    # The middle survivor ends at (8.75, 1): it covers the bottom wall for x in [6.46, 11.04], i.e. 0.83 m of
    # the 6.58 m vacated (bottom wall x in [10.21, 13.5], right wall y in [0, 3.29]): 0.126, below 0.3.
    m = metrics_of([before, before, [CORNER_LEFT, MIDDLE], [CORNER_LEFT, (8.75, 1.0)]], removed=[1])
    assert m["vacated_recovered_fraction"] == pytest.approx(0.83 / 6.58, abs=0.03)
    assert not m["criteria"]["respread_recovers_0.3_of_vacated_walls"]


def test_a_removal_that_vacates_no_wall_gives_no_recovery_and_fails() -> None:
    # Agent 2 at (12.6, 0.9) covers the bottom wall from x = 12.6 - 2.33 = 10.27 and the right wall to
    # y = 3.23, all within what agent 1 at (12.5, 1) covers: removing it leaves every wall covered.
    before = [CORNER_LEFT, CORNER_RIGHT, (12.6, 0.9)]
    m = metrics_of([before, before, [CORNER_LEFT, CORNER_RIGHT], [CORNER_LEFT, CORNER_RIGHT]], removed=[2])
    assert m["vacated_wall_fraction"] == 0.0
    assert m["vacated_recovered_fraction"] is None
    assert not m["criteria"]["respread_recovers_0.3_of_vacated_walls"]
