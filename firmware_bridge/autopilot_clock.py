"""The autopilot's clock since boot placed on the local clock, so that a GPS fix is stamped when it was read, and
the IMU and attitude when they were sent, not when their messages arrived.

ArduPilot stamps GPS_RAW_INT with the time its GPS driver read the fix (`time_usec` = last_fix_time_ms * 1000,
libraries/AP_GPS/AP_GPS.cpp send_mavlink_gps_raw) and sends it at the rate asked, so a fix is up to one stream
interval old when it goes out, plus the link's delay. Its other messages carry the time they were sent
(`time_boot_ms`; RAW_IMU's `time_usec`). A message sent at autopilot time b (s) that arrives at local time a gives
a sample a - b = offset + delay, and the estimate is the smallest recent sample (the offset plus the smallest
delay):

    offset[k] = min(a_k - b_k, offset[k-1] + LEAK_PER_S * (a_k - a_(k-1)))

The leak forgets old samples (one 1 s old counts 10 ms more), so an autopilot clock up to 1 % slower than the
local one is followed (quartz clocks differ by 1e-4); a faster one is followed at once by the min. What the min
alone would never follow, and how it is caught:
- the autopilot's clock starts again (a reboot, the 49.7-day wrap of time_boot_ms): its time goes back by more
  than BACKSTEP_S, and the estimate restarts from that sample;
- the clocks' rates differ by more than the leak (a simulated world that cannot keep its pace): when every sample
  of a WINDOW_S window is more than JUMP_S above the estimate, it restarts from the window's smallest sample. So
  the estimate is never more than about JUMP_S + 2 WINDOW_S * (rate difference) too low.
One late message, or a burst shorter than the window, changes nothing. A fix stamped f is at local time f + offset
(never later than its arrival), and so is a message sent at f: several read from a link at once (a serial port
read in bursts, a busy vessel loop) keep the times they were sent, not the one time of their arrival.
"""

from __future__ import annotations

import math

LEAK_PER_S = 0.01  # s/s: how fast the estimate forgets its smallest sample
WINDOW_S = 1.0  # s
JUMP_S = 0.05  # a window whose samples are all this far above the estimate restarts it, s
BACKSTEP_S = 1.0  # the autopilot's time going back by more than this restarts the estimate, s
RESOLUTION_S = 0.002  # ArduPilot's times are whole ms on both sides: a fix younger than this is taken as arrived
# time_usec at or above this (about 3.2 years since boot) is UNIX time (MAVLink: "the receiving end can infer
# timestamp format ... by checking for the magnitude of the number"), which this clock does not map.
BOOT_TIME_LIMIT_US = 10**14


class AutopilotClock:
    """Where the autopilot's time since boot falls on the local clock (module docstring)."""

    def __init__(self, leak_per_s: float = LEAK_PER_S, jump_s: float = JUMP_S, window_s: float = WINDOW_S) -> None:
        self.leak_per_s, self.jump_s, self.window_s = leak_per_s, jump_s, window_s
        self.offset_s: float | None = None  # local time minus autopilot time, s (None before the first sample)
        self.restarts = 0  # times the estimate restarted (not counting the first sample)
        self._last_arrival_s = -math.inf
        self._newest_boot_s = -math.inf
        self._window_start_s = -math.inf
        self._window_min_s = math.inf

    def observe(self, boot_s: float, arrival_s: float) -> None:
        """A message sent at autopilot time boot_s (s since its boot) arrived at local time arrival_s (s)."""
        sample = arrival_s - boot_s
        if not (math.isfinite(sample) and 0.0 <= boot_s < BOOT_TIME_LIMIT_US * 1e-6):
            return  # not a time since boot
        if self.offset_s is None or boot_s < self._newest_boot_s - BACKSTEP_S:
            self._restart(sample, arrival_s, counted=self.offset_s is not None)
            self._newest_boot_s = boot_s
        else:
            leaked = self.offset_s + self.leak_per_s * max(0.0, arrival_s - self._last_arrival_s)
            self.offset_s = min(sample, leaked)
            self._window_min_s = min(self._window_min_s, sample)
            if arrival_s >= self._window_start_s + self.window_s:
                if self._window_min_s > self.offset_s + self.jump_s:
                    self._restart(self._window_min_s, arrival_s)
                self._window_start_s, self._window_min_s = arrival_s, math.inf
            self._newest_boot_s = max(self._newest_boot_s, boot_s)
        self._last_arrival_s = max(self._last_arrival_s, arrival_s)

    def _restart(self, offset_s: float, arrival_s: float, counted: bool = True) -> None:
        self.restarts += counted
        self.offset_s = offset_s
        self._window_start_s, self._window_min_s = arrival_s, math.inf

    def place(self, time_usec: int, arrival_s: float) -> float:
        """The local time (s) of autopilot time time_usec (us since its boot) in a message that arrived at
        arrival_s (a GPS fix's time of reading, another message's time of sending): the arrival when the stamp
        cannot be placed (no sample yet, 0, UNIX time) or is younger than RESOLUTION_S, never later than the
        arrival."""
        if self.offset_s is None or not 0 < time_usec < BOOT_TIME_LIMIT_US:
            return arrival_s
        placed = time_usec * 1e-6 + self.offset_s
        return placed if placed < arrival_s - RESOLUTION_S else arrival_s
