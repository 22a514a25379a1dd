"""The best-wall-coverage reference (sitl.experiments.perimeter_reference) against lengths worked out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sitl.experiments.perimeter_reference import PACKAGED_ROOM, best_wall_coverage, covered_wall_length

PERIMETER_M = 2 * (13.5 + 6.2)


def test_a_robot_off_a_corner_covers_a_plus_the_chord_on_each_wall() -> None:
    # At (1, 1) with r = 2.5: on the bottom wall x in [0, 1 + sqrt(6.25 - 1)], the same on the left wall.
    assert covered_wall_length(np.array([[1.0, 1.0]]), PACKAGED_ROOM, 2.5) == pytest.approx(2 * (1 + math.sqrt(5.25)))


def test_a_robot_farther_than_the_radius_from_every_wall_covers_nothing() -> None:
    assert covered_wall_length(np.array([[6.75, 3.1]]), PACKAGED_ROOM, 2.5) == 0.0


def test_overlapping_robots_count_their_union_once() -> None:
    # Two robots 1 m from the bottom wall at x = 5 and x = 7: chords [2.71, 7.29] and [4.71, 9.29]: 6.58 m.
    half = math.sqrt(6.25 - 1.0)
    got = covered_wall_length(np.array([[5.0, 1.0], [7.0, 1.0]]), PACKAGED_ROOM, 2.5)
    assert got == pytest.approx(2.0 + 2 * half)
    assert got == pytest.approx(covered_wall_length(np.array([[5.0, 1.0], [7.0, 1.0], [6.0, 1.0]]), PACKAGED_ROOM, 2.5))


def test_the_configuration_five_ebots_reach_at_best_matches_the_metric() -> None:
    # Seed 101's settled positions (tests/test_perimeter_equilibria.py, A): the metric's 0.1 m grid gave 0.759.
    a = np.array([(1.04, 1.10), (1.09, 5.17), (6.46, 1.32), (12.35, 5.12), (12.43, 1.15)])
    assert covered_wall_length(a, PACKAGED_ROOM, 2.5) / PERIMETER_M == pytest.approx(0.759, abs=0.005)


def test_one_robot_at_best_sits_r_over_root_two_from_a_corner() -> None:
    # Covering a + sqrt(r^2 - a^2) of each wall is largest at a = r / sqrt(2): 2 sqrt(2) r = 7.07 m.
    fraction, positions = best_wall_coverage(1)
    assert fraction == pytest.approx(2 * math.sqrt(2) * 2.5 / PERIMETER_M, abs=1e-4)
    corner = np.array([[0.0, 0.0], [13.5, 0.0], [13.5, 6.2], [0.0, 6.2]])
    offsets = np.abs(positions[0] - corner)
    assert np.min(np.max(np.abs(offsets - 2.5 / math.sqrt(2)), axis=1)) < 0.01
