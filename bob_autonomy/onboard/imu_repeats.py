"""An IMU sample that reaches a vessel twice is fused once.

ArduPilot puts the IMU's current sample in RAW_IMU (its RAW_SENS stream, 1 Hz by default) and in SCALED_IMU
(which the vessel asks for), in the same units (mG, mrad/s; libraries/GCS_MAVLink/GCS_Common.cpp send_raw_imu,
send_scaled_imu), so when both go out in one pass of Rover's GCS update_send they are equal field for field and
sent within 1 ms (RAW_IMU stamped in us, SCALED_IMU in whole ms); the simulated autopilot sends them at the same
time. Both decode to an ImuReading, and an EKF that fused both would count one gyro measurement twice: in the
45-buoy `aggregation` fleet half of the samples were fused twice, an overconfident yaw rate. A row is a repeat
when its values equal its agent's last IMU row exactly and it was taken within REPEAT_WINDOW_S of it; repeats
are dropped and counted. The window: a pair sent 0-1 ms apart is placed up to 3 ms apart on the vessel's clock
(the freshest message of a read is placed at its arrival when its stamp would put it within 2 ms of it:
firmware_bridge/autopilot_clock.py RESOLUTION_S); with a 2 ms window a tenth of real ArduPilot's pairs were
fused twice. A sample of a later pass (2.5 ms later, update_send runs at 400 Hz) with the very same values
would be dropped too; at rest ArduPilot's SITL sends the same values (0, 0, -1001 mG, 0 mrad/s) in each
message of a stream, 20 ms or more apart, which the 20 ms window of the first version dropped
(tests/ardupilot/test_real_imu_repeats.py).
"""

from __future__ import annotations

import numpy as np

from bob_autonomy.core.arrays import FloatArray
from firmware_bridge.readings import ImuReading, rows_of

REPEAT_WINDOW_S = 0.0035  # s: a pair is placed at most 3 ms apart (module docstring)


class ImuRepeats:
    """The last IMU row of each of n agents, to drop a row that repeats it (module docstring)."""

    def __init__(self, n: int) -> None:
        self.last_t = np.full(n, -np.inf)
        self.last_values = np.full((n, 6), np.nan)
        self.dropped = 0  # rows dropped as repeats

    def fresh(self, reading: ImuReading) -> ImuReading | None:
        """The reading without the rows that repeat their agent's last IMU row (None when none is left)."""
        agents = reading.agents
        values = _values(reading)
        if len(np.unique(agents)) < len(agents):  # an agent twice in one reading: row by row, in order
            keep = np.array([self._keep(agents[i : i + 1], reading.t_s[i : i + 1], values[i : i + 1])[0]
                             for i in range(len(agents))], dtype=bool)  # fmt: skip
        else:
            keep = self._keep(agents, reading.t_s, values)
        if keep.all():
            return reading
        self.dropped += int(np.count_nonzero(~keep))
        if not keep.any():
            return None
        return rows_of(reading, keep)

    def _keep(self, agents: np.ndarray, t_s: FloatArray, values: FloatArray) -> np.ndarray:
        last = self.last_values[agents]
        same = ((values == last) | (np.isnan(values) & np.isnan(last))).all(axis=1)
        keep = ~(same & (np.abs(t_s - self.last_t[agents]) <= REPEAT_WINDOW_S))
        self.last_t[agents[keep]] = t_s[keep]
        self.last_values[agents[keep]] = values[keep]
        return keep


def _values(reading: ImuReading) -> FloatArray:
    """(k, 6): accel x, y, gyro z, accel z, gyro x, y (NaN where the reading has no such field)."""
    k = len(reading.agents)
    accel_z = np.full(k, np.nan) if reading.accel_z_mps2 is None else reading.accel_z_mps2
    gyro_xy = np.full((k, 2), np.nan) if reading.gyro_xy_radps is None else reading.gyro_xy_radps
    return np.column_stack((reading.accel_body_mps2, reading.gyro_z_radps, accel_z, gyro_xy))
