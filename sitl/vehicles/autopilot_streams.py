"""Which telemetry the simulated autopilot sends, and how often: ArduPilot's stream groups and message intervals.

ArduPilot sends each message at an interval per link (libraries/GCS_MAVLink/GCS_Common.cpp):
- At boot every message of a stream group gets the group's rate, MAVn_<GROUP> Hz (SRn_* before ArduPilot 4.7;
  Rover's defaults are 1 Hz, PARAMS 10: libraries/GCS_MAVLink/GCS_MAVLink_Parameters.cpp), HEARTBEAT 1 Hz
  (`initialise_message_intervals_from_streamrates`).
- MAV_CMD_SET_MESSAGE_INTERVAL (`set_message_interval`): interval 0 restores the default (the group's rate, or
  off when the message is in no group), -1 stops it, other negatives are DENIED, below 1 ms counts as 1 ms, above
  60 s as 60 s; an interval shorter than Rover's 50 Hz loop allows (25 ms, `cap_message_interval`,
  libraries/AP_Scheduler/AP_Scheduler.cpp SCHEDULER_DEFAULT_LOOP_RATE) is DENIED with a STATUSTEXT; a message
  ArduPilot cannot schedule (no ap_message: WHEEL_DISTANCE and NAMED_VALUE_FLOAT among them) is DENIED with
  "No ap_message for mavlink id (N)" (that text on SITL builds); param3 != 0 is DENIED.
- MAV_CMD_GET_MESSAGE_INTERVAL: MESSAGE_INTERVAL with the interval in us, -1 when off (ACCEPTED), 0 when
  ArduPilot does not know the message (FAILED) (`handle_command_get_message_interval`).
- REQUEST_DATA_STREAM (libraries/GCS_MAVLink/GCS_Param.cpp `handle_request_data_stream`): sets a group's rate
  parameter (start_stop 0: rate 0) and re-initialises its messages; MAV_DATA_STREAM_ALL sets every group but
  PARAMS; an unknown group or start_stop > 1 is ignored. No reply.

The simulator produces the messages in PRODUCED; others that ArduPilot knows are accepted (their interval is
kept and reported) but never sent. A message is sent when its interval is due AND a reading newer than its last
copy exists (the simulated sensors' latest readings): a stream faster than its sensor goes at the sensor's rate.
"""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mavlink

m = mavlink
# Stream groups: parameter suffix -> (MAV_DATA_STREAM id, the messages ArduPilot puts in it that we can name).
# libraries/GCS_MAVLink/GCS_MAVLink_Parameters.cpp STREAM_*_msgs; Rover adds WHEEL_DISTANCE (EXTRA1) and
# RC_CHANNELS_SCALED (RAW_CTRL, "SERVO_OUT").
STREAM_GROUPS: dict[str, tuple[int, tuple[int, ...]]] = {
    "RAW_SENS": (m.MAV_DATA_STREAM_RAW_SENSORS, (m.MAVLINK_MSG_ID_RAW_IMU, m.MAVLINK_MSG_ID_SCALED_IMU2,
                 m.MAVLINK_MSG_ID_SCALED_IMU3, m.MAVLINK_MSG_ID_SCALED_PRESSURE)),
    "EXT_STAT": (m.MAV_DATA_STREAM_EXTENDED_STATUS, (m.MAVLINK_MSG_ID_SYS_STATUS, m.MAVLINK_MSG_ID_POWER_STATUS,
                 m.MAVLINK_MSG_ID_MEMINFO, m.MAVLINK_MSG_ID_MISSION_CURRENT, m.MAVLINK_MSG_ID_GPS_RAW_INT,
                 m.MAVLINK_MSG_ID_NAV_CONTROLLER_OUTPUT, m.MAVLINK_MSG_ID_FENCE_STATUS,
                 m.MAVLINK_MSG_ID_POSITION_TARGET_GLOBAL_INT)),
    "RC_CHAN": (m.MAV_DATA_STREAM_RC_CHANNELS, (m.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, m.MAVLINK_MSG_ID_RC_CHANNELS)),
    "RAW_CTRL": (m.MAV_DATA_STREAM_RAW_CONTROLLER, (m.MAVLINK_MSG_ID_RC_CHANNELS_SCALED,)),
    "POSITION": (m.MAV_DATA_STREAM_POSITION, (m.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
                 m.MAVLINK_MSG_ID_LOCAL_POSITION_NED)),
    "EXTRA1": (m.MAV_DATA_STREAM_EXTRA1, (m.MAVLINK_MSG_ID_ATTITUDE, m.MAVLINK_MSG_ID_AHRS2,
               m.MAVLINK_MSG_ID_PID_TUNING, m.MAVLINK_MSG_ID_WHEEL_DISTANCE)),
    "EXTRA2": (m.MAV_DATA_STREAM_EXTRA2, (m.MAVLINK_MSG_ID_VFR_HUD,)),
    "EXTRA3": (m.MAV_DATA_STREAM_EXTRA3, (m.MAVLINK_MSG_ID_AHRS, m.MAVLINK_MSG_ID_WIND,
               m.MAVLINK_MSG_ID_DISTANCE_SENSOR, m.MAVLINK_MSG_ID_SYSTEM_TIME, m.MAVLINK_MSG_ID_BATTERY_STATUS,
               m.MAVLINK_MSG_ID_EKF_STATUS_REPORT, m.MAVLINK_MSG_ID_VIBRATION)),
}  # fmt: skip

