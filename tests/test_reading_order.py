"""The pipelines feed a batch of readings in measurement-time order (bob_autonomy.onboard.pipeline._flatten), so that
a GPS fix delivered with the IMU reading of a later time is fused in order, not by replaying that IMU reading:
the same numbers, without the re-run."""

from __future__ import annotations

import numpy as np

from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.estimation.row_replay import _RowReplay
from bob_autonomy.onboard.pipeline import BuoyPipeline, EbotPipeline, _flatten
from firmware_bridge.readings import CompassReading, GpsFix, ImuReading

FRAME = LocalFrame(43.0, 5.0)
AGENTS = np.arange(3)


def imu(t: float) -> ImuReading:
    return ImuReading(AGENTS, np.full(3, t), np.full((3, 2), 0.05), np.full(3, 0.01))


def fix(t: float, rng: np.random.Generator) -> GpsFix:
    lat, lon = FRAME.to_geodetic(rng.normal(0.0, 1.0, 3), rng.normal(0.0, 1.0, 3))
    return GpsFix(AGENTS, np.full(3, t), lat, lon, rng.normal(0.0, 0.1, (3, 2)))


def compass(t: float) -> CompassReading:
    return CompassReading(AGENTS, np.full(3, t), np.full(3, 0.3))


def test_a_batch_is_ordered_by_time_and_a_reading_without_one_keeps_its_place() -> None:
    rng = np.random.default_rng(1)
    a, b, c = imu(1.0), fix(0.9, rng), compass(1.0)
    assert _flatten([a, b, c]) == [b, a, c]  # stable: the compass at 1.0 stays after the IMU at 1.0
    timeless = CompassReading(AGENTS, np.full(3, np.nan), np.full(3, 0.3))
    late_fix = fix(0.5, rng)
    assert _flatten([a, timeless, late_fix]) == [late_fix, a, timeless]


def test_a_late_fix_in_the_batch_gives_the_in_order_result_without_a_replay(monkeypatch) -> None:
    replays = []
    original = _RowReplay._replay
    monkeypatch.setattr(_RowReplay, "_replay", lambda self, *args: replays.append(args) or original(self, *args))
    batched, in_order = (
        BuoyPipeline(3, FRAME, np.full(3, 10.0), estimator="ekf", controller="simple") for _ in range(2)
    )
    rng_a, rng_b = np.random.default_rng(2), np.random.default_rng(2)
    for k in range(1, 40):
        t = 0.5 * k
        batched.feed([imu(t), fix(t - 0.1, rng_a), compass(t)])  # as the sensors deliver them
        for reading in (fix(t - 0.1, rng_b), imu(t), compass(t)):
            in_order.feed([reading])
    assert replays == []
    np.testing.assert_array_equal(batched.estimator.x, in_order.estimator.x)
    np.testing.assert_array_equal(batched.estimator.P, in_order.estimator.P)


def test_a_pipeline_knows_a_position_only_from_a_fix_and_a_heading_only_from_a_compass() -> None:
    """An EKF that has fused no fix estimates (0, 0) and no compass reading 0 rad, finite and unknown: a vessel must
    not step on them."""
    rng = np.random.default_rng(3)
    for estimator in ("ekf", "simple"):
        pipeline = BuoyPipeline(3, FRAME, np.full(3, 10.0), estimator=estimator, controller="simple")
        pipeline.feed([imu(1.0), imu(1.1)])
        assert not pipeline.position_known(1.1).any() and not pipeline.heading_known(1.1).any()
        pipeline.feed([fix(0.95, rng)])  # dated before the filter's first reading (the first fix's lag)
        assert pipeline.position_known(1.1).all() and not pipeline.heading_known(1.1).any()
        pipeline.feed([compass(1.1)])
        assert pipeline.heading_known(1.1).all()
    ebots = EbotPipeline(np.zeros((2, 2)), np.zeros(2), 0.1, 0.2, 1e-3, controller="simple")
    assert ebots.position_known(0.0).all() and ebots.heading_known(0.0).all()  # an eBot starts from its known pose
