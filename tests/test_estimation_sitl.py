"""The buoy EKF in the simulated loop, measured against the simulator's truth (issue: state estimation)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import fsolve

from sitl.dynamics import BuoyParams
from sitl.runner import simulate
from sitl.scenario import validate_scenario

GPS_NOISE_M = 2.0  # per axis, white: raw GPS error RMS = 2 * sqrt(2) = 2.83 m
WIND = {"speed_mps": 5.0, "toward_deg": 60.0}
CURRENT = {"speed_mps": 0.1, "toward_deg": 180.0}


def scenario(estimator: str, behavior: dict) -> dict:
    return {
        "name": f"ekf-{estimator}",
        "duration_s": 120.0,
        "dt_s": 0.2,
        "seed": 12,
        "log_period_s": 1.0,
        "fidelity": "physics",
        "vessel": {"estimator": estimator},
        "environment": {"wind": WIND, "current": CURRENT},
        "sensors": {"gps": {"noise_m": GPS_NOISE_M}},
        "groups": [
            {
                "name": "buoys",
                "count": 3,
                "body": "buoy",
                "start": {"box": {"min": [0.0, 0.0], "max": [50.0, 50.0]}, "min_separation_m": 10.0},
                **behavior,
            }
        ],
    }


@pytest.fixture(scope="module")
def survey_run():
    behavior = {"behavior": "waypoints", "params": {"waypoints": [[200.0, 100.0], [0.0, 200.0]], "speed": 0.4}}
    return simulate(validate_scenario(scenario("ekf", behavior), "test"))


def test_ekf_position_error_is_at_most_half_the_raw_gps_error(survey_run) -> None:
    raw_rms = GPS_NOISE_M * math.sqrt(2.0)
    estimation = survey_run.metrics["estimation"]["buoy"]
    assert estimation["position_rms_m"] <= 0.5 * raw_rms, estimation


def test_ekf_heading_error_under_three_degrees(survey_run) -> None:
    assert survey_run.metrics["estimation"]["buoy"]["heading_rms_deg"] < 3.0


def equivalent_drift_mps() -> np.ndarray:
    """The drift the EKF's model should find for a buoy holding station: the water velocity d whose nominal drag
    D(d) equals the force the buoy really feels at rest, water drag D(w) plus windage on the hull.

    Water w = current + 3 % of the wind; about (0.061, 0.229) m/s here (w itself is (-0.025, 0.130)).
    """
    params = BuoyParams()
    wind = WIND["speed_mps"] * np.array([math.cos(math.radians(60.0)), math.sin(math.radians(60.0))])
    water = np.array([-CURRENT["speed_mps"], 0.0]) + params.wind_drift_factor * wind

    def drag(v: np.ndarray) -> np.ndarray:
        return (params.linear_drag_n_per_mps + params.quadratic_drag_n_per_mps2 * np.hypot(*v)) * v

    felt = drag(water) + params.air_drag_n_per_mps2 * np.hypot(*wind) * wind
    return fsolve(lambda d: drag(d) - felt, water)


@pytest.mark.xfail(
    strict=True,
    reason="measured 0.03 to 0.075 m/s per buoy after 120-240 s (biases removed: still ~0.05): the EKF's "
    "drift absorbs the unmodelled windage and the quadratic drag makes that operating-point dependent",
)
def test_ekf_drift_estimate_after_a_minute_of_steady_wind_and_current() -> None:
    run = simulate(validate_scenario(scenario("ekf", {"behavior": "hold-position"}), "test"))
    drift = run.fleet.bodies.buoy_estimator.drift()
    expected = equivalent_drift_mps()
    assert np.abs(drift - expected).max() < 0.05, (drift, expected)


def test_the_simple_estimator_is_worse_than_the_ekf(survey_run) -> None:
    behavior = {"behavior": "waypoints", "params": {"waypoints": [[200.0, 100.0], [0.0, 200.0]], "speed": 0.4}}
    simple = simulate(validate_scenario(scenario("simple", behavior), "test")).metrics["estimation"]["buoy"]
    assert survey_run.metrics["estimation"]["buoy"]["position_rms_m"] < simple["position_rms_m"]
