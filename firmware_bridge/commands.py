"""Encode actuator and housekeeping commands as MAVLink 2 bytes a stock ArduPilot Rover accepts.

Each function returns the bytes of one packed frame, ready for `link.write`. An `Encoder` holds the
source system/component ids and the sequence counter; the module functions use a shared default encoder
unless given one (`encoder=`).

Source ids: ArduPilot takes RC_CHANNELS_OVERRIDE and MANUAL_CONTROL only from the system id in its
SYSID_MYGCS parameter (255 by default), so the default encoder sends as system 255, component
MAV_COMP_ID_ONBOARD_COMPUTER (191). Change one or the other if the vehicle is configured differently.

RC channel mapping (ArduPilot Rover defaults, RCMAP_ROLL=1, RCMAP_THROTTLE=3, RCMAP_YAW=4):
channel 1 = steering (positive = turn right / clockwise), channel 3 = throttle (positive = forward),
channel 4 = lateral (positive = right; omni / vectored frames only). PWM is 1500 +- 400 (1100..1900),
each axis normalised and clipped to [-1, 1] independently; non-finite inputs command neutral (1500).
See docs/mavlink-mapping.md.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.frames import LAYOUTS, layout
from firmware_bridge.rc_channels import STEERING_FULL_SCALE, THROTTLE_FULL_SCALE, RcChannelRange, ResolutionCarry

PWM_NEUTRAL = 1500
PWM_SPAN = 400  # so commands span 1100..1900
CHANNEL_STEERING = 1
CHANNEL_THROTTLE = 3
CHANNEL_LATERAL = 4
UINT16_MAX = 65535
GCS_SYSTEM_ID = 255  # ArduPilot's default SYSID_MYGCS
DEFAULT_RC_RANGE = RcChannelRange()  # ArduPilot's RCn_MIN/TRIM/MAX defaults, Rover's dead zone
ROVER_MODES = {"MANUAL": 0, "ACRO": 1, "STEERING": 3, "HOLD": 4, "LOITER": 5, "AUTO": 10, "RTL": 11, "GUIDED": 15}


class Encoder:
    """Packs MAVLink 2 messages from one source (system, component) with a rolling sequence number."""

    def __init__(
        self, source_system: int = GCS_SYSTEM_ID, source_component: int = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER
    ) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=source_system, srcComponent=source_component)

    def pack(self, message) -> bytes:
        data = bytes(message.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        return data

    def frame(self, message_class: type, *args) -> bytes:
        """The frame `pack(mav.<name>_encode(*args))` gives, without building the message object
        (`firmware_bridge.frames`: the telemetry hot path); signed links take pymavlink's path."""
        mav = self.mav
        if mav.signing.sign_outgoing:
            return self.pack(message_class(*args))
        spec = LAYOUTS.get(message_class.id) or layout(message_class.id)
        data = spec.frame(args, mav.seq, mav.srcSystem, mav.srcComponent)  # frames.pack_frame
        mav.seq = (mav.seq + 1) % 256
        return data


_DEFAULT_ENCODER = Encoder()


def _enc(encoder: Encoder | None) -> Encoder:
    return _DEFAULT_ENCODER if encoder is None else encoder


def normalised_to_pwm(value: float, full_scale: int = THROTTLE_FULL_SCALE) -> int:
    """[-1, 1] -> the PWM (1100..1900 about 1500) that ArduPilot with its default RC calibration and Rover's 30 us
    dead zone reads back as `value` to the nearest unit of `full_scale` (whole percent for throttle and lateral,
    STEERING_FULL_SCALE for steering: `firmware_bridge.rc_channels`); clipped; NaN/inf -> 1500 (neutral)."""
    return DEFAULT_RC_RANGE.pwm_for(value, full_scale)


def _ratio(value: float, scale: float) -> float:
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"the scale must be positive and finite, got {scale!r}")
    return float(value) / scale


def rc_override(channels: dict[int, int], target_system: int = 1, target_component: int = 1, *, encoder=None) -> bytes:
    """RC_CHANNELS_OVERRIDE with the given {channel (1..18): PWM}; channels 1-8 not given are left alone
    (UINT16_MAX), 9-18 not given are ignored (0)."""
    raw = [UINT16_MAX] * 8 + [0] * 10
    for channel, pwm in channels.items():
        if not 1 <= channel <= 18:
            raise ValueError(f"RC channel must be 1..18, got {channel}")
        raw[channel - 1] = int(pwm)
    return _enc(encoder).frame(mavlink.MAVLink_rc_channels_override_message, target_system, target_component, *raw)


