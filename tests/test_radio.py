"""The radio channel (sitl/radio/channel.py): Table 1, monotonicity, range cut-off, seeding, latency, payload limit."""

from __future__ import annotations

import math
import re
import time

import numpy as np
import pytest

from sitl.radio.channel import TABLE_1, RadioChannel, measure_delivery_table, table_pairs

CHANNEL = RadioChannel()


@pytest.mark.parametrize(("swarm", "row"), list(TABLE_1.items()), ids=["N20", "N40"])
def test_measured_table_within_3_points_of_table_1(swarm: tuple[int, float], row: dict[int, float]) -> None:
    n, mean_nn_m = swarm
    start = time.perf_counter()
    measured = measure_delivery_table(CHANNEL, np.random.default_rng(2024), n, mean_nn_m, list(row), 300, 5.0)
    elapsed = time.perf_counter() - start
    assert set(measured) == {float(d) for d in row}
    off = {d: round(100 * (measured[float(d)] - paper), 2) for d, paper in row.items()}
    assert all(abs(pp) <= 3.0 for pp in off.values()), f"measured minus Table 1, percentage points: {off}"
    assert elapsed < 1.5, f"table measurement took {elapsed:.2f} s"


def test_compact_swarm_listeners_hear_all_other_transmitters_and_probes_sit_in_their_bins() -> None:
    # 40 buoys 6.9 m apart span ~50 m: every listener, even a probe 160 m out, has the other N - 2 in range.
    distances = [10.0, 160.0]
    chunks = list(table_pairs(300.0, np.random.default_rng(3), 40, 6.9, distances, 50, 5.0))
    distance = np.concatenate([c[0] for c in chunks])
    interferers = np.concatenate([c[1] for c in chunks])
    assert np.all(interferers == 38)
    assert np.all(np.min(np.abs(distance[:, None] - distances), axis=1) <= 5.0)
    assert np.sum(np.abs(distance - 160.0) <= 5.0) == 50 * 40  # one probe per sender per round, no swarm pair
    # Only the nominal range limits the count: with a 20 m radio most of the swarm is out of reach.
    short = np.concatenate([c[1] for c in table_pairs(20.0, np.random.default_rng(3), 40, 6.9, [10.0], 20, 5.0)])
    assert short.max() < 38 and short.min() >= 0


def test_delivery_falls_with_distance() -> None:
    d = np.linspace(0.0, CHANNEL.nominal_range_m, 601)
    for k in (0, 5, 18, 38, 100):
        p = CHANNEL.delivery_probability(d, np.full(d.size, k))
        assert np.all(np.diff(p) <= 0), f"delivery rises with distance at k={k}"
        assert p[20] - p[-1] > 0.05, f"delivery barely falls with distance at k={k}: {p[20]:.3f} -> {p[-1]:.3f}"


def test_delivery_falls_with_interferers() -> None:
    k = np.linspace(0.0, 200.0, 401)  # float counts allowed
    for d in (1.0, 10.0, 80.0, 160.0, 299.0):
        p = CHANNEL.delivery_probability(np.full(k.size, d), k)
        assert np.all(np.diff(p) < 0), f"delivery does not fall with interferers at d={d}"
    grid = CHANNEL.delivery_probability(np.array([[10.0], [160.0]]), np.array([[18.0, 38.0]]))  # broadcasts
    assert grid.shape == (2, 2) and grid[0, 0] > grid[0, 1] > grid[1, 1] and grid[0, 0] > grid[1, 0] > grid[1, 1]


def test_nothing_delivered_beyond_nominal_range() -> None:
    r = CHANNEL.nominal_range_m
    d = np.array([r * (1 + 1e-9), r + 1.0, 2 * r, 1e5])
    assert np.all(CHANNEL.delivery_probability(d, np.zeros(d.size)) == 0.0)
    assert CHANNEL.delivery_probability(r, 0.0) > 0.5  # the cut-off is at the range, not before it
    mask = CHANNEL.deliver(np.random.default_rng(0), np.full(10_000, r + 0.5), np.zeros(10_000))
    assert not mask.any()
    assert not measure_delivery_table(CHANNEL, np.random.default_rng(0), 20, 19.5, [400.0], 20, 5.0)[400.0]


def test_deliver_is_reproducible_for_a_seed_and_matches_the_probability() -> None:
    rng = np.random.default_rng(11)
    n = 200_000
    distance = rng.uniform(0.0, 350.0, n)
    interferers = rng.integers(0, 60, n).astype(float)
    first = CHANNEL.deliver(np.random.default_rng(5), distance, interferers)
    second = CHANNEL.deliver(np.random.default_rng(5), distance, interferers)
    other = CHANNEL.deliver(np.random.default_rng(6), distance, interferers)
    assert first.dtype == np.bool_ and first.shape == (n,)
    assert np.array_equal(first, second)
    assert not np.array_equal(first, other)
    p = CHANNEL.delivery_probability(distance, interferers)
    tolerance = 5 * math.sqrt(np.sum(p * (1 - p))) / n  # 5 standard errors of the delivered fraction
    assert abs(first.mean() - p.mean()) <= tolerance
    table = [measure_delivery_table(CHANNEL, np.random.default_rng(9), 20, 19.5, [10.0, 80.0], 30, 5.0) for _ in "ab"]
    assert table[0] == table[1]


@pytest.mark.parametrize(("mean_s", "jitter_s"), [(0.02, 0.01), (0.5, 0.4), (0.02, 0.0)])
def test_latency_is_non_negative_with_the_configured_mean(mean_s: float, jitter_s: float) -> None:
    channel = RadioChannel(latency_mean_s=mean_s, latency_jitter_s=jitter_s)
    n = 100_000
    latency = channel.latency(np.random.default_rng(1), n)
    assert latency.shape == (n,) and np.all(latency >= 0)
    tolerance = 5 * jitter_s / math.sqrt(n) + 1e-12  # 5 standard errors of the sample mean
    assert abs(latency.mean() - mean_s) <= tolerance
    assert latency.std() == pytest.approx(jitter_s, rel=0.05, abs=1e-12)
    assert channel.latency(np.random.default_rng(1), 0).shape == (0,)


def test_check_payload_names_the_size_and_the_limit() -> None:
    CHANNEL.check_payload(CHANNEL.payload_limit_bytes)  # at the limit: fine
    with pytest.raises(ValueError, match=r"\b101\b.*\b100\b") as error:
        CHANNEL.check_payload(101)
    assert re.search(r"\bbytes\b", str(error.value))
    with pytest.raises(ValueError, match=r"\b64\b.*\b48\b"):
        RadioChannel(payload_limit_bytes=48).check_payload(64)


def test_invalid_parameters_and_inputs_are_refused() -> None:
    with pytest.raises(ValueError, match="collision_probability"):
        RadioChannel(collision_probability=1.0)
    with pytest.raises(ValueError, match="shadowing_db"):
        RadioChannel(shadowing_db=0.0)
    with pytest.raises(ValueError, match="interferer"):
        CHANNEL.delivery_probability(np.array([10.0]), np.array([-1.0]))
    with pytest.raises(ValueError, match="at least 2"):
        measure_delivery_table(CHANNEL, np.random.default_rng(0), 1, 5.0, [10.0], 10, 5.0)
