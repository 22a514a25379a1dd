"""A rolling, pitching hull: its IMU levelled with the autopilot's attitude (bob_autonomy.estimation.tilt) and its
GPS fixes moved from the antenna to the IMU (bob_autonomy.estimation.antenna): the geometry against scipy's
rotations, the tracker's bookkeeping, MAVLink bytes through both decoders, and a buoy's EKF on a rolling sea
against truth."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from scipy.spatial.transform import Rotation

from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.estimation.antenna import antenna_offsets
from bob_autonomy.estimation.tilt import TiltTracker, euler_rates, level_imu
from bob_autonomy.onboard.pipeline import BuoyPipeline
from firmware_bridge.batch_decoder import decode_batch
from firmware_bridge.decoder import STANDARD_GRAVITY_MPS2, TelemetryDecoder
from firmware_bridge.readings import CompassReading, GpsFix, ImuReading

G = STANDARD_GRAVITY_MPS2
NED_GRAVITY = np.array([0.0, 0.0, G])


def _rotation(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> Rotation:
    """Body (FRD) to NED: yaw about z, then pitch about the new y, then roll about the new x (aerospace order)."""
    return Rotation.from_euler("ZYX", np.column_stack((yaw, pitch, roll)))


def _specific_force_flu(rotation: Rotation, accel_ned: np.ndarray) -> np.ndarray:
    """What an accelerometer reads (x forward, y left, z up) on a hull accelerating at accel_ned (k, 3)."""
    frd = rotation.inv().apply(accel_ned - NED_GRAVITY)
    return frd * np.array([1.0, -1.0, -1.0])


@pytest.mark.parametrize("seed", range(5))
def test_levelling_recovers_the_hulls_horizontal_acceleration_at_any_attitude(seed: int) -> None:
    """f = R^T (a - g) built with scipy for random attitudes (roll, pitch up to 60 deg) and accelerations (heave
    too); levelled, it is a's horizontal part in the frame that yaws with the hull, to rounding."""
    rng = np.random.default_rng(seed)
    k = 400
    yaw, pitch, roll = rng.uniform(-np.pi, np.pi, k), rng.uniform(-1.05, 1.05, k), rng.uniform(-1.05, 1.05, k)
    accel_ned = rng.normal(0.0, 2.0, (k, 3))
    rotation = _rotation(yaw, pitch, roll)
    level, _ = level_imu(_specific_force_flu(rotation, accel_ned), np.zeros((k, 3)), roll, pitch)
    heading_frame = _rotation(yaw, np.zeros(k), np.zeros(k)).inv().apply(accel_ned)  # forward, right, down
    np.testing.assert_allclose(level, heading_frame[:, :2] * np.array([1.0, -1.0]), atol=1e-12)
    unlevelled = _specific_force_flu(rotation, accel_ned)[:, :2]
    assert np.max(np.abs(unlevelled - level)) > 5.0  # gravity in the planar reading: what levelling removes


@pytest.mark.parametrize("seed", range(5))
def test_yaw_rate_and_the_rates_of_roll_and_pitch_follow_from_the_body_rates(seed: int) -> None:
    """Body rates taken from two scipy rotations 2 us apart (R^T dR/dt); the yaw rate from `level_imu` and the
    rates of roll, pitch and heading from `euler_rates` match the Euler angles' own differences."""
    rng = np.random.default_rng(seed)
    k, h = 200, 1e-6
    angles = np.column_stack((rng.uniform(-3, 3, k), rng.uniform(-1.0, 1.0, k), rng.uniform(-1.0, 1.0, k)))
    rates = rng.normal(0.0, 0.8, (k, 3))  # d/dt of yaw, pitch, roll
    before = Rotation.from_euler("ZYX", angles - rates * h)
    after = Rotation.from_euler("ZYX", angles + rates * h)
    body_frd = (before.inv() * after).as_rotvec() / (2 * h)
    _, pitch, roll = angles.T
    gyro_flu = body_frd * np.array([1.0, -1.0, -1.0])
    _, yaw_rate = level_imu(np.zeros((k, 3)), gyro_flu, roll, pitch)
    np.testing.assert_allclose(yaw_rate, -rates[:, 0], atol=1e-6)  # counter-clockwise: minus NED's yaw rate
    np.testing.assert_allclose(euler_rates(roll, pitch, body_frd), rates[:, [2, 1, 0]] * [1, 1, -1], atol=1e-6)


