"""bob_autonomy/onboard/imu_repeats.py: an IMU sample that arrives twice (RAW_IMU and SCALED_IMU of one pass of
the autopilot's update_send) is fused once; a new sample, even with the same values 20 ms later, is fused."""

from __future__ import annotations

import numpy as np

from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.onboard.imu_repeats import ImuRepeats
from bob_autonomy.onboard.pipeline import BuoyPipeline
from firmware_bridge.readings import CompassReading, GpsFix, ImuReading


def imu(agents, t_s, accel, gyro, accel_z=None, gyro_xy=None) -> ImuReading:
    def array(values):
        return None if values is None else np.asarray(values, dtype=float)

    return ImuReading(
        np.asarray(agents), np.asarray(t_s, dtype=float), array(accel), array(gyro), array(accel_z), array(gyro_xy)
    )


def test_a_repeat_within_one_loop_is_dropped_and_a_new_sample_kept() -> None:
    repeats = ImuRepeats(3)
    first = imu([0, 1, 2], [1.0, 1.0, 1.0], [[0.1, 0.2], [0.0, 0.0], [0.3, 0.0]], [0.01, 0.0, 0.02])
    assert repeats.fresh(first) is first
    again = imu(
        [0, 1, 2],
        [1.0, 1.003, 1.02],  # the same values: same time, placed 3 ms apart, 20 ms later (a sample of its own)
        [[0.1, 0.2], [0.0, 0.0], [0.3, 0.0]],
        [0.01, 0.0, 0.02],
    )
    kept = repeats.fresh(again)
    assert kept.agents.tolist() == [2] and kept.t_s.tolist() == [1.02]
    assert repeats.dropped == 2
    other = imu([0], [1.0], [[0.1, 0.25]], [0.01])  # another value at the same time: a sample of its own
    assert repeats.fresh(other) is other
    assert repeats.fresh(imu([1], [1.0], [[0.0, 0.0]], [0.0])) is None and repeats.dropped == 3


def test_the_optional_fields_count_and_an_agent_twice_in_one_reading() -> None:
    repeats = ImuRepeats(2)
    tilted = imu([0, 0], [2.0, 2.0], [[0.1, 0.0], [0.1, 0.0]], [0.0, 0.0], [9.8, 9.8], [[0.0, 0.01], [0.0, 0.01]])
    kept = repeats.fresh(tilted)
    assert kept.agents.tolist() == [0] and kept.accel_z_mps2.tolist() == [9.8] and repeats.dropped == 1
    level = imu([0], [2.0], [[0.1, 0.0]], [0.0])  # no z and no x, y rates: not the tilted sample
    assert repeats.fresh(level) is level


def _pipeline() -> BuoyPipeline:
    return BuoyPipeline(2, LocalFrame(1.3, 103.8), np.array([45.0, 45.0]), estimator="ekf", controller="simple")


def test_the_estimator_fuses_a_sample_sent_twice_once() -> None:
    once, twice = _pipeline(), _pipeline()
    start = [
        GpsFix(np.array([0, 1]), np.array([0.0, 0.0]), np.array([1.3, 1.3001]), np.array([103.8, 103.8]),
               np.zeros((2, 2))),
        CompassReading(np.array([0, 1]), np.array([0.0, 0.0]), np.array([0.3, -0.2])),
    ]  # fmt: skip
    for pipeline in (once, twice):
        pipeline.feed(start)
    rng = np.random.default_rng(1)
    for step in range(1, 20):
        t = 0.1 * step
        sample = imu([0, 1], [t, t], rng.normal(0.0, 0.2, (2, 2)), rng.normal(0.0, 0.05, 2))
        once.feed([sample])
        twice.feed([sample, sample])  # SCALED_IMU and RAW_IMU of one loop
    np.testing.assert_array_equal(once.estimator.x, twice.estimator.x)
    np.testing.assert_array_equal(once.estimator.P, twice.estimator.P)
    assert twice.imu_repeats.dropped == 2 * 19 and once.imu_repeats.dropped == 0
