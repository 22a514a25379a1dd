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

The autopilot keeps what it reads as an integer (RC_Channel::control_in is an
int16_t, the float above truncated towards zero) in units of the channel's
angle: throttle and lateral in whole percent (`set_angle(100)`), steering in
1/4500 (`set_angle(SERVO_MAX)`). So a throttle under 1 % is read as 0, and a
small astern throttle is not "negative" to the steering flip of
PILOT_STEER_TYPE 0 (Rover/mode.cpp `get_pilot_input` tests the integer; a frame
with a steering output flips it back, AP_MotorsUGV::output_regular).
`control_in` gives that integer, `pwm_for(value, full_scale)` the PWM read as the
nearest whole unit, and `RcMap.channels_for` flips the steering only when the
autopilot will read the throttle as negative. `ResolutionCarry` spreads a
command finer than a unit over successive overrides (error diffusion), so that
0.3 % of thrust is 1 % in three overrides of ten rather than none at all.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

PWM_NEUTRAL = 1500
DEFAULT_DEAD_ZONE_US = 30  # Rover's default for steering, throttle and lateral (Rover/radio.cpp init_rc_in)
STEERING_FULL_SCALE = 4500  # Rover/radio.cpp set_control_channels: steering set_angle(SERVO_MAX)
THROTTLE_FULL_SCALE = 100  # throttle and lateral set_angle(100): the autopilot reads them in whole percent


EXPO_OFF_FROM = 0.95  # an expo this high or higher leaves the stick as it is (AP_Math input_expo)


def before_expo(value: float, expo: float) -> float:
    """The stick position x in [-1, 1] that an autopilot shaping its input as y = (1 - e) x / (1 - e |x|) (ArduPilot
    Rover's MANUAL_STR_EXPO, AP_Math input_expo) turns into `value`: x = y / (1 - e + e |y|), the exact inverse
    for e < 0.95 (e may be negative down to -0.5: softer at the centre); at e >= 0.95 the input goes unshaped."""
    y = min(1.0, max(-1.0, value))
    if not math.isfinite(expo) or expo == 0.0 or expo >= EXPO_OFF_FROM:
        return y
    return y / (1.0 - expo + expo * abs(y))