def release_rc_override(target_system: int = 1, target_component: int = 1, *, encoder=None) -> bytes:
    """RC_CHANNELS_OVERRIDE handing channels 1-8 back to the RC radio (0)."""
    return rc_override(dict.fromkeys(range(1, 9), 0), target_system, target_component, encoder=encoder)


def rc_override_for_thrust(
    thrust_body_n: Sequence[float],
    max_thrust_n: float,
    target_system: int = 1,
    target_component: int = 1,
    *,
    yaw_command: float = 0.0,
    encoder: Encoder | None = None,
    carry: ResolutionCarry | None = None,
) -> bytes:
    """A buoy's body-frame thrust (x forward, y left; N) as RC overrides: throttle (ch 3) = x / max,
    lateral (ch 4, positive right) = -y / max, steering (ch 1, positive clockwise) = -yaw_command, where
    yaw_command in [-1, 1] is counter-clockwise positive. carry: the link's error diffusion of throttle and
    lateral over the autopilot's whole percent (None: each rounded alone)."""
    x, y = float(thrust_body_n[0]), float(thrust_body_n[1])
    throttle, lateral = _ratio(x, max_thrust_n), -_ratio(y, max_thrust_n)
    if carry is not None:
        throttle, lateral = carry(CHANNEL_THROTTLE, throttle), carry(CHANNEL_LATERAL, lateral)
    channels = {
        CHANNEL_THROTTLE: normalised_to_pwm(throttle),
        CHANNEL_LATERAL: normalised_to_pwm(lateral),
        CHANNEL_STEERING: normalised_to_pwm(-float(yaw_command), STEERING_FULL_SCALE),
    }
    return rc_override(channels, target_system, target_component, encoder=encoder)


def rc_override_for_wheels(
    left_mps: float,
    right_mps: float,
    max_wheel_speed_mps: float,
    target_system: int = 1,
    target_component: int = 1,
    *,
    encoder: Encoder | None = None,
    carry: ResolutionCarry | None = None,
) -> bytes:
    """Skid-steer wheel speeds as RC overrides the way ArduPilot mixes them back (left = throttle + steering,
    right = throttle - steering): throttle (ch 3) = (left + right) / (2 max), steering (ch 1, positive =
    turn right) = (left - right) / (2 max). carry: as `rc_override_for_thrust`'s, for the throttle."""
    left = _ratio(left_mps, max_wheel_speed_mps)
    right = _ratio(right_mps, max_wheel_speed_mps)
    throttle = (left + right) / 2.0
    if carry is not None:
        throttle = carry(CHANNEL_THROTTLE, throttle)
    channels = {
        CHANNEL_THROTTLE: normalised_to_pwm(throttle),
        CHANNEL_STEERING: normalised_to_pwm((left - right) / 2.0, STEERING_FULL_SCALE),
    }
    return rc_override(channels, target_system, target_component, encoder=encoder)


def _axis(value: float) -> int:
    v = float(value)
    if not math.isfinite(v):
        return 0
    return round(1000 * min(1.0, max(-1.0, v)))


def manual_control(
    throttle: float, steering: float, target_system: int = 1, *, encoder: Encoder | None = None
) -> bytes:
    """MANUAL_CONTROL for a Rover: throttle in [-1, 1] (forward positive) on z, steering in [-1, 1]
    (turn right positive) on y, each scaled to -1000..1000 (ArduPilot Rover maps them over the RC range);
    x and r are marked unused (INT16_MAX)."""
    message = _enc(encoder).mav.manual_control_encode(target_system, 32767, _axis(steering), _axis(throttle), 32767, 0)
    return _enc(encoder).pack(message)


def heartbeat(*, encoder: Encoder | None = None) -> bytes:
    """The onboard computer's HEARTBEAT (MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, active)."""
    message = _enc(encoder).mav.heartbeat_encode(
        mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE
    )
    return _enc(encoder).pack(message)


