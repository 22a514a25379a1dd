"""A GPS antenna away from the hull's reference point (a buoy's mast, a boat's wheelhouse roof): its fixes moved
back to the point the estimator tracks, as ArduPilot's EKF3 does with GPS1_POS_X/Y/Z.

Why: an antenna at r (body frame, m) from the IMU is at p + R r and moves at v + R (w x r), with R the hull's
attitude and w its body rates. On a buoy rolling 9 deg every 5 s with its antenna 1.5 m up the mast, the fixes
swing 0.23 m and their velocity 0.27 m/s about the hull's; a boat turning at 0.5 rad/s with its antenna 1 m
ahead of the IMU sees 0.5 m/s sideways that its hull does not make. The estimator would take that for motion.

What (libraries/AP_NavEKF3/AP_NavEKF3_PosVelFusion.cpp `CorrectGPSForAntennaOffset`, with r = GPS1_POS - INS_POS1):

    p_hull = p_fix - R r,    v_hull = v_fix - R (w x r)

R from roll phi, pitch theta and yaw psi (ZYX, body FRD to north-east-down), at the fix's time.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def body_to_ned(roll_rad: FloatArray, pitch_rad: FloatArray, yaw_rad: FloatArray) -> FloatArray:
    """(k, 3, 3) rotations from the body frame (x forward, y right, z down) to north-east-down, yaw from north,
    clockwise."""
    sr, cr = np.sin(roll_rad), np.cos(roll_rad)
    sp, cp = np.sin(pitch_rad), np.cos(pitch_rad)
    sy, cy = np.sin(yaw_rad), np.cos(yaw_rad)
    return np.stack(
        (
            np.stack((cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr), axis=-1),
            np.stack((sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr), axis=-1),
            np.stack((-sp, cp * sr, cp * cr), axis=-1),
        ),
        axis=-2,
    )


def antenna_offsets(
    attitude_rad: FloatArray, body_rates_frd_radps: FloatArray, antenna_frd_m: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Where the antenna is from the reference point and how fast it moves about it, each (k, 2) east, north (m,
    m/s), for attitudes (k, 3) roll, pitch, heading (rad; heading from east, counter-clockwise), body rates (k, 3)
    FRD rad/s and antenna offsets (k, 3) FRD m. Subtract them from a fix's position and velocity."""
    rotation = body_to_ned(attitude_rad[:, 0], attitude_rad[:, 1], np.pi / 2 - attitude_rad[:, 2])
    position = np.einsum("kij,kj->ki", rotation, antenna_frd_m)
    velocity = np.einsum("kij,kj->ki", rotation, np.cross(body_rates_frd_radps, antenna_frd_m))
    return position[:, [1, 0]], velocity[:, [1, 0]]
