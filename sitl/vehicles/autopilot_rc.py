"""RC input of the simulated autopilot: overrides, their expiry, scaling, the pilot's steering/throttle/lateral
and the motor mixing, as ArduPilot Rover does them.

- RC_CHANNELS_OVERRIDE is taken only from MAV_GCS_SYSID (libraries/GCS_MAVLink/GCS_Common.cpp
  `handle_rc_channels_override`); channels 1-8: UINT16_MAX = leave alone, 0 = release; 9-18: 0 and UINT16_MAX
  leave alone, UINT16_MAX-1 releases. An override counts for RC_OVERRIDE_TIME s (0: overrides disabled, negative:
  never expire) (libraries/RC_Channel/RC_Channel.cpp `has_override`, RC_Channel.h `get_override_timeout_ms`).
- Without an override a channel reads the receiver; with no receiver it keeps its last value (RC_Channel::update
  returns early), and RC_Channels::read_input reports new input only when an override arrives.
- Steering (RCMAP_ROLL), throttle (RCMAP_THROTTLE) and lateral (RCMAP_YAW) are "angle" inputs (Rover/radio.cpp
  `set_control_channels`) scaled about RCx_TRIM with the dead zone RCx_DZ by `pwm_to_angle_dz_trim`
  (RC_Channel.cpp), reversed by RCx_REVERSED, and kept as an int16 (`control_in`): throttle and lateral in whole
  percent, steering in 1/4500, truncated towards zero.
- Pilot input (Rover/mode.cpp `get_pilot_input`, `get_pilot_desired_steering_and_throttle`): zero under radio
  failsafe; PILOT_STEER_TYPE 0 (default) and 2 flip steering when throttle is negative, 3 does not, 1 reads two
  paddles; skid-steer and omni frames scale steering and throttle back together when |s| + |t| > 1; throttle is
  slew-limited by MOT_SLEWRATE %/s (libraries/AR_Motors/AP_MotorsUGV.cpp `get_slew_limited_throttle`), and the
  steering flips again if the limited throttle has the other sign.
- Lateral moves only an omni frame (FRAME_TYPE != 0, AP_MotorsUGV::is_omni, `output_omni`).
- A frame with a steering output (a motorboat's) turns it the other way while the motor throttle is negative
  (AP_MotorsUGV::output_regular, MANUAL without speed scaling), so with PILOT_STEER_TYPE 0 its rudder follows the
  stick astern too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

UINT16_MAX = 65535
OVERRIDE_CHANNELS = 18
SKID_FUNCTIONS = (73, 74)  # SERVOn_FUNCTION throttle left / right (libraries/SRV_Channel/SRV_Channel.h)
# OmniX motor factors (throttle, steering, lateral): libraries/AR_Motors/AP_MotorsUGV.cpp setup_omni.
OMNI_FACTORS = {
    1: ((1.0, -1.0, -1.0), (0.0, -1.0, 1.0), (1.0, 1.0, 1.0)),
    2: ((1.0, -1.0, -1.0), (1.0, -1.0, 1.0), (1.0, 1.0, -1.0), (1.0, 1.0, 1.0)),
    3: ((0.0, 1.0, 1.0), (1.0, 0.0, 0.0), (0.0, -1.0, 1.0), (1.0, 0.0, 0.0)),
    4: ((-1.0, 1.0, -0.26795), (0.73205, 1.0, -0.73205), (0.26795, 1.0, 1.0)),
}


def scale_angle(
    pwm: int, low: int, trim: int, high: int, dead_zone: int, reversed_: bool, full_scale: int | None = None
) -> float:
    """An RC PWM as ArduPilot's angle input in [-1, 1] (RC_Channel::pwm_to_angle_dz_trim divided by its range).

    full_scale: the channel's angle (100 for throttle and lateral, 4500 for steering: Rover/radio.cpp
    set_control_channels); the value is then the int16 control_in ArduPilot keeps, truncated towards zero, in
    units of 1 / full_scale: a throttle under 1 % reads 0. None: the exact fraction.
    """
    r = min(high, max(low, int(pwm)))
    top, bottom = trim + dead_zone, trim - dead_zone
    sign = -1.0 if reversed_ else 1.0
    if r > top and high != top:
        above, span = r - top, high - top
    elif r < bottom and bottom != low:
        above, span = r - bottom, bottom - low
    else:
        return 0.0
    if full_scale is None:
        return sign * above / span
    units = abs(above) * full_scale // span  # (float) high_in * delta / span, then int16: truncated towards zero
    return sign * math.copysign(units, above) / full_scale


def input_expo(stick: float, expo: float) -> float:
    """The stick in [-1, 1] shaped by an expo e (AP_Math/control.cpp input_expo, MANUAL_STR_EXPO in Rover's
    MANUAL): (1 - e) x / (1 - e |x|) after clamping x to [-1, 1], for e < 0.95; above that x is left alone."""
    x = min(1.0, max(-1.0, stick))
    if expo >= 0.95:
        return x
    return (1.0 - expo) * x / (1.0 - expo * abs(x))


def norm_input_dz(pwm: int, low: int, trim: int, high: int, dead_zone: int, reversed_: bool) -> float:
    """RC_Channel::norm_input_dz (used by the two-paddle steering type)."""
    sign = -1.0 if reversed_ else 1.0
    dz_min, dz_max = trim - dead_zone, trim + dead_zone
    if pwm < dz_min and dz_min > low:
        value = sign * (pwm - dz_min) / (dz_min - low)
    elif pwm > dz_max and high > dz_max:
        value = sign * (pwm - dz_max) / (high - dz_max)
    else:
        value = 0.0
    return min(1.0, max(-1.0, value))


@dataclass
class RcInput:
    """The autopilot's RC inputs: overrides with their time, the receiver (neutral sticks at each TRIM, or none)."""

    receiver: bool = True
    override: list[int] = field(default_factory=lambda: [0] * OVERRIDE_CHANNELS)
    override_t: list[float] = field(default_factory=lambda: [-math.inf] * OVERRIDE_CHANNELS)
    radio_in: list[int] = field(default_factory=lambda: [0] * OVERRIDE_CHANNELS)
    last_valid_s: float = -math.inf  # when RC input was last "new" (Rover::read_radio last_valid_rc_ms)

    # What the last `update` found, and when it stays true (see `_unchanged`): (override list, override_t list,
    # mutations, timeout, t_s, the earliest live override's time or None, any live); None: nothing yet.
    _live: tuple | None = field(default=None, init=False, repr=False, compare=False)
    _mutations: int = field(default=0, init=False, repr=False, compare=False)
    _inputs: tuple | None = field(default=None, init=False, repr=False, compare=False)  # trims, radio_in, receiver

    def apply_override(self, raw: list[int], t_s: float) -> None:
        """Store an RC_CHANNELS_OVERRIDE's 18 values (GCS_Common.cpp handle_rc_channels_override)."""
        self._mutations += 1
        override, override_t = self.override, self.override_t
        for i, value in enumerate(raw[:8]):  # channels 1-8: UINT16_MAX leaves alone
            if value != UINT16_MAX:
                override[i] = int(value)
                override_t[i] = t_s
        extra = raw[8:OVERRIDE_CHANNELS]  # 9-18: 0 and UINT16_MAX leave alone (all of them, as a rule)
        if extra.count(0) + extra.count(UINT16_MAX) == len(extra):
            extra = []
        for i, value in enumerate(extra, 8):
            if value in (0, UINT16_MAX):
                continue
            override[i] = 0 if value == UINT16_MAX - 1 else int(value)
            override_t[i] = t_s
        self.last_valid_s = t_s

    def clear_overrides(self) -> None:
        """RC_Channels::clear_overrides (a failsafe does this)."""
        self.override = [0] * OVERRIDE_CHANNELS
        self.override_t = [-math.inf] * OVERRIDE_CHANNELS

    def has_override(self, i: int, t_s: float, timeout_s: float) -> bool:
        if self.override[i] == 0:
            return False
        if timeout_s < 0:
            return True
        if timeout_s == 0:
            return False
        return t_s - self.override_t[i] < timeout_s

    def _unchanged(self, t_s: float, timeout_s: float) -> bool:
        """True when which overrides are live is what the last `update` found: no override stored or cleared
        since, the same timeout, and t_s no earlier and before the first live override expires (an expired one
        stays expired as time goes on; t_s - since < timeout is monotone in since)."""
        live = self._live
        return (
            live is not None
            and live[0] is self.override
            and live[1] is self.override_t
            and live[2] == self._mutations
            and live[3] == timeout_s
            and live[4] <= t_s
            and (live[5] is None or t_s - live[5] < timeout_s)
        )

    def any_override(self, t_s: float, timeout_s: float) -> bool:
        if self._unchanged(t_s, timeout_s):
            return self._live[6]
        if timeout_s == 0:
            return False
        live = (t_s - self.override_t[i] < timeout_s for i in range(OVERRIDE_CHANNELS) if self.override[i])
        return any(self.override) if timeout_s < 0 else any(live)

    def update(self, t_s: float, timeout_s: float, trims: list[int]) -> bool:
        """Refresh radio_in (RC_Channel::update): override, else the receiver, else the last value; returns
        `any_override(t_s, timeout_s)`. (The test of `has_override` inlined, all channels in one comprehension;
        skipped while nothing it reads has changed: this runs for every vehicle several times a step.)"""
        inputs = self._inputs
        if (
            inputs is not None
            and inputs[0] is trims
            and inputs[1] is self.radio_in
            and inputs[2] == self.receiver
            and self._unchanged(t_s, timeout_s)
        ):
            if self.receiver:
                self.last_valid_s = t_s
            return self._live[6]
        override, override_t = self.override, self.override_t
        if timeout_s == 0:  # overrides disabled
            live = [False] * OVERRIDE_CHANNELS
        elif timeout_s < 0:  # overrides never expire
            live = [bool(value) for value in override]
        else:
            live = [bool(value) and t_s - since < timeout_s for value, since in zip(override, override_t, strict=True)]
        if self.receiver:
            neutral = list(trims[:OVERRIDE_CHANNELS]) + [1500] * (OVERRIDE_CHANNELS - len(trims))
            self.radio_in[:] = [v if on else n for v, on, n in zip(override, live, neutral, strict=True)]
            self.last_valid_s = t_s
        else:
            self.radio_in[:] = [v if on else r for v, on, r in zip(override, live, self.radio_in, strict=True)]
        expiring = [since for since, on in zip(override_t, live, strict=True) if on] if timeout_s > 0 else []
        first = min(expiring) if expiring else None
        self._live = (override, override_t, self._mutations, timeout_s, t_s, first, any(live))
        self._inputs = (trims, self.radio_in, self.receiver)
        return self._live[6]  # what `any_override` finds now: `_unchanged` holds at t_s