def _imu(rows, t, accel_flu, gyro_flu) -> ImuReading:
    accel_flu, gyro_flu = np.atleast_2d(accel_flu), np.atleast_2d(gyro_flu)
    return ImuReading(np.asarray(rows), np.asarray(t, dtype=float), accel_flu[:, :2].copy(), gyro_flu[:, 2].copy(),
                      accel_flu[:, 2].copy(), gyro_flu[:, :2].copy())  # fmt: skip


def _attitude(rows, t, roll, pitch, body_frd=None) -> CompassReading:
    k = len(rows)
    body = np.zeros((k, 3)) if body_frd is None else np.atleast_2d(body_frd)
    return CompassReading(np.asarray(rows), np.asarray(t, dtype=float), np.zeros(k), np.asarray(roll, dtype=float),
                          np.asarray(pitch, dtype=float), body)  # fmt: skip


def test_the_tracker_levels_with_each_rows_newest_attitude_carried_to_the_readings_time() -> None:
    """Row 0 rolls at 0.3 rad/s: its attitude at t = 1.0 s, carried 0.1 s on, levels the reading of t = 1.1 s
    exactly; row 1's second attitude of one reading wins over its first; row 2 has none (used as it came,
    counted); an older attitude does not replace a newer one; a level hull's reading is left as it is."""
    tracker = TiltTracker(3)
    tracker.note(_attitude([0, 1, 1], [1.0, 1.0, 1.05], [0.2, 0.5, 0.1], [0.0, 0.0, -0.05],
                           [[0.3, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]))  # fmt: skip
    tracker.note(_attitude([1], [0.9], [0.7], [0.7]))  # older: ignored
    roll_then = 0.2 + 0.3 * 0.1
    truth = np.array([[0.4, -0.2, 0.0]])  # NED: forward 0.4 m/s^2, 0.2 to the left
    f0 = _specific_force_flu(_rotation(np.zeros(1), np.zeros(1), np.array([roll_then])), truth)
    f1 = _specific_force_flu(_rotation(np.zeros(1), np.array([-0.05]), np.array([0.1])), truth)
    f2 = np.array([[0.1, 0.2, G]])
    out = tracker.level(_imu([0, 1, 2], [1.1, 1.1, 1.1], np.vstack((f0, f1, f2)), np.zeros((3, 3))))
    np.testing.assert_allclose(out.accel_body_mps2[:2], [[0.4, 0.2], [0.4, 0.2]], atol=1e-12)
    assert np.array_equal(out.accel_body_mps2[2], f2[0, :2])
    assert tracker.levelled == 2 and tracker.unlevelled == 1
    flat = TiltTracker(1)
    flat.note(_attitude([0], [2.0], [0.0], [0.0], [[0.0, 0.0, 0.3]]))  # turning, not tilting
    reading = _imu([0], [2.0], [[0.1, -0.2, G]], [[0.0, 0.0, 0.3]])
    assert flat.level(reading) is reading
    stale = TiltTracker(1)
    stale.note(_attitude([0], [1.0], [0.3], [0.0]))
    assert stale.level(reading) is reading and stale.unlevelled == 1  # 1 s apart: too old to use


def test_attitude_and_the_whole_imu_come_through_both_decoders_from_pymavlink_frames() -> None:
    """Frames packed by pymavlink as ArduPilot sends them (ATTITUDE: roll, pitch, rates; SCALED_IMU and RAW_IMU:
    mG and mrad/s, FRD) read by `feed` and by the batch decoder alike, in our frame (x forward, y left, z up)."""
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    frames = (
        mav.attitude_encode(1000, 0.1, -0.2, 0.3, 0.01, -0.02, 0.03).pack(mav)
        + mav.scaled_imu_encode(1010, 170, -340, -985, 12, -24, 36, 0, 0, 0).pack(mav)
        + mav.raw_imu_encode(1020000, 171, -341, -986, 13, -25, 37, 0, 0, 0, 0, 0).pack(mav)
    )
    g = G / 1000.0
    for batched in (False, True):
        decoder = TelemetryDecoder(lambda: 5.0, agent=0, source_system=1, source_component=1)
        if batched:
            result = decode_batch([decoder], [frames])
            assert result is not None
            rows, columns = result
            readings = [columns.take(r.key, [r.index]) for r in rows[0]]
        else:
            readings = decoder.feed(frames)
        attitude, scaled, raw = readings
        assert attitude.roll_rad[0] == np.float32(0.1) and attitude.pitch_rad[0] == np.float32(-0.2)
        np.testing.assert_array_equal(attitude.body_rates_frd_radps, np.float32([[0.01, -0.02, 0.03]]))
        for reading, (ax, ay, az, gx, gy, gz) in ((scaled, (170, -340, -985, 12, -24, 36)),
                                                  (raw, (171, -341, -986, 13, -25, 37))):  # fmt: skip
            np.testing.assert_array_equal(reading.accel_body_mps2, [[ax * g, -ay * g]])
            np.testing.assert_array_equal(reading.accel_z_mps2, [-az * g])
            np.testing.assert_array_equal(reading.gyro_xy_radps, [[gx / 1000.0, -gy / 1000.0]])
            np.testing.assert_array_equal(reading.gyro_z_radps, [-gz / 1000.0])


ORIGIN = LocalFrame(1.3405, 103.956)


def _rolling_sea_readings(
    seed: int, duration_s: float, *, attitude: bool, antenna_frd_m=(0.0, 0.0, 0.0), gps_sigma=(2.0, 0.1)
) -> list[list[object]]:
    """A buoy held still (no thrust, still water) while waves roll it up to 9 deg and pitch it up to 7 deg (periods
    5.3 and 7.1 s); per 0.04 s: its IMU (25 Hz; 0.03 m/s^2 and 0.002 rad/s noise), its ATTITUDE every 0.1 s
    (0.3 deg noise, heading 30 deg; with the tilt only when `attitude`), its GPS every 0.2 s (gps_sigma: m, m/s)
    from an antenna at antenna_frd_m (x forward, y right, z down) from the IMU."""
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 2 * np.pi, 2)
    yaw = math.radians(60.0)  # NED: heading 30 deg from east, counter-clockwise
    w_roll, w_pitch = 2 * np.pi / 5.3, 2 * np.pi / 7.1
    batches = []
    for i in range(round(duration_s / 0.04)):
        t = 0.04 * (i + 1)
        roll, pitch = (
            math.radians(9) * math.sin(w_roll * t + phase[0]),
            math.radians(7) * math.sin(w_pitch * t + phase[1]),
        )
        roll_rate = math.radians(9) * w_roll * math.cos(w_roll * t + phase[0])
        pitch_rate = math.radians(7) * w_pitch * math.cos(w_pitch * t + phase[1])
        body = np.array([[roll_rate, pitch_rate * math.cos(roll), -pitch_rate * math.sin(roll)]])  # yaw rate 0
        f = _specific_force_flu(_rotation(np.array([yaw]), np.array([pitch]), np.array([roll])), np.zeros((1, 3)))
        f = f + rng.normal(0.0, 0.03, (1, 3))
        gyro = body * np.array([1.0, -1.0, -1.0]) + rng.normal(0.0, 0.002, (1, 3))
        batch: list[object] = [_imu([0], [t], f, gyro)]
        if i % 5 == 4:  # ArduPilot's AHRS: about 0.3 deg
            noisy = rng.normal(0.0, math.radians(0.3), 2)
            heading = np.array([math.pi / 2 - yaw])
            tilt = (np.array([roll + noisy[0]]), np.array([pitch + noisy[1]]), body) if attitude else (None,) * 3
            batch.append(CompassReading(np.array([0]), np.array([t]), heading, *tilt))
        if i % 5 == 2:
            rotation = _rotation(np.array([yaw]), np.array([pitch]), np.array([roll]))
            antenna = rotation.apply(np.atleast_2d(antenna_frd_m))[0]  # north, east, down
            swing = rotation.apply(np.cross(body, np.atleast_2d(antenna_frd_m)))[0]
            x, y = antenna[1] + rng.normal(0.0, gps_sigma[0]), antenna[0] + rng.normal(0.0, gps_sigma[0])
            lat, lon = ORIGIN.to_geodetic(x, y)
            velocity = np.array([[swing[1], swing[0]]]) + rng.normal(0, gps_sigma[1], (1, 2))
            batch.append(GpsFix(np.array([0]), np.array([t]), np.atleast_1d(lat), np.atleast_1d(lon), velocity))
        batches.append(batch)
    return batches