def command_long_arm(
    arm: bool, target_system: int = 1, target_component: int = 1, *, force: bool = False, encoder=None
) -> bytes:
    """COMMAND_LONG MAV_CMD_COMPONENT_ARM_DISARM: param1 = 1 arm / 0 disarm; param2 = 21196 forces it."""
    message = _enc(encoder).mav.command_long_encode(
        target_system,
        target_component,
        mavlink.MAV_CMD_COMPONENT_ARM_DISARM,
        0,
        1.0 if arm else 0.0,
        21196.0 if force else 0.0,
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
    )
    return _enc(encoder).pack(message)


def set_mode(mode: str | int, target_system: int = 1, target_component: int = 1, *, encoder=None) -> bytes:
    """COMMAND_LONG MAV_CMD_DO_SET_MODE to a Rover mode (name as in ROVER_MODES, or its custom mode number),
    with MAV_MODE_FLAG_CUSTOM_MODE_ENABLED; ArduPilot answers with a COMMAND_ACK."""
    if isinstance(mode, str):
        try:
            custom = ROVER_MODES[mode.upper()]
        except KeyError:
            raise ValueError(f"unknown Rover mode {mode!r}; known: {sorted(ROVER_MODES)}") from None
    else:
        custom = int(mode)
    message = _enc(encoder).mav.command_long_encode(
        target_system,
        target_component,
        mavlink.MAV_CMD_DO_SET_MODE,
        0,
        float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED),
        float(custom),
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
    )
    return _enc(encoder).pack(message)


# -- the vehicle's side: what an autopilot makes of these commands -----------------------------------------


def pwm_to_normalised(pwm: int) -> float:
    """What ArduPilot reads from an RC PWM (us) with its default calibration and dead zone, in [-1, 1] (the
    inverse of `normalised_to_pwm`); 0 and UINT16_MAX (not overridden) give NaN."""
    if pwm in (0, UINT16_MAX):
        return math.nan
    return DEFAULT_RC_RANGE.value_of(int(pwm))


def rc_axes(message) -> tuple[float, float, float]:
    """(steering, throttle, lateral) in [-1, 1] from a decoded RC_CHANNELS_OVERRIDE (NaN: not overridden)."""
    channels = [message.chan1_raw, message.chan2_raw, message.chan3_raw, message.chan4_raw]
    return tuple(pwm_to_normalised(channels[c - 1]) for c in (CHANNEL_STEERING, CHANNEL_THROTTLE, CHANNEL_LATERAL))


def thrust_from_rc(message, max_thrust_n: float) -> tuple[float, float]:
    """Body-frame thrust (x forward, y left; N) a vectored buoy applies for an RC_CHANNELS_OVERRIDE: the inverse
    of `rc_override_for_thrust` (up to PWM quantization, 1/400 of the maximum); channels not overridden: 0."""
    _steering, throttle, lateral = rc_axes(message)
    x = 0.0 if math.isnan(throttle) else throttle * max_thrust_n
    y = 0.0 if math.isnan(lateral) else -lateral * max_thrust_n
    return x, y


def wheels_from_rc(message, max_wheel_speed_mps: float) -> tuple[float, float]:
    """(left, right) wheel speeds (m/s) a skid-steer rover applies for an RC_CHANNELS_OVERRIDE, by ArduPilot's
    mixing (left = throttle + steering, right = throttle - steering, each clipped to [-1, 1]); the inverse of
    `rc_override_for_wheels` up to PWM quantization."""
    steering, throttle, _lateral = rc_axes(message)
    throttle = 0.0 if math.isnan(throttle) else throttle
    steering = 0.0 if math.isnan(steering) else steering
    left = min(1.0, max(-1.0, throttle + steering))
    right = min(1.0, max(-1.0, throttle - steering))
    return left * max_wheel_speed_mps, right * max_wheel_speed_mps


def wheels_from_manual_control(message, max_wheel_speed_mps: float) -> tuple[float, float]:
    """(left, right) wheel speeds (m/s) for a MANUAL_CONTROL (z throttle, y steering, each -1000..1000)."""
    throttle = 0.0 if message.z == 32767 else message.z / 1000.0
    steering = 0.0 if message.y == 32767 else message.y / 1000.0
    left = min(1.0, max(-1.0, throttle + steering))
    right = min(1.0, max(-1.0, throttle - steering))
    return left * max_wheel_speed_mps, right * max_wheel_speed_mps
