"""Non-finite actuator commands: finite_pair keeps numpy.nan_to_num's rule, so the RC override bytes are those of
the nan_to_num'ed command (NaN -> neutral, +-inf -> full deflection of that sign)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from bob_autonomy.core.arrays import finite_pair
from bob_autonomy.onboard.vehicle_link import VehicleLink

SPECIAL = (0.0, -0.0, 1.5, -3.25, 1e308, math.nan, math.inf, -math.inf)


@pytest.mark.parametrize(("x", "y"), list(itertools.product(SPECIAL, repeat=2)))
def test_finite_pair_is_nan_to_num(x: float, y: float) -> None:
    expected = np.nan_to_num(np.array([x, y]))
    got = finite_pair(np.array([x, y]))
    assert all(isinstance(v, float) for v in got)
    np.testing.assert_array_equal(np.array(got), expected)
    assert [math.copysign(1.0, v) for v in got] == [math.copysign(1.0, v) for v in expected]


@pytest.mark.parametrize("kind", ["buoy", "ebot"])
def test_override_bytes_of_a_non_finite_command_are_those_of_nan_to_num(kind: str) -> None:
    full = 45.0 if kind == "buoy" else 0.2
    for x, y in itertools.product(SPECIAL, repeat=2):
        sent, reference = VehicleLink(1, kind, full, lambda: 0.0), VehicleLink(1, kind, full, lambda: 0.0)
        assert sent.command(np.array([x, y])) == reference.command(np.nan_to_num(np.array([x, y])))
    with pytest.raises(ValueError):
        VehicleLink(1, kind, full, lambda: 0.0).command(np.zeros(3))  # not a pair: refused, as before
