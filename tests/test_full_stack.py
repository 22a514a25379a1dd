"""The lockstep full stack: vehicles and vessels exchange real MAVLink bytes (sitl.vehicles.vehicle_transport).

The vessels decode telemetry with firmware_bridge and drive with RC_CHANNELS_OVERRIDE; the result must
match the direct hand-over of readings up to PWM quantization. (The scenario criteria are checked with the
direct link in tests/test_physics_scenarios.py, and over real processes in tests/test_process_fleet.py.)
"""

from __future__ import annotations

import numpy as np
import pytest

from sitl.experiments.runner import simulate
from sitl.experiments.scenario import load_scenario
from sitl.vehicles.sensors import CompassSpec, GpsSpec, ImuSpec


@pytest.fixture(scope="module")
def two_links() -> dict:
    runs = {}
    # The alpha-beta estimator uses the readings' times only to extrapolate, so the comparison isolates the
    # transport (the EKF also replays by time, and MAVLink readings carry their reception time).
    for link in ("direct", "mavlink"):
        scenario = load_scenario("aggregation").with_overrides(duration_s=120.0, link=link, estimator="simple")
        result = simulate(scenario)
        runs[link] = result
    return runs


def test_mavlink_link_tracks_the_direct_hand_over(two_links: dict) -> None:
    direct = two_links["direct"].fleet.bodies.position
    mavlink = two_links["mavlink"].fleet.bodies.position
    gap = np.hypot(*(direct - mavlink).T)
    # RC PWM steps are 1/400 of the thrust and readings are stamped on reception: a few decimetres after 2 min.
    assert np.median(gap) < 0.5, f"median gap {np.median(gap):.2f} m"
    assert gap.max() < 2.0, f"largest gap {gap.max():.2f} m"


def test_every_byte_went_through_firmware_bridge(two_links: dict) -> None:
    counters = two_links["mavlink"].metrics["vehicle_link"]
    dt_s = load_scenario("aggregation").dt_s
    steps = round(120.0 / dt_s) + round(2.0 / 0.1)  # the run, and the 2 s pre-roll at 0.1 s
    assert counters["vehicle_commands"] == 45 * steps  # every command arrived as RC_CHANNELS_OVERRIDE
    assert counters["vehicle_refused"] == 0 and counters["vehicle_failsafes"] == 0
    # The vessels asked for their streams as bob-autonomy does (the vehicles stream at ArduPilot's 1 Hz defaults
    # until asked). Each sensor message comes with every reading (its rate, capped by the rate asked and by one
    # reading per step: sitl/vehicles/sensors.py), over the 2 s pre-roll at 0.1 s steps and the 120 s run (+-2 per
    # buoy). GPS_RAW_INT goes at the rate asked, as ArduPilot sends it: a fix again until the next one, each copy
    # stamped with its fix's time, and read once.
    asked = {"GPS_RAW_INT": 10.0, "ATTITUDE": 20.0, "SCALED_IMU": 25.0}
    sensors = {"GPS_RAW_INT": GpsSpec(), "ATTITUDE": CompassSpec(), "SCALED_IMU": ImuSpec()}
    read = dict(
        counters, vessel_decoded_GPS_RAW_INT=counters["vessel_decoded_GPS_RAW_INT"] - counters["vessel_repeated_fix"]
    )
    for name, spec in sensors.items():
        rate = min(spec.rate_hz, asked[name])
        expected = 45 * (2.0 * min(rate, 10.0) + 120.0 * min(rate, 1.0 / dt_s))
        got = read[f"vessel_decoded_{name}"]
        assert abs(got - expected) <= 45 * 2, (name, got, expected)
    # The 5 Hz GPS at 10 Hz in the pre-roll: every fix twice; at 0.5 s steps a new fix at (nearly) every step.
    repeats = 45 * 2.0 * (asked["GPS_RAW_INT"] - GpsSpec().rate_hz)
    assert abs(counters["vessel_repeated_fix"] - repeats) <= 45 * 2, counters["vessel_repeated_fix"]
    assert abs(counters["vessel_decoded_HEARTBEAT"] - 45 * 122) <= 45 * 2
    assert counters["vessel_bad_crc"] == counters["vessel_malformed"] == 0
    assert two_links["direct"].metrics.get("vehicle_link") == {}
