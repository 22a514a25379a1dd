"""RC_CHANNELS_OVERRIDE for a whole lockstep fleet at once, both ways: the vessels' carried whole units and PWMs
as arrays, and the autopilots' reading of one override frame each without a pymavlink message object.

Why: a 45-vessel lockstep step sends one override per vessel, and building, framing, checking and decoding them
one object at a time was a fifth of the full stack's step (`benchmarks/aggregation_speed.py --profile`, "MAVLink
down"). What it guarantees: the same numbers and bytes as the one-at-a-time path (`ResolutionCarry`,
`RcChannelRange.pwm_for`, `TelemetryDecoder.feed_messages`), checked by tests/test_override_batch.py; anything
the fast path does not cover is handed back for the usual path.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import cache

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.batch_decoder import checked_frames
from firmware_bridge.decoder import TelemetryDecoder
from firmware_bridge.frames import V2_HEADER_LEN, layout
from firmware_bridge.rc_channels import THROTTLE_FULL_SCALE, RcChannelRange, ResolutionCarry

OVERRIDE_ID = mavlink.MAVLINK_MSG_ID_RC_CHANNELS_OVERRIDE
_OVERRIDE = layout(OVERRIDE_ID)
_CRC_LEN = 2


def carried_units(
    carries: Sequence[ResolutionCarry], channel: object, values: np.ndarray, full_scale: int = THROTTLE_FULL_SCALE
) -> np.ndarray:
    """What `carries[k](channel, values[k], full_scale)` returns, times full_scale, for every k at once: the whole
    units (float array) each link sends, its error diffusion advanced as the call would (same IEEE operations, so
    the same numbers: u = clip(v, -1, 1) * full_scale + owed, units = round half away from zero, clipped to
    +-full_scale, owed = clip(u - units, -0.5, 0.5); a value of 0 or not finite sends 0 and clears the debt)."""
    v = np.asarray(values, dtype=float)
    owed = np.array([carry.owed(channel) for carry in carries], dtype=float)
    live = np.isfinite(v) & (v != 0.0)
    target = np.clip(np.where(live, v, 0.0), -1.0, 1.0) * full_scale + owed
    units = np.clip(np.copysign(np.floor(np.abs(target) + 0.5), target), -full_scale, full_scale)
    debt = np.clip(target - units, -0.5, 0.5)
    for carry, is_live, left in zip(carries, live.tolist(), debt.tolist(), strict=True):
        carry.set_owed(channel, left if is_live else None)
    return np.where(live, units, 0.0)


@cache
def pwm_table(calibration: RcChannelRange, full_scale: int) -> np.ndarray:
    """`calibration.pwm_for(k / full_scale, full_scale)` for k = -full_scale .. full_scale (index k + full_scale):
    the PWM of each whole unit, looked up by `carried_units`' results."""
    units = range(-full_scale, full_scale + 1)
    return np.array([calibration.pwm_for(k / full_scale, full_scale) for k in units], dtype=np.int64)


def read_overrides(decoders: Sequence[TelemetryDecoder], chunks: Sequence[bytes]) -> list[tuple | None]:
    """Each chunk that is one whole, unsigned MAVLink 2 RC_CHANNELS_OVERRIDE frame with a good checksum, for a
    decoder with nothing pending, no message hook and no signing key: (source system, source component, the
    message's fields in declaration order), counted in that decoder as `feed_messages` counts it. Any other
    chunk: None, its decoder untouched (feed it as usual)."""
    found: list[tuple | None] = []
    for decoder, chunk in zip(decoders, chunks, strict=True):
        frames: list = []
        if (
            decoder._buf
            or decoder.message_hook is not None
            or decoder._mav.signing.secret_key is not None
            or not checked_frames(chunk, 0, frames)
            or len(frames) != 1
            or frames[0][3] != OVERRIDE_ID
        ):
            found.append(None)
            continue
        n = len(chunk)
        c = decoder.counters
        c.bytes_fed += n
        c.received += 1
        c.frame_bytes += n
        c.decoded += 1
        c.by_type[_OVERRIDE.name] = c.by_type.get(_OVERRIDE.name, 0) + 1
        c.pending_bytes = 0
        found.append((chunk[5], chunk[6], _OVERRIDE.fields(chunk[V2_HEADER_LEN : n - _CRC_LEN])))
    return found