def _velocity_rms(seed: int, attitude: bool, antenna=None, told=False, gps_sigma=(2.0, 0.1)) -> tuple[float, float]:
    """RMS speed (m/s) and distance (m) of the EKF's estimate from the still truth after the first 10 s of 28: the
    antenna at `antenna` (FRD m; None: at the IMU), the pipeline `told` where it is or not."""
    pipeline = BuoyPipeline(1, ORIGIN, np.array([45.0]), estimator="ekf", controller="simple")
    if told:
        pipeline.antenna_frd_m[:] = antenna
    speeds, distances = [], []
    where = (0.0, 0.0, 0.0) if antenna is None else antenna
    readings = _rolling_sea_readings(seed, 28.0, attitude=attitude, antenna_frd_m=where, gps_sigma=gps_sigma)
    for i, batch in enumerate(readings):
        pipeline.feed(batch)
        t = 0.04 * (i + 1)
        if t > 10.0:
            e = pipeline.estimate(t)
            speeds.append(float(np.hypot(*e.velocity[0])))
            distances.append(float(np.hypot(*e.position[0])))
    return float(np.sqrt(np.mean(np.square(speeds)))), float(np.sqrt(np.mean(np.square(distances))))


@pytest.mark.parametrize("seed", range(5))
def test_a_buoy_rolling_in_waves_keeps_a_still_estimate_once_its_imu_is_levelled(seed: int) -> None:
    """A still buoy rolled and pitched by waves: with the attitude its EKF's speed stays within a few cm/s of
    zero; without it (the planar accelerometer read as the hull's acceleration) it is several times worse."""
    speed, distance = _velocity_rms(seed, attitude=True)
    speed_flat, distance_flat = _velocity_rms(seed, attitude=False)
    print(f"seed {seed}: levelled {speed:.3f} m/s {distance:.2f} m; not {speed_flat:.3f} m/s {distance_flat:.2f} m")
    assert speed < 0.08 and distance < 1.5
    assert speed_flat > 3 * speed