# Messages ArduPilot can schedule (GCS_Common.cpp mavlink_id_to_ap_message_id, the part a Rover build has).
# WHEEL_DISTANCE is in EXTRA1 but has no entry there: only REQUEST_DATA_STREAM EXTRA1 changes its rate.
SCHEDULABLE = frozenset(
    [mid for _, (_, ids) in STREAM_GROUPS.items() for mid in ids if mid != m.MAVLINK_MSG_ID_WHEEL_DISTANCE]
    + [m.MAVLINK_MSG_ID_HEARTBEAT, m.MAVLINK_MSG_ID_HOME_POSITION, m.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN,
       m.MAVLINK_MSG_ID_SCALED_IMU, m.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, m.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
       m.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, m.MAVLINK_MSG_ID_PARAM_VALUE, m.MAVLINK_MSG_ID_MISSION_ITEM_REACHED,
       m.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED, 435]  # 435: AVAILABLE_MODES (not in this pymavlink)
)  # fmt: skip

# What the simulator can send on a schedule.
PRODUCED = frozenset({
    m.MAVLINK_MSG_ID_HEARTBEAT, m.MAVLINK_MSG_ID_SYS_STATUS, m.MAVLINK_MSG_ID_GPS_RAW_INT,
    m.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, m.MAVLINK_MSG_ID_ATTITUDE, m.MAVLINK_MSG_ID_RAW_IMU,
    m.MAVLINK_MSG_ID_SCALED_IMU, m.MAVLINK_MSG_ID_WHEEL_DISTANCE, m.MAVLINK_MSG_ID_DISTANCE_SENSOR,
    m.MAVLINK_MSG_ID_RC_CHANNELS, m.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, m.MAVLINK_MSG_ID_VFR_HUD,
    m.MAVLINK_MSG_ID_BATTERY_STATUS, m.MAVLINK_MSG_ID_HOME_POSITION, m.MAVLINK_MSG_ID_SYSTEM_TIME,
    m.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
})  # fmt: skip

HEARTBEAT_INTERVAL_MS = 1000
MIN_INTERVAL_MS = 25  # Rover's 50 Hz loop: GCS_Common.cpp cap_message_interval (interval_ms * 800 < 20000 us)
MAX_INTERVAL_MS = 60000
STREAM_OF_DATA_STREAM = {stream_id: name for name, (stream_id, _) in STREAM_GROUPS.items()}


