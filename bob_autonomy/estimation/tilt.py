"""An IMU on a hull that rolls and pitches, levelled with the autopilot's attitude before the EKF uses it.

Why: the estimators treat the accelerometer's x, y as the hull's horizontal acceleration and the z gyro as its
yaw rate. On a level hull that is so. On water it rolls and pitches, and the accelerometer measures specific
force f = R^T (a - g), so a tilt of theta puts g sin(theta) of gravity into the planar reading (0.17 m/s^2 per
degree; ArduPilot's SITL motorboat, rolled up to 4.7 degrees by its waves, reads 0.34-0.54 m/s^2 RMS while it
lies still: tests/ardupilot/test_real_waves.py), and the z gyro mixes in the roll and pitch rates. The EKF
would integrate that into metres-per-second velocity errors (a still buoy rolled 9 degrees: 1.6 m/s RMS).

What: with ATTITUDE's roll phi (right side down) and pitch theta (nose up), the readings in the body frame
(x forward, y right, z down: FRD, as MAVLink gives them) are turned into the frame that yaws with the hull but
stays level:

    a_fwd   = cos(theta) f_x + sin(theta) (sin(phi) f_y + cos(phi) f_z)
    a_right = cos(phi) f_y - sin(phi) f_z
    yaw rate = (q sin(phi) + r cos(phi)) / cos(theta)        (the Euler rate of yaw; p, q, r the body rates)

(gravity has no horizontal part, so a_fwd, a_right are the hull's own acceleration). The attitude is carried
from its reading to the IMU reading's time with the Euler rates of roll and pitch,

    roll rate = p + (q sin(phi) + r cos(phi)) tan(theta),    pitch rate = q cos(phi) - r sin(phi).

Readings here are in the estimators' frame (x forward, y left, z up; rates counter-clockwise), converted at
the edges.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from firmware_bridge.readings import CompassReading, ImuReading

FloatArray = NDArray[np.float64]
MAX_ATTITUDE_AGE_S = 0.5  # an attitude further than this from an IMU reading's time is not used to level it


def level_imu(
    accel_flu_mps2: FloatArray, gyro_flu_radps: FloatArray, roll_rad: FloatArray, pitch_rad: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """(accel (k, 2) m/s^2 forward and left in the level frame, yaw rate (k,) rad/s counter-clockwise) from the
    specific force (k, 3) and body rates (k, 3) in x forward, y left, z up, and the roll, pitch (k,) rad (module
    docstring)."""
    fx, fy, fz = accel_flu_mps2[:, 0], -accel_flu_mps2[:, 1], -accel_flu_mps2[:, 2]  # to FRD
    q, r = -gyro_flu_radps[:, 1], -gyro_flu_radps[:, 2]
    sr, cr, sp, cp = np.sin(roll_rad), np.cos(roll_rad), np.sin(pitch_rad), np.cos(pitch_rad)
    forward = cp * fx + sp * (sr * fy + cr * fz)
    right = cr * fy - sr * fz
    yaw_rate = (q * sr + r * cr) / cp
    return np.column_stack((forward, -right)), -yaw_rate


def euler_rates(roll_rad: FloatArray, pitch_rad: FloatArray, body_rates_frd_radps: FloatArray) -> FloatArray:
    """(k, 3) rates of roll, pitch and heading (counter-clockwise), rad/s, from the body rates p, q, r (k, 3) (FRD,
    as ATTITUDE's rollspeed, pitchspeed, yawspeed) at roll and pitch (k,) rad."""
    p, q, r = body_rates_frd_radps[:, 0], body_rates_frd_radps[:, 1], body_rates_frd_radps[:, 2]
    sr, cr = np.sin(roll_rad), np.cos(roll_rad)
    yaw = q * sr + r * cr
    return np.column_stack((p + yaw * np.tan(pitch_rad), q * cr - r * sr, -yaw / np.cos(pitch_rad)))


class TiltTracker:
    """The latest attitude of each of n rows (from CompassReadings that carry one), and IMU readings levelled with
    it (module docstring).

    Counters: `levelled`, the IMU rows levelled; `unlevelled`, rows that carried the full IMU but had no attitude
    within MAX_ATTITUDE_AGE_S of their time, used as they came (a hull taken as level).
    """

    def __init__(self, n: int, max_age_s: float = MAX_ATTITUDE_AGE_S) -> None:
        self.max_age_s = max_age_s
        self.t_s = np.full(n, np.nan)
        self.roll_pitch = np.zeros((n, 2))
        self.rates = np.zeros((n, 2))  # of roll and pitch, rad/s
        self.heading = np.zeros(n)  # rad from east, counter-clockwise, and its rate (rad/s): for `attitude_at`
        self.heading_rate = np.zeros(n)
        self.body_rates = np.zeros((n, 3))  # FRD, as ATTITUDE gives them
        self.levelled = 0
        self.unlevelled = 0

    def note(self, reading: CompassReading) -> None:
        """Keep each row's attitude if it is newer than the one held (rows without a finite one are skipped)."""
        if reading.roll_rad is None or reading.pitch_rad is None or reading.body_rates_frd_radps is None:
            return
        roll, pitch, body = reading.roll_rad, reading.pitch_rad, reading.body_rates_frd_radps
        rates = euler_rates(roll, pitch, body)
        rows, t = reading.agents, reading.t_s
        good = np.isfinite(roll) & np.isfinite(pitch) & np.all(np.isfinite(rates), axis=1) & np.isfinite(t)
        good &= np.isfinite(reading.heading_rad) & np.all(np.isfinite(body), axis=1)
        take = np.flatnonzero(good & ~(t < self.t_s[rows]))  # newer than the one held, or none held (NaN)
        if len(np.unique(rows[take])) < len(take):  # a row twice: in order, so that its latest reading wins
            winner: dict[int, int] = {}
            for j in take:
                if rows[j] not in winner or not t[j] < t[winner[rows[j]]]:
                    winner[rows[j]] = j
            take = np.array(sorted(winner.values()), dtype=np.intp)
        at = rows[take]
        self.t_s[at] = t[take]
        self.roll_pitch[at] = np.column_stack((roll[take], pitch[take]))
        self.rates[at] = rates[take, :2]
        self.heading[at] = reading.heading_rad[take]
        self.heading_rate[at] = rates[take, 2]
        self.body_rates[at] = body[take]

    def attitude_at(self, rows: NDArray[np.intp], t_s: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(attitude (k, 3): roll, pitch, heading rad, carried to times t_s (k,) s with their rates; known (k,)):
        known where an attitude is held within max_age_s of the time."""
        age = t_s - self.t_s[rows]
        known = np.abs(age) <= self.max_age_s
        age = np.where(known, age, 0.0)
        angles = np.column_stack((self.roll_pitch[rows], self.heading[rows]))
        rates = np.column_stack((self.rates[rows], self.heading_rate[rows]))
        return angles + rates * age[:, None], known

    def level(self, reading: ImuReading) -> ImuReading:
        """The reading with its accelerometer and yaw rate levelled where it carries the full IMU and an attitude
        is held; rows of a level hull (roll, pitch and their rates all zero) are left exactly as they are."""
        if reading.accel_z_mps2 is None or reading.gyro_xy_radps is None:
            return reading
        rows = reading.agents
        age = reading.t_s - self.t_s[rows]
        known = np.abs(age) <= self.max_age_s  # False where none is held (NaN)
        self.unlevelled += int(np.count_nonzero(~known))
        tilted = known & (np.any(self.roll_pitch[rows] != 0.0, axis=1) | np.any(self.rates[rows] != 0.0, axis=1))
        self.levelled += int(np.count_nonzero(known))
        if not tilted.any():
            return reading
        k = np.flatnonzero(tilted)
        angles = self.roll_pitch[rows[k]] + self.rates[rows[k]] * age[k, None]  # carried to the IMU's time
        accel3 = np.column_stack((reading.accel_body_mps2[k], reading.accel_z_mps2[k]))
        gyro3 = np.column_stack((reading.gyro_xy_radps[k], reading.gyro_z_radps[k]))
        accel, yaw_rate = level_imu(accel3, gyro3, angles[:, 0], angles[:, 1])
        accel_out, rate_out = reading.accel_body_mps2.copy(), reading.gyro_z_radps.copy()
        accel_out[k], rate_out[k] = accel, yaw_rate
        return replace(reading, accel_body_mps2=accel_out, gyro_z_radps=rate_out)
