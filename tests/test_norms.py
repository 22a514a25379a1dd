"""sitl.norms gives the bits of the plain np.hypot expressions it replaces: lengths at their bound to within a
few units in the last place, far from it, zero, NaN, infinite, and where squares underflow or overflow."""

from __future__ import annotations

import numpy as np
import pytest

from sitl.norms import exceeds, limit_scale


def lengths_about(bound: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(dx, dy) at random angles whose lengths are `bound` to within 4 ulp, every 7th anywhere in [0, 2 bound)."""
    angle = rng.uniform(0.0, 2 * np.pi, bound.size)
    length = bound * (1.0 + rng.integers(-4, 5, bound.size) * np.finfo(float).eps)
    length[::7] *= rng.uniform(0.0, 2.0, length[::7].size)
    return length * np.cos(angle), length * np.sin(angle)


def test_exceeds_gives_hypots_verdicts() -> None:
    rng = np.random.default_rng(5)
    bound = rng.uniform(0.5, 40.0, 200_000)
    dx, dy = lengths_about(bound, rng)
    dy[::11] = np.nan  # no held message
    assert np.array_equal(exceeds(dx, dy, bound, bound), np.hypot(dx, dy) > bound)
    one = np.array(0.05)  # one bound for every element
    dx, dy = lengths_about(np.full(50_000, 0.05), rng)
    assert np.array_equal(exceeds(dx, dy, one, one), np.hypot(dx, dy) > 0.05)
    tiny = np.full(3, 1e-120)  # bounds where squares underflow: hypot throughout
    assert np.array_equal(exceeds(np.array([0.0, 1e-120, 2e-120]), np.zeros(3), tiny, tiny), [False, False, True])
    nothing = np.full(2, np.nan)
    assert not exceeds(np.ones(2), np.ones(2), nothing, nothing).any()


@pytest.mark.parametrize("bound", [1.0, 0.05, 1e-9, 3.7e5])
def test_limit_scale_gives_the_plain_expressions_bits(bound: float) -> None:
    rng = np.random.default_rng(int(bound * 1e9) % 2**32)
    dx, dy = lengths_about(np.full(100_000, bound), rng)
    vectors = np.column_stack((dx, dy))
    vectors[::13] = 0.0
    vectors[5::97, 0] = np.nan
    vectors[6::97, 1] = np.inf
    vectors[7::97] = np.finfo(float).max  # the square overflows
    vectors[8::97] = 1e-200  # the square underflows
    plain = np.minimum(1.0, bound / np.maximum(np.hypot(vectors[:, 0], vectors[:, 1]), 1e-12))
    fast = limit_scale(vectors, bound)
    assert np.array_equal(fast, plain, equal_nan=True)
    assert np.array_equal(fast.view(np.int64), plain.view(np.int64))  # the same bits, signs of zero included
    assert (fast < 1.0).any() and (fast == 1.0).any()  # both branches taken


def test_limit_scale_refuses_a_bound_it_cannot_answer_exactly() -> None:
    with pytest.raises(ValueError, match="bound"):
        limit_scale(np.ones((2, 2)), 1e-13)
    with pytest.raises(ValueError, match="bound"):
        limit_scale(np.ones((2, 2)), float("nan"))