def interval_for_rate(rate_hz: float) -> int:
    """A group's message interval, ms, from its rate parameter (GCS_Common.cpp get_interval_for_stream)."""
    if rate_hz <= 0:
        return 0
    return min(MAX_INTERVAL_MS, int(1000 // rate_hz))


class StreamSchedule:
    """Message intervals (ms, 0 = off) of one link, and when each message is next due (s).

    group_rate(name) -> Hz reads the MAVn_<GROUP> parameters; set_group_rate(name, hz) writes one.
    """

    def __init__(self, group_rate, set_group_rate) -> None:
        self.group_rate, self.set_group_rate = group_rate, set_group_rate
        self.interval_ms: dict[int, int] = {}
        self.next_due_s: dict[int, float] = {}
        self._scheduled: dict[tuple[int, ...], tuple[int, ...]] = {}  # ids with an interval, per asked tuple
        for name in STREAM_GROUPS:
            self.initialise_group(name)
        self.interval_ms[m.MAVLINK_MSG_ID_HEARTBEAT] = HEARTBEAT_INTERVAL_MS

    def default_interval_ms(self, message_id: int) -> int:
        """What interval 0 restores (GCS_Common.cpp get_default_interval_for_ap_message)."""
        if message_id == m.MAVLINK_MSG_ID_HEARTBEAT:
            return HEARTBEAT_INTERVAL_MS
        for name, (_, ids) in STREAM_GROUPS.items():
            if message_id in ids:
                return interval_for_rate(self.group_rate(name))
        return 0

    def initialise_group(self, name: str) -> None:
        interval = interval_for_rate(self.group_rate(name))
        for message_id in STREAM_GROUPS[name][1]:
            self._set(message_id, interval)

    def _set(self, message_id: int, interval_ms: int) -> None:
        if interval_ms > 0:
            interval_ms = max(MIN_INTERVAL_MS, interval_ms)  # set_ap_message_interval: cap_message_interval
        self.interval_ms[message_id] = interval_ms
        self.next_due_s.pop(message_id, None)  # restart its schedule at the next chance
        self._scheduled.clear()

    def set_message_interval(self, param1: float, param2: float, param3: float) -> tuple[int, str | None]:
        """MAV_CMD_SET_MESSAGE_INTERVAL (message id, interval us, response target): (MAV_RESULT, STATUSTEXT)."""
        if not all(math.isfinite(p) for p in (param1, param2, param3)):
            return m.MAV_RESULT_DENIED, None  # the simulator's check: C would cast NaN to an arbitrary integer
        if param3 != 0:
            return m.MAV_RESULT_DENIED, None
        if not 0 <= param1 < 2**32 or not -(2**31) <= param2 < 2**31:
            return m.MAV_RESULT_DENIED, None
        message_id, interval_us = int(param1), int(param2)
        if message_id not in SCHEDULABLE:
            return m.MAV_RESULT_DENIED, f"No ap_message for mavlink id ({message_id})"
        if interval_us == 0:
            interval_ms = self.default_interval_ms(message_id)
        elif interval_us == -1:
            interval_ms = 0
        elif interval_us < 0:
            return m.MAV_RESULT_DENIED, None
        else:
            interval_ms = min(MAX_INTERVAL_MS, max(1, interval_us // 1000))
        if 0 < interval_ms < MIN_INTERVAL_MS:
            text = f"Requested rate for message ID {message_id} too fast. Increase SCHED_LOOP_RATE"
            return m.MAV_RESULT_DENIED, text
        self._set(message_id, interval_ms)
        return m.MAV_RESULT_ACCEPTED, None

    def get_message_interval(self, param1: float) -> tuple[int, int | None]:
        """MAV_CMD_GET_MESSAGE_INTERVAL: (MAV_RESULT, MESSAGE_INTERVAL's interval_us or None for no reply)."""
        if not math.isfinite(param1) or not 0 <= param1 < 2**32:
            return m.MAV_RESULT_DENIED, None
        message_id = int(param1)
        if message_id >= 2 << 15 or message_id not in SCHEDULABLE:
            return m.MAV_RESULT_FAILED, 0
        interval = self.interval_ms.get(message_id, 0)
        return m.MAV_RESULT_ACCEPTED, (interval * 1000 if interval else -1)

    def request_data_stream(self, stream_id: int, rate_hz: int, start_stop: int) -> bool:
        """REQUEST_DATA_STREAM; False when ArduPilot would ignore it (bad start_stop, unknown group)."""
        if start_stop not in (0, 1):
            return False
        rate = rate_hz if start_stop == 1 else 0
        if stream_id == m.MAV_DATA_STREAM_ALL:
            names = list(STREAM_GROUPS)  # PARAMS is not among them: ArduPilot never touches it here
        elif stream_id in STREAM_OF_DATA_STREAM:
            names = [STREAM_OF_DATA_STREAM[stream_id]]
        else:
            return False
        for name in names:
            self.set_group_rate(name, min(rate, 50))
            self.initialise_group(name)
        return True

    def due(self, message_id: int, t_s: float) -> bool:
        """True when `message_id` may go out at t_s; call `sent` when it does. Keeps a fixed grid so the average
        rate is the requested one whatever the callers' step."""
        interval = self.interval_ms.get(message_id, 0)
        if interval <= 0:
            return False
        return t_s + 1e-9 >= self.next_due_s.get(message_id, -math.inf)

    def scheduled(self, message_ids: tuple[int, ...]) -> tuple[tuple[int, float], ...]:
        """(id, period s) of the ids among `message_ids` (kept in their order) that have an interval; worked out
        again only when an interval changes (`_set`), for a caller that checks `due` and calls `sent` itself."""
        scheduled = self._scheduled.get(message_ids)
        if scheduled is None:
            intervals = self.interval_ms
            scheduled = tuple((i, intervals[i] / 1000.0) for i in message_ids if intervals.get(i, 0) > 0)
            self._scheduled[message_ids] = scheduled
        return scheduled

    def due_among(self, message_ids: tuple[int, ...], t_s: float) -> list[int]:
        """The ids among `message_ids` (kept in their order) that `due` says may go out at t_s, in one pass."""
        next_due, limit = self.next_due_s, t_s + 1e-9
        return [i for i, _ in self.scheduled(message_ids) if limit >= next_due.get(i, -math.inf)]

    def sent(self, message_id: int, t_s: float) -> None:
        period = self.interval_ms.get(message_id, 0) / 1000.0
        self.next_due_s[message_id] = next_due(self.next_due_s.get(message_id, -math.inf), period, t_s)


def next_due(due_s: float, period_s: float, t_s: float) -> float:
    """When a message due at due_s, sent at t_s, is due again: on its grid, or a period after t_s when the grid has
    fallen a period behind (the caller's step is longer than the period)."""
    due = due_s + period_s
    return due if due > t_s - period_s else t_s + period_s