def _nearest_whole(x: float) -> int:
    """x rounded to the nearest integer, halves away from zero (Python's round() takes halves to even)."""
    return int(math.copysign(math.floor(abs(x) + 0.5), x))


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

    def pwm_for(self, value: float, full_scale: int | None = None) -> int:
        """The PWM (us) that ArduPilot reads as `value` in [-1, 1] (clipped; NaN or inf -> TRIM, neutral).

        full_scale: the channel's angle (THROTTLE_FULL_SCALE, STEERING_FULL_SCALE): the PWM whose `control_in` is
        value x full_scale rounded to the nearest unit (half away from zero; under half a unit: TRIM), the
        nearer of the two PWMs about it when one microsecond spans several units. None: the first PWM past the
        continuous inverse (read back as `value` to within a microsecond, before the autopilot's truncation).
        """
        u = float(value)
        if not math.isfinite(u) or u == 0.0:
            return self.trim_us
        u = min(1.0, max(-1.0, -u if self.reversed else u))
        high, low = self.trim_us + self.dead_zone_us, self.trim_us - self.dead_zone_us
        if full_scale is None:
            if u > 0:
                return min(self.max_us, math.ceil(high + u * (self.max_us - high)))
            return max(self.min_us, math.floor(low + u * (low - self.min_us)))
        target = u * full_scale
        units = _nearest_whole(target)
        if units == 0:
            return self.trim_us
        edge, span, sign = (high, self.max_us - high, 1) if units > 0 else (low, low - self.min_us, -1)
        if span <= 0:
            return self.trim_us
        step = -((-abs(units) * span) // full_scale)  # ceil: the first PWM read as at least |units| units
        best = edge + sign * step
        if step > 1:  # the nearer of the two PWMs about the unit (the first on a tie)
            other = edge + sign * (step - 1)
            if abs(self._raw_units(other, full_scale) - target) < abs(self._raw_units(best, full_scale) - target):
                best = other
        return min(self.max_us, max(self.min_us, best))

    def _raw_units(self, pwm_us: int, full_scale: int) -> int:
        """control_in of `pwm_us` before the reversal (the unreversed channel's integer reading)."""
        r = min(self.max_us, max(self.min_us, int(pwm_us)))
        high, low = self.trim_us + self.dead_zone_us, self.trim_us - self.dead_zone_us
        if r > high and self.max_us != high:
            return (full_scale * (r - high)) // (self.max_us - high)
        if r < low and low != self.min_us:
            return -((full_scale * (low - r)) // (low - self.min_us))
        return 0

    def control_in(self, pwm_us: int, full_scale: int) -> int:
        """What ArduPilot stores from `pwm_us` (RC_Channel::control_in): pwm_to_angle_dz_trim with high_in =
        full_scale, truncated towards zero into an integer; negated when REVERSED."""
        units = self._raw_units(pwm_us, full_scale)
        return -units if self.reversed else units

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


class ResolutionCarry:
    """Error diffusion of commands over an autopilot that reads whole units (whole percent of throttle).

    Each call returns the value to send for one channel: the wish plus what earlier overrides of that channel
    still owe, rounded to the nearest unit (half away from zero); the rounding error is owed to the next one. A
    steady wish is met on average to well under a unit, where rounding alone would hold it at the nearest unit
    (under half a percent of thrust: none). A wish of exactly 0 is sent as 0 and clears what is owed (a stop is
    a stop); what is owed is at most half a unit, also when the wish is beyond full scale.
    """

    def __init__(self) -> None:
        self._owed: dict[object, float] = {}

    def __call__(self, channel: object, value: float, full_scale: int = THROTTLE_FULL_SCALE) -> float:
        """The value in [-1, 1], a whole number of 1 / full_scale, to send on `channel` (any key) for `value`."""
        u = float(value)
        if not math.isfinite(u) or u == 0.0:
            self._owed.pop(channel, None)
            return 0.0
        target = min(1.0, max(-1.0, u)) * full_scale + self._owed.get(channel, 0.0)
        units = min(full_scale, max(-full_scale, _nearest_whole(target)))
        self._owed[channel] = min(0.5, max(-0.5, target - units))
        return units / full_scale

    def owed(self, channel: object) -> float:
        """What earlier overrides of `channel` still owe, in units (0 when nothing)."""
        return self._owed.get(channel, 0.0)

    def set_owed(self, channel: object, owed: float | None) -> None:
        """Set what `channel` owes (None: nothing, as after a stop): for a batch that carries many links at once
        (`firmware_bridge.override_batch.carried_units`)."""
        if owed is None:
            self._owed.pop(channel, None)
        else:
            self._owed[channel] = owed


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

    def channels_for(
        self, steering: float, throttle: float, lateral: float | None, *, flip_in_reverse: bool = False
    ) -> dict[int, int]:
        """{channel: PWM} for normalised steering (positive = turn right), throttle (positive = forward) and
        lateral (positive = right; None leaves the lateral channel at its TRIM), each the nearest the autopilot
        can read (whole percent; steering in 1/4500). flip_in_reverse (where the autopilot negates the steering
        once in reverse: `bob_autonomy.onboard.autopilot.AutopilotProfile.steering_flips_in_reverse`): the
        steering is sent negated when the autopilot will read the throttle as negative, so that it comes out as
        meant; a throttle under half a percent astern is read as 0 and the steering goes as it is."""
        throttle_range = self.range_of(self.throttle)
        throttle_pwm = throttle_range.pwm_for(throttle, THROTTLE_FULL_SCALE)
        if flip_in_reverse and throttle_range.control_in(throttle_pwm, THROTTLE_FULL_SCALE) < 0:
            steering = -steering
        return {
            self.steering: self.range_of(self.steering).pwm_for(steering, STEERING_FULL_SCALE),
            self.throttle: throttle_pwm,
            self.lateral: self.range_of(self.lateral).pwm_for(0.0 if lateral is None else lateral, THROTTLE_FULL_SCALE),
        }
