"""Resilient (W-MSR) consensus: behaviors.resilient, HeadingConsensus and BobRule with resilient_f, by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
from behavior_helpers import make_table, make_view
from numpy.testing import assert_allclose

from behaviors.base import SwarmTable, View, wrap_angle
from behaviors.bob_rule import BobRule
from behaviors.heading_consensus import HeadingConsensus
from behaviors.resilient import wmsr_keep

DEG = math.pi / 180.0


def mean_deg(*angles_deg: float) -> float:
    """Direction of the sum of unit vectors at these angles (deg), computed by hand."""
    s = sum(math.sin(a * DEG) for a in angles_deg)
    c = sum(math.cos(a * DEG) for a in angles_deg)
    return math.degrees(math.atan2(s, c))


# -- the rule itself ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("difference", "f", "kept"),
    [
        ([3.0, 1.0, -2.0, -5.0, 0.0, 2.0], 0, [1, 1, 1, 1, 1, 1]),
        ([3.0, 1.0, -2.0, -5.0, 0.0, 2.0], 1, [0, 1, 1, 0, 1, 1]),  # the largest above, the smallest below
        ([3.0, 1.0, -2.0, -5.0, 0.0, 2.0], 2, [0, 1, 0, 0, 1, 0]),
        ([3.0, 1.0, -2.0, -5.0, 0.0, 2.0], 9, [0, 0, 0, 0, 1, 0]),  # fewer than F on a side: all of them go
        ([0.0, 0.0, 0.0], 1, [1, 1, 1]),  # equal to one's own: never discarded
        ([4.0, 4.0, 1.0], 1, [1, 0, 1]),  # a tie at the cut: one of the two (the later pair) goes
        ([-1.0, np.nan, 7.0], 1, [0, 1, 0]),  # not a number: treated as equal, kept
        ([], 1, []),
    ],
)
def test_one_listener_by_hand(difference, f, kept) -> None:
    mask = wmsr_keep(np.array(difference, dtype=float), np.zeros(len(difference), dtype=np.intp), f)
    assert mask.astype(int).tolist() == kept


def test_listeners_are_independent_whatever_the_pair_order() -> None:
    # Listener 1's pairs interleaved with listener 0's: each drops its own extremes.
    difference = np.array([5.0, -1.0, 2.0, -7.0, 1.0, 3.0, -2.0])
    listener = np.array([0, 1, 0, 1, 1, 0, 0])
    # Listener 0: 5, 2, 3, -2 -> drop 5 and -2. Listener 1: -1, -7, 1 -> drop 1 and -7.
    assert wmsr_keep(difference, listener, 1).astype(int).tolist() == [0, 1, 1, 0, 0, 1, 0]


def test_negative_f_is_refused() -> None:
    with pytest.raises(ValueError, match="at least 0"):
        wmsr_keep(np.zeros(2), np.zeros(2, dtype=np.intp), -1)
    for bad in (-1, 1.5, "1"):
        with pytest.raises(ValueError, match="resilient_f"):
            HeadingConsensus(resilient_f=bad)
        with pytest.raises(ValueError, match="resilient_f"):
            BobRule(H=1, resilient_f=bad)


# -- heading consensus (eq. 2) ------------------------------------------------------------------------------


def test_heading_consensus_f1_by_hand() -> None:
    headings = [0.0, 10.0, 20.0, 170.0]
    table = make_table([[0, 0], [1, 0], [2, 0], [3, 0]], headings=[h * DEG for h in headings])
    wish = HeadingConsensus(resilient_f=1).step(make_view(table))
    # 0 deg hears +10, +20, +170: drops +170 -> mean(0, 10, 20) = 10.
    # 10 deg hears -10, +10, +160: drops +160 and -10 -> mean(10, 20) = 15.
    # 20 deg hears -20, -10, +150: drops +150 and -20 -> mean(20, 10) = 15.
    # 170 deg hears -170, -160, -150: drops -170 (heading 0) -> mean(170, 10, 20).
    expected = [10.0, 15.0, 15.0, mean_deg(170.0, 10.0, 20.0)]
    assert_allclose(np.degrees(wish.heading), expected, atol=1e-9)
    plain = HeadingConsensus().step(make_view(table))  # F = 0 is eq. (2) as printed
    assert_allclose(np.degrees(plain.heading[0]), mean_deg(0.0, 10.0, 20.0, 170.0), atol=1e-9)
    assert_allclose(HeadingConsensus(resilient_f=0).step(make_view(table)).heading, plain.heading)


def test_the_difference_is_circular() -> None:
    # Own 170 deg: -170 deg is 20 deg counter-clockwise (greater), 150 deg is 20 deg clockwise (smaller).
    table = make_table([[0, 0], [1, 0], [2, 0]], headings=[170 * DEG, -170 * DEG, 150 * DEG])
    wish = HeadingConsensus(resilient_f=1).step(make_view(table, rows=[0], pairs=[(0, 1), (0, 2)]))
    assert_allclose(np.degrees(wish.heading), [170.0], atol=1e-9)  # both discarded: it keeps its own


def faulty_table(headings_deg: list[float], lie_deg: float) -> tuple[SwarmTable, list[tuple[int, int]]]:
    """n agents in rows 0..n-1, and in row n what the last one broadcasts: its heading + lie_deg. Everyone
    hears everyone else, the last agent through row n."""
    n = len(headings_deg)
    headings = [h * DEG for h in headings_deg] + [(headings_deg[-1] + lie_deg) * DEG]
    table = make_table([[k, 0.0] for k in range(n + 1)], headings=headings)
    pairs = [(i, n if j == n - 1 else j) for i in range(n) for j in range(n) if i != j]
    return table, pairs


def iterate(headings_deg: list[float], lie_deg: float, f: int, steps: int) -> np.ndarray:
    """Headings (deg) after `steps` synchronous steps of eq. (2) (each turns to its target at once)."""
    headings = list(headings_deg)
    for _ in range(steps):
        table, pairs = faulty_table(headings, lie_deg)
        wish = HeadingConsensus(resilient_f=f).step(make_view(table, rows=range(len(headings)), pairs=pairs))
        headings = np.degrees(wish.heading).tolist()
    return np.array(headings)


def test_a_neighbour_that_always_broadcasts_120_degrees_off_drags_eq_2_but_not_w_msr() -> None:
    start = [-40.0, -25.0, -10.0, 0.0, 5.0, 15.0, 30.0, 45.0, 50.0, 20.0]  # the last one lies
    resilient = iterate(start, 120.0, f=1, steps=60)
    normal = resilient[:-1]
    assert np.ptp(normal) < 0.01  # the normal agents agree
    assert -40.0 <= normal.mean() <= 50.0  # on a heading within the range they started in
    again = iterate(resilient.tolist(), 120.0, f=1, steps=1)
    assert np.abs(again[:-1] - normal).max() < 0.01  # and stay there
    # Eq. (2) agrees too, but the stuck offset keeps turning everyone, step after step, without end:
    # at agreement each normal agent's target is atan(sin 120 / (9 + cos 120)) = 5.8 deg further round.
    plain = iterate(start, 120.0, f=0, steps=60)
    turned = np.degrees(wrap_angle(np.radians(iterate(plain.tolist(), 120.0, f=0, steps=1) - plain)))
    assert np.ptp(plain[:-1]) < 1.0
    assert_allclose(turned[:-1], math.degrees(math.atan2(math.sin(120 * DEG), 9 + math.cos(120 * DEG))), atol=0.5)


# -- the consensus sum of the BoB rule (eq. 5) --------------------------------------------------------------


def bob_view(headings_deg: list[float], velocities=None) -> View:
    """Agent 0 at the origin; its neighbours exactly p0 = 10 m away (pair term zero) with these headings."""
    n = len(headings_deg)
    angles = np.linspace(0.0, 2 * math.pi, n, endpoint=False)[: n - 1] if n > 1 else []
    positions = [[0.0, 0.0]] + [[10.0 * math.cos(a), 10.0 * math.sin(a)] for a in angles]
    table = make_table(positions, headings=[h * DEG for h in headings_deg])
    if velocities is not None:
        table.velocity[:] = velocities
    return make_view(table, rows=[0], pairs=[(0, j) for j in range(1, n)])


def unit_deg(angle: float) -> np.ndarray:
    return np.array([math.cos(angle * DEG), math.sin(angle * DEG)])


def test_bob_rule_consensus_sum_f1_by_hand() -> None:
    view = bob_view([0.0, 10.0, 20.0, 170.0])
    rule = dict(p0=10.0, H=1, speed_scale=1.0, max_speed=10.0)
    # N = 3 neighbours heard; pair terms zero at p0; no goal. v = (1/3) (theta_0 + kept thetas).
    plain = BobRule(**rule).step(view).velocity[0]
    assert_allclose(plain, (unit_deg(0) + unit_deg(10) + unit_deg(20) + unit_deg(170)) / 3, atol=1e-12)
    resilient = BobRule(**rule, resilient_f=1).step(view).velocity[0]
    assert_allclose(resilient, (unit_deg(0) + unit_deg(10) + unit_deg(20)) / 3, atol=1e-12)
    both_sides = BobRule(**rule, resilient_f=1).step(bob_view([0.0, 10.0, -30.0, 170.0])).velocity[0]
    assert_allclose(both_sides, (unit_deg(0) + unit_deg(10)) / 3, atol=1e-12)  # -30 and 170 both left out


def test_bob_rule_resilient_courses_by_hand() -> None:
    # align_course: courses of 0, 10, 20 and 170 deg (speeds 1, 2, 1, 1 m/s); agent 0 moves east.
    speeds, courses = [1.0, 2.0, 1.0, 1.0], [0.0, 10.0, 20.0, 170.0]
    velocities = np.array([s * unit_deg(c) for s, c in zip(speeds, courses, strict=True)])
    view = bob_view([90.0, 90.0, 90.0, 90.0], velocities=velocities)  # hull headings say nothing
    rule = dict(p0=10.0, H=1, speed_scale=1.0, max_speed=10.0, align_course=True, resilient_f=1)
    assert_allclose(BobRule(**rule).step(view).velocity[0], (unit_deg(0) + unit_deg(10) + unit_deg(20)) / 3)
    velocities[2] = 0.0  # a still neighbour: course counted as equal to ours, never discarded (a zero term)
    view = bob_view([90.0, 90.0, 90.0, 90.0], velocities=velocities)
    assert_allclose(BobRule(**rule).step(view).velocity[0], (unit_deg(0) + unit_deg(10)) / 3, atol=1e-12)


def test_bob_rule_leaves_neighbours_beyond_p0_to_the_pair_term() -> None:
    # A neighbour 20 m away is outside R_i: W-MSR only sees the ones within p0 (here the 170 deg one alone).
    table = make_table([[0, 0], [10, 0], [20, 0]], headings=[0.0, 170 * DEG, 5 * DEG])
    view = make_view(table, rows=[0], pairs=[(0, 1), (0, 2)])
    rule = dict(p0=10.0, H=1, speed_scale=1.0, max_speed=10.0, resilient_f=1)
    # N = 2; pair terms zero (H = 1 repels only inside p0); R = {1}: 170 deg dropped.
    assert_allclose(BobRule(**rule).step(view).velocity[0], unit_deg(0) / 2, atol=1e-12)
