"""Wind and current (sitl/world/environment.py) against values worked out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from sitl.world.environment import CurrentGrid, CurrentSpec, Environment, WindSpec


def env(wind: WindSpec | None = None, current: CurrentSpec | None = None, seed: int = 0) -> Environment:
    return Environment(wind or WindSpec(), current or CurrentSpec(), np.random.default_rng(seed))


def test_mean_wind_blows_towards_its_direction_everywhere() -> None:
    e = env(WindSpec(speed_mps=5.0, toward_deg=90.0))  # towards north
    points = np.array([[0.0, 0.0], [100.0, -50.0], [-3.0, 7.0]])
    assert_allclose(e.wind_at(points), [[0.0, 5.0]] * 3, atol=1e-12)
    e.step(1.0)  # no gusts: steady
    assert_allclose(e.wind_at(points), [[0.0, 5.0]] * 3, atol=1e-12)
    w = env(WindSpec(speed_mps=2.0, toward_deg=225.0)).wind_at(np.zeros((1, 2)))
    assert_allclose(w, [[-math.sqrt(2.0), -math.sqrt(2.0)]], atol=1e-12)


def test_gusts_are_uniform_in_space_and_change_in_time() -> None:
    e = env(WindSpec(speed_mps=6.0, toward_deg=0.0, gust_intensity=0.3, gust_time_constant_s=10.0))
    points = np.array([[0.0, 0.0], [500.0, 500.0]])
    first = e.wind_at(points)
    assert_allclose(first[0], first[1])
    assert_allclose(first[0], np.array([6.0, 0.0]) + e.gust)
    e.step(5.0)
    assert not np.allclose(e.wind_at(points)[0], first[0])


def gust_series(spec: WindSpec, dt_s: float, steps: int, seed: int = 1) -> np.ndarray:
    e = env(spec, seed=seed)
    out = np.empty((steps, 2))
    for k in range(steps):
        e.step(dt_s)
        out[k] = e.gust
    return out


def test_gust_stationary_std_and_autocorrelation_at_tau() -> None:
    tau, dt, speed, intensity = 5.0, 0.5, 8.0, 0.25
    sigma = intensity * speed  # 2 m/s per axis by definition
    g = gust_series(WindSpec(speed, 0.0, intensity, tau), dt, 40_000)
    # 20,000 s of record = 2,000 correlation times: the std is within ~1.5 % (1 sigma).
    assert_allclose(g.std(axis=0), [sigma, sigma], rtol=0.06)
    assert_allclose(g.mean(axis=0), [0.0, 0.0], atol=0.15 * sigma)
    lag = round(tau / dt)
    g0 = g - g.mean(axis=0)
    rho = (g0[:-lag] * g0[lag:]).sum(axis=0) / (g0 * g0).sum(axis=0)
    assert_allclose(rho, [math.exp(-1.0)] * 2, atol=0.05)
    # The axes are independent.
    assert abs(np.corrcoef(g[:, 0], g[:, 1])[0, 1]) < 0.05


def test_gust_discretization_is_exact_for_long_steps() -> None:
    # One step of a whole time constant: an exact OU step decorrelates by exp(-1);
    # an Euler step (g - g dt/tau) would decorrelate completely.
    tau, sigma = 3.0, 1.5
    g = gust_series(WindSpec(3.0, 0.0, sigma / 3.0, tau), tau, 20_000, seed=2)
    g0 = g - g.mean(axis=0)
    rho = (g0[:-1] * g0[1:]).sum(axis=0) / (g0 * g0).sum(axis=0)
    assert_allclose(rho, [math.exp(-1.0)] * 2, atol=0.03)
    assert_allclose(g.std(axis=0), [sigma, sigma], rtol=0.04)


def test_no_gusts_without_intensity_or_wind() -> None:
    assert_allclose(gust_series(WindSpec(5.0, 0.0, 0.0), 1.0, 10), 0.0)
    assert_allclose(gust_series(WindSpec(0.0, 0.0, 0.5), 1.0, 10), 0.0)


def test_gusts_are_deterministic_for_a_seed() -> None:
    spec = WindSpec(5.0, 30.0, 0.2, 8.0)
    assert_allclose(gust_series(spec, 0.1, 50, seed=7), gust_series(spec, 0.1, 50, seed=7), rtol=0, atol=0)
    assert not np.allclose(gust_series(spec, 0.1, 50, seed=7), gust_series(spec, 0.1, 50, seed=8))


def test_uniform_current() -> None:
    e = env(current=CurrentSpec(speed_mps=0.4, toward_deg=180.0))
    assert_allclose(e.current_at(np.array([[1.0, 2.0], [-9.0, 4.0]])), [[-0.4, 0.0]] * 2, atol=1e-12)


# A 3 x 2 grid (3 columns in x from 10 m, 2 rows in y from -5 m), spacing 10 m by 4 m.
GRID = CurrentGrid(
    x0_m=10.0,
    y0_m=-5.0,
    dx_m=10.0,
    dy_m=4.0,
    u_mps=((0.0, 0.2, 0.4), (0.6, 0.8, 1.0)),
    v_mps=((1.0, 0.0, -1.0), (0.0, 0.0, 0.0)),
)


def test_grid_at_nodes_returns_node_values() -> None:
    e = env(current=CurrentSpec(grid=GRID))
    nodes = np.array([[10.0, -5.0], [30.0, -5.0], [20.0, -1.0], [30.0, -1.0]])
    assert_allclose(e.current_at(nodes), [[0.0, 1.0], [0.4, -1.0], [0.8, 0.0], [1.0, 0.0]], atol=1e-12)


def test_grid_at_a_cell_centre_is_the_mean_of_its_corners() -> None:
    e = env(current=CurrentSpec(grid=GRID))
    # Cell between x 10..20, y -5..-1: corners u 0, 0.2, 0.6, 0.8 and v 1, 0, 0, 0.
    assert_allclose(e.current_at(np.array([[15.0, -3.0]])), [[0.4, 0.25]], atol=1e-12)
    # A quarter of the way in x and y in the second cell: weights by hand.
    wx, wy = 0.25, 0.25
    u = (1 - wx) * (1 - wy) * 0.2 + wx * (1 - wy) * 0.4 + (1 - wx) * wy * 0.8 + wx * wy * 1.0
    v = (1 - wx) * (1 - wy) * 0.0 + wx * (1 - wy) * -1.0
    assert_allclose(e.current_at(np.array([[22.5, -4.0]])), [[u, v]], atol=1e-12)


def test_grid_is_clamped_at_its_edges_and_added_to_the_uniform_part() -> None:
    e = env(current=CurrentSpec(speed_mps=0.1, toward_deg=90.0, grid=GRID))
    points = np.array(
        [
            [-100.0, -50.0],  # beyond the lower-left corner
            [100.0, 50.0],  # beyond the upper-right corner
            [15.0, -50.0],  # below the bottom edge, half way between two nodes
            [100.0, -3.0],  # right of the right edge, half way up
        ]
    )
    expected = np.array([[0.0, 1.0], [1.0, 0.0], [0.1, 0.5], [0.7, -0.5]]) + np.array([0.0, 0.1])
    assert_allclose(e.current_at(points), expected, atol=1e-12)


def test_single_node_grid_is_constant() -> None:
    grid = CurrentGrid(0.0, 0.0, 1.0, 1.0, u_mps=((0.3,),), v_mps=((-0.2,),))
    e = env(current=CurrentSpec(grid=grid))
    assert_allclose(e.current_at(np.array([[5.0, -5.0], [0.0, 0.0]])), [[0.3, -0.2]] * 2)


def test_invalid_specs_are_rejected() -> None:
    with pytest.raises(ValueError):
        CurrentGrid(0.0, 0.0, 1.0, 1.0, u_mps=((0.0, 1.0),), v_mps=((0.0,),))
    with pytest.raises(ValueError):
        WindSpec(gust_time_constant_s=0.0)
    with pytest.raises(ValueError):
        env().wind_at(np.zeros((3, 3)))
