"""How the simulated sensors' readings become a simulated vehicle's telemetry (lockstep transport and UDP vehicle
server alike): each reading is handed to its vehicle (`SimulatedVehicle.observe`), which sends it as its streams
say (sitl/vehicles/mavlink_vehicle.py)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from firmware_bridge.readings import SensorReadings

if TYPE_CHECKING:
    from sitl.vehicles.mavlink_vehicle import SimulatedVehicle


def encode_readings(
    readings: SensorReadings,
    t_s: float,
    vehicles: Sequence[SimulatedVehicle],
    frames: list[bytearray],
    rows: Sequence[int] | None = None,
    *,
    metres_per_tick: float = 1.0,
    fused_position: bool = False,
) -> None:
    """Give each vehicle its readings; with "sensor-rate" streams also append to frames[row] each reading's message
    at once (SCALED_IMU, GPS_RAW_INT and, when `fused_position`, GLOBAL_POSITION_INT for ground stations,
    ATTITUDE, WHEEL_DISTANCE of ticks * metres_per_tick). A reading's agent k is vehicle rows[k] (rows None: k
    itself). Then call `prepend_streams` once: the vehicles' streams send what is due, this step's readings among
    it (before, the streams ran first, and a message due then went out with the last step's reading: GPS_RAW_INT,
    which ArduPilot repeats at its interval, would wait a whole step for the new fix)."""

    def vehicle_rows(agents):
        return [(i, int(k) if rows is None else int(rows[k])) for i, k in enumerate(agents)]

    def direct(row: int) -> bool:
        return vehicles[row].streams == "sensor-rate"

    # Each array converted to Python numbers once (`_floats`, `tolist`), not element by element.
    if readings.imu is not None:
        r = readings.imu
        tilted = r.accel_z_mps2 is not None and r.gyro_xy_radps is not None
        accel, gyro_z = r.accel_body_mps2.tolist(), _floats(r.gyro_z_radps)
        accel_z, gyro_xy = (_floats(r.accel_z_mps2), r.gyro_xy_radps.tolist()) if tilted else (None, None)
        for i, row in vehicle_rows(r.agents):
            extra = (accel_z[i], tuple(gyro_xy[i])) if tilted else ()
            vehicles[row].observe("imu", t_s, tuple(accel[i]), gyro_z[i], *extra)
            if direct(row):
                more = {"accel_z_mps2": extra[0], "gyro_xy_radps": extra[1]} if tilted else {}
                frames[row] += vehicles[row].telemetry.scaled_imu(t_s, r.accel_body_mps2[i], r.gyro_z_radps[i], **more)
    if readings.compass is not None:
        c = readings.compass
        tilted = c.roll_rad is not None and c.pitch_rad is not None and c.body_rates_frd_radps is not None
        heading = _floats(c.heading_rad)
        if tilted:
            roll, pitch, rates = _floats(c.roll_rad), _floats(c.pitch_rad), c.body_rates_frd_radps.tolist()
        for i, row in vehicle_rows(c.agents):
            extra = (roll[i], pitch[i], tuple(rates[i])) if tilted else ()
            vehicles[row].observe("compass", t_s, heading[i], *extra)
    if readings.gps is not None:
        g = readings.gps
        lat, lon = _floats(g.lat_deg), _floats(g.lon_deg)
        velocities = None if g.velocity_mps is None else g.velocity_mps.tolist()
        h_acc, speed_acc = _reported(g.accuracy_m, len(lat)), _reported(g.speed_accuracy_mps, len(lat))
        for i, row in vehicle_rows(g.agents):
            velocity = None if velocities is None else tuple(map(float, velocities[i]))
            accuracy = (h_acc[i], speed_acc[i])
            vehicle = vehicles[row]
            vehicle.observe("gps", t_s, lat[i], lon[i], velocity, *accuracy)
            if direct(row):
                frames[row] += vehicle.telemetry.gps_raw_int(
                    t_s, g.lat_deg[i], g.lon_deg[i], velocity, h_acc_m=accuracy[0], vel_acc_mps=accuracy[1]
                )
                if fused_position:
                    heading = vehicle.heading()
                    frames[row] += vehicle.telemetry.global_position_int(
                        t_s, g.lat_deg[i], g.lon_deg[i], velocity, heading
                    )
    if readings.compass is not None:
        c = readings.compass
        tilted = c.roll_rad is not None and c.pitch_rad is not None and c.body_rates_frd_radps is not None
        for i, row in vehicle_rows(c.agents):
            if direct(row):
                more = {}
                if tilted:
                    p, q, r = c.body_rates_frd_radps[i].tolist()
                    more = {"roll_rad": c.roll_rad[i], "pitch_rad": c.pitch_rad[i], "roll_pitch_rates_radps": (p, q)}
                    more["yaw_rate_radps"] = -r
                frames[row] += vehicles[row].telemetry.attitude(t_s, c.heading_rad[i], **more)
    if readings.encoders is not None:
        e = readings.encoders
        for i, row in vehicle_rows(e.agents):
            distances = tuple(float(x) * metres_per_tick for x in e.ticks[i])
            vehicles[row].observe("wheels", t_s, distances)
            if direct(row):
                frames[row] += vehicles[row].telemetry.wheel_distance(t_s, distances)


def _floats(values: np.ndarray) -> list[float]:
    """A 1-d array's values as Python floats (what float() of each element gives)."""
    return list(map(float, values.tolist()))


def _reported(values: np.ndarray | None, n: int) -> list[float | None]:
    """A receiver's reported accuracy of each of n rows (None: it reports none, or not a finite number)."""
    if values is None:
        return [None] * n
    return [v if math.isfinite(v) else None for v in _floats(values)]


def prepend_streams(t_s: float, vehicles: Sequence[SimulatedVehicle], frames: list[bytearray]) -> None:
    """Put in front of frames[k] what vehicle k's streams send at t_s (`housekeeping`): once its readings of the
    step are in (`encode_readings`), so a message due now carries the newest reading, and before the step's
    sensor-rate frames, as a vehicle sends them."""
    for vehicle, data in zip(vehicles, frames, strict=True):
        data[:0] = vehicle.housekeeping(t_s)


def encode_senses(
    t_s: float,
    vehicles: Sequence[SimulatedVehicle],
    frames: list[bytearray],
    rows: Sequence[int],
    ranges_m: np.ndarray,
    light: np.ndarray,
    max_range_m: float,
) -> None:
    """Give eBot k (vehicle rows[k]) its range finders' and light sensors' readings and append what it sends:
    DISTANCE_SENSOR per sonar (id = sonar index) and the two light readings as NAMED_VALUE_FLOAT; ranges_m (k,
    sonars) m, NaN = no echo; light (k, 2) W/m^2. "sensor-rate": every reading; "ardupilot": DISTANCE_SENSOR at
    its EXTRA3 interval, light with every reading (a script's NAMED_VALUE_FLOAT has no stream)."""
    for k, row in enumerate(rows):
        vehicle = vehicles[row]
        vehicle.observe("ranges", t_s, tuple(float(d) for d in ranges_m[k]), float(max_range_m))
        vehicle.observe("light", t_s, float(light[k, 0]), float(light[k, 1]))
        if vehicle.streams == "ardupilot":
            frames[row] += vehicle.stream(t_s)
            continue
        telemetry = vehicle.telemetry
        for sonar, distance in enumerate(ranges_m[k]):
            frames[row] += telemetry.distance_sensor(t_s, sonar, float(distance), max_range_m)
        frames[row] += telemetry.light(t_s, float(light[k, 0]), float(light[k, 1]))