@dataclass
class PilotOutput:
    """What the motors get, each in [-1, 1]: steering (+ clockwise), throttle (+ forward), lateral (+ right)."""

    steering: float = 0.0
    throttle: float = 0.0
    lateral: float = 0.0


def pilot_demand(channel, steer_type: int, skid: bool) -> tuple[float, float]:
    """Rover/mode.cpp get_pilot_input + the skid-steer saturation of get_pilot_desired_steering_and_throttle.
    `channel(name, paddle=False)` reads "steer" or "throttle" as an angle input (or norm_input_dz for paddles)."""
    if steer_type == 1:  # two paddles
        left, right = channel("steer", True), channel("throttle", True)
        throttle, steering = 0.5 * (left + right), 0.5 * (left - right)
    else:
        throttle = channel("throttle", False)
        steering = channel("steer", False)
        if steer_type in (0, 2) and throttle < 0:
            steering = -steering
    if skid:
        saturation = abs(min(1.0, max(-1.0, steering))) + abs(min(1.0, max(-1.0, throttle)))
        if saturation > 1.0:
            steering, throttle = steering / saturation, throttle / saturation
    return steering, throttle


def slew_limited(throttle: float, previous: float, slew_pct_per_s: float, dt_s: float) -> float:
    """AP_MotorsUGV::get_slew_limited_throttle on [-1, 1] throttle (MOT_SLEWRATE in % of full range per s)."""
    if slew_pct_per_s <= 0:
        return throttle
    step = slew_pct_per_s / 100.0 * max(0.0, dt_s)
    return min(previous + step, max(previous - step, throttle))


