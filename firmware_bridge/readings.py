"""Typed, timestamped sensor readings as the autonomy receives them.

Whether they come from MAVLink telemetry on a vessel or from the simulator's
sensor models, readings arrive in these forms: batches over agents (a vessel
has one), each row with the index of its agent and the time the measurement
was taken (s), so late and out-of-order readings can be handled by time.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


@dataclass(frozen=True, eq=False)
class GpsFix:
    """GPS fixes: agent indices (k,), measurement times t_s (k,), WGS-84 lat_deg, lon_deg (k,),
    ground velocity_mps (k, 2) east, north (None when the source has none), and the receiver's own one-sigma
    accuracies: accuracy_m (k,) horizontal, m, and speed_accuracy_mps (k,), m/s (NaN where it reported none; None
    when the source has no such field)."""

    agents: IntArray
    t_s: FloatArray
    lat_deg: FloatArray
    lon_deg: FloatArray
    velocity_mps: FloatArray | None = None
    accuracy_m: FloatArray | None = None
    speed_accuracy_mps: FloatArray | None = None


@dataclass(frozen=True, eq=False)
class CompassReading:
    """Compass headings: agent indices (k,), measurement times t_s (k,), heading_rad (k,) from east, CCW; from an
    autopilot's ATTITUDE also the hull's tilt: roll_rad (k,) right side down, pitch_rad (k,) nose up, and
    body_rates_frd_radps (k, 3), the body rates about x forward, y right, z down (rollspeed, pitchspeed,
    yawspeed), all as ATTITUDE gives them (None when the source has none)."""

    agents: IntArray
    t_s: FloatArray
    heading_rad: FloatArray
    roll_rad: FloatArray | None = None
    pitch_rad: FloatArray | None = None
    body_rates_frd_radps: FloatArray | None = None


@dataclass(frozen=True, eq=False)
class ImuReading:
    """IMU readings: agent indices (k,), measurement times t_s (k,), accel_body_mps2 (k, 2) in the body
    frame (x forward, y left), gyro_z_radps (k,) yaw rate (CCW positive). From a MAVLink IMU message also the
    rest of the body-frame reading (z up): accel_z_mps2 (k,) (+9.8 on a level hull at rest) and gyro_xy_radps
    (k, 2) about x and y, so that a tilted hull's reading can be levelled (`bob_autonomy.estimation.tilt`); None
    when the source is level by construction (the simulator's sensors)."""

    agents: IntArray
    t_s: FloatArray
    accel_body_mps2: FloatArray
    gyro_z_radps: FloatArray
    accel_z_mps2: FloatArray | None = None
    gyro_xy_radps: FloatArray | None = None


@dataclass(frozen=True, eq=False)
class EncoderReading:
    """Wheel encoders: agent indices (k,), measurement times t_s (k,), cumulative ticks (k, 2) int64 (left, right)."""

    agents: IntArray
    t_s: FloatArray
    ticks: NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class SensorReadings:
    """What one `SensorSuite.sample` call delivers; None for a sensor that delivered nothing."""

    gps: GpsFix | None = None
    compass: CompassReading | None = None
    imu: ImuReading | None = None
    encoders: EncoderReading | None = None


@dataclass(frozen=True, eq=False)
class RangeReading:
    """Range finders: agent indices (k,), reception times t_s (k,), sensor ids (k,) and distance_m (k,) in
    metres, NaN when nothing is within range (DISTANCE_SENSOR beyond its max_distance)."""

    agents: IntArray
    t_s: FloatArray
    sensor: IntArray
    distance_m: FloatArray


@dataclass(frozen=True, eq=False)
class LightReading:
    """Light sensors: agent indices (k,), reception times t_s (k,), side (k,) 0 left / 1 right, intensity (k,)
    W/m^2 (NAMED_VALUE_FLOAT "light_l" / "light_r")."""

    agents: IntArray
    t_s: FloatArray
    side: IntArray
    intensity: FloatArray


Reading = TypeVar("Reading")


def rows_of(reading: Reading, keep: NDArray[np.bool_] | IntArray) -> Reading:
    """The same kind of reading holding only the rows `keep` picks (a mask or indices) of every array field; a
    field it does not have stays None."""
    picked = {
        f.name: (value[keep] if isinstance(value, np.ndarray) else value)
        for f in dataclasses.fields(reading)
        if (value := getattr(reading, f.name)) is not None
    }
    return type(reading)(**picked)