@pytest.mark.parametrize("seed", range(5))
def test_antenna_offsets_are_scipys_rotation_of_the_lever_arm_and_its_swing(seed: int) -> None:
    """Where an antenna at r (FRD) is and how fast it moves about the IMU, R r and R (w x r), against scipy's
    rotation of the same attitude (heading from east, counter-clockwise, as ours)."""
    rng = np.random.default_rng(seed)
    k = 300
    attitude = np.column_stack((rng.uniform(-1, 1, k), rng.uniform(-1, 1, k), rng.uniform(-np.pi, np.pi, k)))
    rates, arm = rng.normal(0, 1, (k, 3)), rng.normal(0, 2, (k, 3))
    rotation = _rotation(np.pi / 2 - attitude[:, 2], attitude[:, 1], attitude[:, 0])
    where, swing = antenna_offsets(attitude, rates, arm)
    np.testing.assert_allclose(where, rotation.apply(arm)[:, [1, 0]], atol=1e-12)
    np.testing.assert_allclose(swing, rotation.apply(np.cross(rates, arm))[:, [1, 0]], atol=1e-12)


MAST = (0.3, 0.0, -1.5)  # an antenna 1.5 m up a mast, 0.3 m forward of the IMU


@pytest.mark.parametrize("seed", range(3))
def test_a_buoy_with_its_antenna_up_a_mast_keeps_a_still_estimate_once_its_fixes_are_moved_to_the_imu(seed) -> None:
    """The rolling buoy's antenna 1.5 m up a mast and 0.3 m forward swings about 0.25 m and 0.27 m/s; with a good
    receiver (0.3 m, 0.05 m/s) the EKF told where the antenna is keeps still (seeds 0-2: 0.025-0.031 m/s and
    0.07-0.09 m RMS), one not told follows the swing and sits at the antenna (0.070-0.076 m/s, 0.35-0.41 m)."""
    good = (0.3, 0.05)
    speed, distance = _velocity_rms(seed, True, MAST, told=True, gps_sigma=good)
    speed_not, distance_not = _velocity_rms(seed, True, MAST, told=False, gps_sigma=good)
    print(f"seed {seed}: told {speed:.3f} m/s {distance:.3f} m; not {speed_not:.3f} m/s {distance_not:.3f} m")
    assert speed < 0.05 and distance < 0.2
    assert speed_not > 1.5 * speed and distance_not > 2.5 * distance
