"""Metrics for boats that cannot stop in place (sitl.experiments.station_metrics, `average_window_s` of the
aggregation metric):
a boat circling its spot counts at the centre of its circle, and how far it wanders is reported."""

from __future__ import annotations

import numpy as np
import pytest

from sitl.experiments.recorder import Frame, Recorder
from sitl.experiments.station_metrics import time_averaged, wander_m
from sitl.experiments.swarm_metrics import aggregation_metrics, hull_area_m2

SPOTS = np.array([[0.0, 0.0], [20.0, 0.0], [20.0, 20.0], [0.0, 20.0], [10.0, 10.0]])  # hull 400 m2


def _circling(radius: float = 3.0, period_s: float = 40.0, seconds: float = 300.0, step: float = 5.0) -> Recorder:
    """Five boats each circling its spot (radius m, period s), phases spread; the last one leaves at t = 200 s."""
    frames = []
    for t in np.arange(0.0, seconds, step):
        phase = 2 * np.pi * t / period_s + np.arange(5) * 1.3
        position = SPOTS + radius * np.column_stack((np.cos(phase), np.sin(phase)))
        agents = np.arange(5) if t < 200.0 else np.arange(4)
        frames.append(Frame(t, agents, position[agents], np.zeros(agents.size), np.zeros((agents.size, 2)), []))
    return Recorder(step, ["motorboat"] * 5, frames)


def test_the_time_averaged_position_is_the_centre_of_the_circle_and_the_wander_its_radius() -> None:
    rec = _circling()
    averaged = time_averaged(rec, 40.0)  # one whole period: 8 samples of the circle
    assert averaged.frames[-1].position == pytest.approx(SPOTS[:4], abs=1e-9)
    assert hull_area_m2(averaged.frames[30].position) == pytest.approx(400.0, abs=1e-6)
    assert hull_area_m2(rec.frames[30].position) > 450.0  # the circles widen the instantaneous hull
    _, wander = wander_m(rec, 40.0)
    assert wander[-1] == pytest.approx(np.full(4, 3.0))
    assert wander[-1].size == 4  # agents that left are not averaged in
    assert time_averaged(rec, 0.0) is rec


def test_the_aggregation_metric_uses_the_window_and_says_so() -> None:
    class Fleet:
        n = 5
        events_log = ({"t_s": 50.0, "action": "set-behavior"},)

    rec = _circling(seconds=190.0)
    plain = aggregation_metrics(Fleet(), rec, {})
    averaged = aggregation_metrics(Fleet(), rec, {"average_window_s": 40.0})
    assert "average_window_s" not in plain
    assert averaged["area_aggregated_m2"] == pytest.approx(400.0, abs=1e-6)
    assert plain["area_aggregated_m2"] != pytest.approx(400.0, abs=10.0)  # the instantaneous hull has the circles
    assert averaged["area_aggregated_instant_m2"] == plain["area_aggregated_m2"]
    assert averaged["average_window_s"] == 40.0
    assert averaged["wander_rms_m_settled"] == pytest.approx(3.0, abs=0.3)
