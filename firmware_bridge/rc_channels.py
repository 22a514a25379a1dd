"""RC channel scaling as ArduPilot applies it, and its inverse for the RC overrides we send.

ArduPilot Rover reads steering, throttle and lateral as "angle" channels
(Rover/radio.cpp `set_control_channels`: `set_angle`), so an input PWM p becomes
a normalised command u in [-1, 1] by RC_Channel::pwm_to_angle_dz_trim
(libraries/RC_Channel/RC_Channel.cpp), with r = p clipped to [MIN, MAX] and
dead zone DZ about TRIM (Rover sets a default DZ of 30 us, Rover/radio.cpp
`init_rc_in`):

    u = +(r - (TRIM + DZ)) / (MAX - (TRIM + DZ))   when r > TRIM + DZ
    u = +(r - (TRIM - DZ)) / ((TRIM - DZ) - MIN)   when r < TRIM - DZ
    u = 0                                          otherwise,

negated when the channel is REVERSED. `pwm_for` is the exact inverse (u = 0 gives
TRIM), so a wish of 0.78 reaches the autopilot as 0.78 whatever the channel's
calibration, where a fixed 1500 +- 400 would not (SITL's rover.parm sets
1000..2000: 1900 us read as 78 % throttle, issue #18).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

PWM_NEUTRAL = 1500
DEFAULT_DEAD_ZONE_US = 30  # Rover's default for steering, throttle and lateral (Rover/radio.cpp init_rc_in)


@dataclass(frozen=True)
class RcChannelRange:
    """One RC input's calibration as the autopilot holds it: RCn_MIN, RCn_TRIM, RCn_MAX, RCn_DZ (us), RCn_REVERSED."""

    min_us: int = 1100
    trim_us: int = 1500
    max_us: int = 1900
    dead_zone_us: int = DEFAULT_DEAD_ZONE_US
    reversed: bool = False

    def problem(self) -> str | None:
        """Why this calibration cannot carry a command both ways about TRIM, or None when it can."""
        if not 800 <= self.min_us < self.trim_us < self.max_us <= 2200:
            has = f"MIN {self.min_us}, TRIM {self.trim_us}, MAX {self.max_us}"
            return f"needs 800 <= MIN < TRIM < MAX <= 2200 us, has {has}"
        if self.dead_zone_us < 0 or self.trim_us + self.dead_zone_us >= self.max_us:
            return f"dead zone {self.dead_zone_us} us leaves no travel above TRIM {self.trim_us} (MAX {self.max_us})"
        if self.trim_us - self.dead_zone_us <= self.min_us:
            return f"dead zone {self.dead_zone_us} us leaves no travel below TRIM {self.trim_us} (MIN {self.min_us})"
        return None

    def pwm_for(self, value: float) -> int:
        """The PWM (us) that ArduPilot reads as `value` in [-1, 1] (clipped; NaN or inf -> TRIM, neutral)."""
        u = float(value)
        if not math.isfinite(u) or u == 0.0:
            return self.trim_us
        u = min(1.0, max(-1.0, -u if self.reversed else u))
        if u > 0:
            high = self.trim_us + self.dead_zone_us
            return min(self.max_us, math.ceil(high + u * (self.max_us - high)))
        low = self.trim_us - self.dead_zone_us
        return max(self.min_us, math.floor(low + u * (low - self.min_us)))

    def value_of(self, pwm_us: float) -> float:
        """What ArduPilot reads from `pwm_us`, in [-1, 1] (RC_Channel::pwm_to_angle_dz_trim, normalised)."""
        r = min(float(self.max_us), max(float(self.min_us), float(pwm_us)))
        high, low = self.trim_us + self.dead_zone_us, self.trim_us - self.dead_zone_us
        if r > high and self.max_us != high:
            u = (r - high) / (self.max_us - high)
        elif r < low and low != self.min_us:
            u = (r - low) / (low - self.min_us)
        else:
            u = 0.0
        return -u if self.reversed else u


@dataclass(frozen=True)
class RcMap:
    """Which RC input carries which axis (RCMAP_ROLL = steering, RCMAP_THROTTLE = throttle, RCMAP_YAW = lateral
    on Rover: Rover/radio.cpp `set_control_channels`), and each channel's calibration."""

    steering: int = 1
    throttle: int = 3
    lateral: int = 4
    ranges: tuple[tuple[int, RcChannelRange], ...] = ()

    def range_of(self, channel: int) -> RcChannelRange:
        for number, calibration in self.ranges:
            if number == channel:
                return calibration
        return RcChannelRange()

    def problem(self) -> str | None:
        """Why this map cannot be driven (a channel outside 1..8 or shared, or a calibration that cannot work)."""
        channels = {"steering (RCMAP_ROLL)": self.steering, "throttle (RCMAP_THROTTLE)": self.throttle}
        channels["lateral (RCMAP_YAW)"] = self.lateral
        for what, channel in channels.items():
            if not 1 <= channel <= 8:
                return f"{what} is channel {channel}; RC overrides reach channels 1-8 only"
        if len(set(channels.values())) != 3:
            return f"steering, throttle and lateral share a channel ({self.steering}, {self.throttle}, {self.lateral})"
        for what, channel in channels.items():
            why = self.range_of(channel).problem()
            if why is not None:
                return f"{what} channel {channel}: {why}"
        return None

    def channels_for(self, steering: float, throttle: float, lateral: float | None) -> dict[int, int]:
        """{channel: PWM} for normalised steering (positive = turn right), throttle (positive = forward) and
        lateral (positive = right; None leaves the lateral channel at its TRIM)."""
        return {
            self.steering: self.range_of(self.steering).pwm_for(steering),
            self.throttle: self.range_of(self.throttle).pwm_for(throttle),
            self.lateral: self.range_of(self.lateral).pwm_for(0.0 if lateral is None else lateral),
        }