def omni_motor_outputs(frame_type: int, out: PilotOutput) -> list[float]:
    """Each omni motor's output in [-1, 1] (AP_MotorsUGV::output_omni: sum of factors, scaled back evenly)."""
    factors = OMNI_FACTORS.get(frame_type, ())
    raw = [out.throttle * t + out.steering * s + out.lateral * lat for t, s, lat in factors]
    biggest = max([1.0] + [abs(v) for v in raw])
    return [v / biggest for v in raw]


def skid_outputs(out: PilotOutput) -> tuple[float, float]:
    """(left, right) in [-1, 1]: throttle + steering, throttle - steering, scaled back together on saturation
    (AP_MotorsUGV::output_skid_steering with symmetric thrust)."""
    steering = min(1.0, max(-1.0, out.steering))
    throttle = min(1.0, max(-1.0, out.throttle))
    saturation = max(abs(throttle) + abs(steering), 1.0)
    return (throttle + steering) / saturation, (throttle - steering) / saturation


def servo_pwm(value: float, low: int = 1100, trim: int = 1500, high: int = 1900) -> int:
    """An output in [-1, 1] as SERVOn PWM about its trim (SRV_Channel defaults 1100/1500/1900)."""
    v = min(1.0, max(-1.0, value))
    return round(trim + v * ((high - trim) if v >= 0 else (trim - low)))
