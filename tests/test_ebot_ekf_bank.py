"""EbotEkfBank (the eBot EKFs of a fleet in arrays) against EbotEkf (one filterpy ExtendedKalmanFilter per robot),
reading by reading: the same outcomes, states, covariances and counters, over seeded random reading streams with
gyro and wheel headings, late readings replayed, wild fixes gated and reset, non-finite readings, an agent twice in
one call, and compass readings without a time."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bob_autonomy.estimation import OUTCOMES, EbotEkf, EbotEkfBank, EbotEkfParams

WHEEL_BASE_M, METRES_PER_TICK = 0.1, 2.0 * math.pi * 0.03 / 360
N = 4


class Pair:
    """A bank and its reference filters, fed the same readings; each call checks that both said the same."""

    def __init__(self, rng: np.random.Generator, params: EbotEkfParams | None = None) -> None:
        start = rng.uniform(-5.0, 5.0, (N, 2))
        heading = rng.uniform(-math.pi, math.pi, N)
        self.bank = EbotEkfBank(start, heading, WHEEL_BASE_M, METRES_PER_TICK, params)
        self.singles = [EbotEkf(start[i], heading[i], WHEEL_BASE_M, METRES_PER_TICK, params) for i in range(N)]

    def encoders(self, agents, t, ticks, gyro=None) -> None:
        codes = self.bank.update_encoders(np.array(agents), t, ticks, gyro)
        said = [
            self.singles[a].update_encoders(t[k], ticks[k], None if gyro is None else gyro[k])
            for k, a in enumerate(agents)
        ]
        assert [OUTCOMES[c] for c in codes] == said

    def compass(self, agents, heading, t=None) -> None:
        codes = self.bank.update_compass(np.array(agents), heading, t)
        said = [self.singles[a].update_compass(None if t is None else t[k], heading[k]) for k, a in enumerate(agents)]
        assert [OUTCOMES[c] for c in codes] == said

    def position(self, agents, t, xy, sigma) -> None:
        codes = self.bank.update_position(np.array(agents), t, xy, sigma)
        said = [self.singles[a].update_position(t[k], xy[k], sigma[k]) for k, a in enumerate(agents)]
        assert [OUTCOMES[c] for c in codes] == said

    def check(self) -> None:
        est = self.bank.estimate(0.0)
        assert np.all(np.abs(est.heading) <= math.pi)  # wrapped after every reading
        for i, f in enumerate(self.singles):
            pos, vel, head = f.estimate()
            np.testing.assert_allclose(est.position[i], pos, rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(est.velocity[i], vel, rtol=1e-9, atol=1e-9)
            assert abs(math.remainder(est.heading[i] - head, 2.0 * math.pi)) <= 1e-9
            np.testing.assert_allclose(self.bank.P[i], f.covariance, rtol=1e-8, atol=1e-12)
        for counter in ("rejected", "late", "gated", "resets", "failures"):
            assert getattr(self.bank, counter) == sum(getattr(f, counter) for f in self.singles), counter


def drive(pair: Pair, rng: np.random.Generator, steps: int) -> None:
    """Random driving at 10 Hz with every kind of reading, some late, wild, non-finite or repeated."""
    everyone = list(range(N))
    ticks = np.zeros((N, 2), dtype=np.int64)
    rate = rng.uniform(-60.0, 120.0, (N, 2))  # ticks per step
    for k in range(steps):
        t = 0.1 * k
        if k % 25 == 0:
            rate = rng.uniform(-60.0, 120.0, (N, 2))
        ticks = ticks + np.rint(rate + rng.normal(0.0, 3.0, (N, 2))).astype(np.int64)
        gyro = rng.normal(0.0, 0.5, N) if k % 3 else None
        pair.encoders(everyone, np.full(N, t), ticks, gyro)
        heading = rng.uniform(-math.pi, math.pi, N)
        if k % 2:
            pair.compass(everyone, heading, np.full(N, t - rng.uniform(0.0, 0.15)))  # late: replayed
        if k % 7 == 3:
            pair.compass([1, 3], heading[:2])  # at the filter's own time
        if k % 5 == 0:
            agents = list(rng.permutation(N)[:3])
            xy = pair.bank.x[agents, 0:2] + rng.normal(0.0, 0.3, (3, 2))
            if 40 <= k < 100:
                xy[0] += 200.0  # wild fixes of one agent: gated, then a reset after a run of them
            pair.position(agents, np.full(3, t - 0.05), xy, rng.uniform(0.1, 0.5, 3))
        if k % 11 == 0:
            pair.compass([2], [math.nan], [t])  # non-finite: rejected
            pair.position([0], [t], np.array([[1.0, 2.0]]), [-1.0])  # no positive sigma: rejected
            pair.encoders([3, 3], np.array([t, t]), np.array([ticks[3], ticks[3] + 5]))  # one agent twice
            ticks[3] += 5
        if k == 30:
            pair.compass([0], [0.1], [t - 5.0])  # older than the replay window: late
    pair.check()


@pytest.mark.parametrize("seed", range(5))
def test_bank_follows_the_filterpy_filters_reading_by_reading(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pair = Pair(rng)
    drive(pair, rng, 150)
    assert pair.bank.resets >= 1 and pair.bank.gated >= 10  # the wild fixes were gated, then reset
    assert pair.bank.late >= 1 and pair.bank.rejected >= 2


def test_compass_before_any_clock_fuses_into_the_start_pose_unlogged() -> None:
    rng = np.random.default_rng(7)
    pair = Pair(rng)
    pair.compass([0, 2], [0.5, math.nan])
    pair.check()
    assert np.isnan(pair.bank.t).all()  # no clock was set
    assert pair.bank.rejected == 1


def test_encoder_ticks_given_as_floats_reject_non_finite_counts() -> None:
    bank = EbotEkfBank(np.zeros((2, 2)), 0.0, WHEEL_BASE_M, METRES_PER_TICK)
    codes = bank.update_encoders(np.arange(2), 0.0, np.array([[0.0, 0.0], [math.nan, 3.0]]))
    assert [OUTCOMES[c] for c in codes] == ["init", "rejected"]
    assert bank.rejected == 1


def test_carry_moves_the_position_and_widens_its_variance() -> None:
    bank = EbotEkfBank(np.zeros((2, 2)), 0.0, WHEEL_BASE_M, METRES_PER_TICK)
    before = bank.P[1].copy()
    bank.carry(1, np.array([0.5, -0.2]), 0.04, np.array([1.0, 0.0]))
    est = bank.estimate()
    np.testing.assert_array_equal(est.position, [[0.0, 0.0], [0.5, -0.2]])
    np.testing.assert_array_equal(est.velocity[1], [1.0, 0.0])
    np.testing.assert_allclose(np.diag(bank.P[1]) - np.diag(before), [0.04, 0.04, 0.0])
