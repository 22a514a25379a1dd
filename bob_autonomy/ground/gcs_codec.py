"""MAVLink 2 framing, checking and signing for one endpoint (`MavlinkCodec`), its counters, and signing keys.

Used by the vessel's ground-station component (`bob_autonomy.ground.gcs`) and by mission scripts
(`bob_autonomy.ground.mission`). Signing: with a key, every frame we send is MAVLink 2 signed, and a received frame
is accepted only if it is signed with the key (SHA-256 of key + frame, first 48 bits) and its timestamp is
newer than the last one accepted from the same (link id, system, component); a stream not seen before must
not be more than 60 s older than our own clock. Unsigned (`unsigned_rejected`), wrongly signed
(`bad_signature`) and replayed or stale (`replay_rejected`) frames are counted and dropped. RADIO_STATUS and
RADIO, which telemetry radios inject unsigned, are let through as MAVProxy does, but are not counted as
`authenticated`: only frames that carried the key (every accepted frame when there is none) are, and only
they may make their sender a peer of a link (`firmware_bridge.links.UdpLink.confirm_peer`). The signature
is checked before the timestamp is recorded, so a forged frame cannot advance a stream. Without a key
everything well-formed is accepted, signed or not (signatures then unchecked).
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.decoder import classify_frame, next_marker
from firmware_bridge.frames import frame_checksum

__all__ = [
    "ALLOWED_UNSIGNED",
    "GcsCounters",
    "MavlinkCodec",
    "SigningKeyError",
    "load_signing_key",
    "passphrase_to_key",
    "signing_timestamp",
]

logger = logging.getLogger(__name__)

SIGNING_EPOCH_UNIX_S = 1420070400  # 2015-01-01 00:00:00 UTC: MAVLink 2 signing timestamps count from here
NEW_STREAM_WINDOW = 60 * 100_000  # 60 s in the signing timestamp's 10 us units
ALLOWED_UNSIGNED = frozenset({mavlink.MAVLINK_MSG_ID_RADIO_STATUS, mavlink.MAVLINK_MSG_ID_RADIO})

_V1 = mavlink.PROTOCOL_MARKER_V1
_V2 = mavlink.PROTOCOL_MARKER_V2
_SIGNED = mavlink.MAVLINK_IFLAG_SIGNED
_SIG_LEN = mavlink.MAVLINK_SIGNATURE_BLOCK_LEN  # 13: link id, 6-byte timestamp, 6-byte signature
_HEADER_LEN = {_V1: mavlink.HEADER_LEN_V1, _V2: mavlink.HEADER_LEN_V2}
_MAX_BUFFER = 65536


def _as_mavlink2(frame: bytes) -> bytes:
    """A whole MAVLink 1 frame re-framed as an unsigned MAVLink 2 one (the frame itself when it is not whole or
    its message id is unknown). MAVLink 2 drops the payload's trailing zero bytes but keeps at least one."""
    header = _HEADER_LEN[_V1]
    if len(frame) < header + 2 or len(frame) != header + frame[1] + 2:
        return frame
    msg_type = mavlink.mavlink_map.get(frame[5])
    if msg_type is None:
        return frame
    payload = frame[header : header + frame[1]].rstrip(b"\0") or b"\0"
    seq, system, component, msg_id = frame[2], frame[3], frame[4], frame[5]
    out = bytearray((_V2, len(payload), 0, 0, seq, system, component, msg_id, 0, 0)) + payload
    out += frame_checksum(out, len(out), msg_type.crc_extra).to_bytes(2, "little")
    return bytes(out)


# -- signing keys ---------------------------------------------------------------------------------------------


class SigningKeyError(ValueError):
    """A signing key file could not be read or used; the message names the file."""


def passphrase_to_key(passphrase: str) -> bytes:
    """The 32-byte key MAVProxy's `signing setup PASSPHRASE` / `signing key PASSPHRASE` derive: SHA-256 of
    the passphrase's bytes (UTF-8; MAVProxy passes ASCII)."""
    return hashlib.sha256(passphrase.encode("utf-8")).digest()


def load_signing_key(path: str | os.PathLike[str]) -> bytes:
    """Read a signing key file: exactly 32 bytes are the raw key; anything else is a passphrase (UTF-8
    text, surrounding white space and the final newline stripped) whose SHA-256 is the key, as MAVProxy
    derives it. SigningKeyError for a missing, unreadable or empty file."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise SigningKeyError(f"cannot read signing key file {p}: {exc}") from exc
    if len(data) == 32:
        return data
    try:
        passphrase = data.decode("utf-8").strip()
    except UnicodeDecodeError:
        raise SigningKeyError(
            f"signing key file {p}: {len(data)} bytes that are not UTF-8 text: neither a 32-byte raw key nor a "
            "passphrase"
        ) from None
    if not passphrase:
        raise SigningKeyError(f"signing key file {p} is empty")
    return passphrase_to_key(passphrase)


def signing_timestamp(unix_time_s: float) -> int:
    """A MAVLink 2 signing timestamp (10 us units since 2015-01-01 UTC) from a Unix time in seconds."""
    return int((max(float(unix_time_s), SIGNING_EPOCH_UNIX_S) - SIGNING_EPOCH_UNIX_S) * 100_000)


# -- counters and the codec -----------------------------------------------------------------------------------


@dataclass
class GcsCounters:
    """What a codec / component has seen. Frames: every complete candidate frame (`frames`) is exactly one
    of `accepted`, `malformed` (bad checksum, header, length or payload), `unknown_id` (a message id the
    dialect does not know), `unsigned_rejected`, `bad_signature`, `replay_rejected`; `authenticated` counts
    the accepted frames that carried the key (all of them without a key). `skipped_bytes` is
    noise between frames. The component adds what it did with accepted messages; `out_of_range` counts the
    messages it refused for a value that is not finite or outside its field's range (bob_autonomy.ground.gcs_checks).
    `SECURITY` names the counters an operator should see (logged and reported by process fleets)."""

    SECURITY = ("unsigned_rejected", "bad_signature", "replay_rejected", "malformed", "out_of_range")

    bytes_received: int = 0
    frames: int = 0
    accepted: int = 0
    authenticated: int = 0
    malformed: int = 0
    unknown_id: int = 0
    skipped_bytes: int = 0
    unsigned_rejected: int = 0
    bad_signature: int = 0
    replay_rejected: int = 0
    sent: int = 0
    ignored_other_target: int = 0
    ignored_message: int = 0
    handler_errors: int = 0
    commands: int = 0
    commands_unsupported: int = 0
    commands_denied: int = 0
    autopilot_refused: int = 0  # commands passed on to the autopilot that it refused or left unanswered
    params_set: int = 0
    params_rejected: int = 0
    mission_uploads: int = 0
    mission_errors: int = 0
    mission_retries: int = 0
    dropped_outgoing: int = 0
    out_of_range: int = 0

    def security(self) -> dict[str, int]:
        """The counters of rejected input (`SECURITY`), by name."""
        return {name: int(getattr(self, name)) for name in self.SECURITY}


class MavlinkCodec:
    """MAVLink 2 framing, checking and signing for one endpoint (our system and component ids).

    `decode(data)` returns the messages completed by `data` (stream semantics: a partial frame waits for
    the next call; `datagram=True` drops a trailing partial frame instead, right for UDP where a datagram
    holds whole frames). `pack(message)` returns the bytes of one frame, signed when a key is set.
    Never raises from `decode`; see the module docstring for the signing rules.
    """

    def __init__(
        self,
        system_id: int,
        component_id: int,
        *,
        signing_key: bytes | None = None,
        link_id: int = 0,
        wall_clock: Callable[[], float] = time.time,
        counters: GcsCounters | None = None,
    ) -> None:
        if signing_key is not None and len(signing_key) != 32:
            raise SigningKeyError(f"a MAVLink 2 signing key is 32 bytes, got {len(signing_key)}")
        if not 1 <= system_id <= 255 or not 0 <= component_id <= 255:
            raise ValueError(f"bad MAVLink ids: system {system_id}, component {component_id}")
        self.signing_key = bytes(signing_key) if signing_key is not None else None
        self.wall_clock = wall_clock
        self.counters = counters if counters is not None else GcsCounters()
        self.mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        if self.signing_key is not None:
            self.mav.signing.secret_key = self.signing_key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.link_id = int(link_id) & 0xFF
            self.mav.signing.timestamp = signing_timestamp(wall_clock())
        self._decoder = mavlink.MAVLink(None)  # no key: signatures are checked here, not by pymavlink
        self._buf = bytearray()
        self.streams: dict[tuple[int, int, int], int] = {}  # (link id, system, component) -> last timestamp

    @property
    def system_id(self) -> int:
        return self.mav.srcSystem

    @property
    def component_id(self) -> int:
        return self.mav.srcComponent

    # -- sending -------------------------------------------------------------------------------------------

    def pack(self, message: mavlink.MAVLink_message) -> bytes:
        """One frame from this endpoint, with the next sequence number (and a signature when keyed)."""
        if self.signing_key is not None:
            # Timestamps must increase and should follow the wall clock (the receiver compares new streams
            # with its own clock); pymavlink adds one per frame.
            self.mav.signing.timestamp = max(self.mav.signing.timestamp, signing_timestamp(self.wall_clock()))
        data = bytes(message.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        self.counters.sent += 1
        return data

    def sign_routed(self, frame: bytes) -> bytes:
        """Another component's frame (the autopilot's, routed to the ground station) as this link sends it.

        Without a key: unchanged. With one, an unsigned MAVLink 2 frame gets the signed flag, its checksum
        redone (the flag is under the checksum) and this link's signature (link id, the next timestamp, the first
        48 bits of SHA-256(key + frame + link id + timestamp)), so that a ground station taking only signed frames
        (MAVProxy's `set allow_unsigned 0`) hears the autopilot behind the vessel too, and no one can pass off
        frames as the autopilot's on this link. A MAVLink 1 frame (an autopilot port set to MAVLink 1, e.g.
        ArduPilot's SERIALn_PROTOCOL 1) has no room for a signature: it is re-framed as MAVLink 2 first (same
        sequence, system, component, message and payload; the payload's zero tail cut as MAVLink 2 does), so a
        strict ground station hears it too. A frame already signed, or one of a message id the dialect does not
        know (no CRC_EXTRA to redo its checksum), is left as it is."""
        key = self.signing_key
        if key is None:
            return frame
        if frame[:1] == bytes((_V1,)):
            frame = _as_mavlink2(frame)
        if len(frame) < _HEADER_LEN[_V2] + 2 or frame[0] != _V2 or frame[2] & _SIGNED:
            return frame
        msg_type = mavlink.mavlink_map.get(frame[7] | (frame[8] << 8) | (frame[9] << 16))
        if msg_type is None:
            return frame
        out = bytearray(frame)
        out[2] |= _SIGNED
        crc_at = len(out) - 2
        out[crc_at:] = frame_checksum(out, crc_at, msg_type.crc_extra).to_bytes(2, "little")
        signing = self.mav.signing
        timestamp = max(signing.timestamp, signing_timestamp(self.wall_clock()))
        signing.timestamp = timestamp + 1  # one clock for our own frames and the routed ones: always increasing
        out += bytes((signing.link_id,)) + timestamp.to_bytes(6, "little")
        out += hashlib.sha256(key + bytes(out)).digest()[:6]
        return bytes(out)

    # -- receiving -----------------------------------------------------------------------------------------

    def decode(self, data: bytes, *, datagram: bool = False) -> list[mavlink.MAVLink_message]:
        """Messages completed by `data`, in order; everything else counted (never raises)."""
        messages: list[mavlink.MAVLink_message] = []
        try:
            self.counters.bytes_received += len(data)
            self._buf.extend(data)
            self._frame(messages)
            if datagram or len(self._buf) > _MAX_BUFFER:
                self.counters.skipped_bytes += len(self._buf)
                self._buf.clear()
        except Exception:  # defensive: nothing escapes into the caller
            logger.debug("MAVLink decode failed", exc_info=True)
            self.counters.malformed += 1
            self.counters.skipped_bytes += len(self._buf)
            self._buf.clear()
        return messages

    def _frame(self, messages: list[mavlink.MAVLink_message]) -> None:
        c = self.counters
        buf = self._buf
        n = len(buf)
        pos = 0
        while pos < n:
            start = next_marker(buf, pos)
            if start < 0:
                c.skipped_bytes += n - pos
                pos = n
                break
            c.skipped_bytes += start - pos
            pos = start
            magic = buf[pos]
            if n - pos < 3:
                break
            length = _HEADER_LEN[magic] + buf[pos + 1] + 2
            if magic == _V2 and buf[pos + 2] & _SIGNED:
                length += _SIG_LEN
            if n - pos < length:
                break  # wait for the rest
            frame = bytearray(buf[pos : pos + length])
            c.frames += 1
            end = pos + length
            verdict, msg = classify_frame(frame, self._decoder, followed=end == n or buf[end] in (_V1, _V2))
            if verdict in ("bad_crc", "malformed"):
                c.malformed += 1
                c.skipped_bytes += 1
                pos += 1  # resynchronise one byte on: a real frame may start inside this one
                continue
            pos += length
            if verdict == "unknown":
                c.unknown_id += 1
                continue
            rejection = self._authenticate(frame, magic)
            if rejection is not None:
                setattr(c, rejection, getattr(c, rejection) + 1)
                continue
            c.accepted += 1
            if self.signing_key is None or (magic == _V2 and frame[2] & _SIGNED):
                c.authenticated += 1
            messages.append(msg)
        del buf[:pos]

    def _authenticate(self, frame: bytearray, magic: int) -> str | None:
        """None if the frame may be used, else the name of the counter of its rejection."""
        key = self.signing_key
        if key is None:
            return None
        signed = magic == _V2 and bool(frame[2] & _SIGNED)
        if not signed:
            msg_id = (frame[7] | (frame[8] << 8) | (frame[9] << 16)) if magic == _V2 else frame[5]
            return None if msg_id in ALLOWED_UNSIGNED else "unsigned_rejected"
        expected = hashlib.sha256(key + bytes(frame[:-6])).digest()[:6]
        if not hmac.compare_digest(expected, bytes(frame[-6:])):
            return "bad_signature"
        link_id = frame[-13]
        timestamp = int.from_bytes(frame[-12:-6], "little")
        stream = (link_id, frame[5], frame[6])  # v2 header: system at 5, component at 6
        last = self.streams.get(stream)
        if last is None:
            now = max(self.mav.signing.timestamp, signing_timestamp(self.wall_clock()))
            if timestamp + NEW_STREAM_WINDOW < now:
                return "replay_rejected"
        elif timestamp <= last:
            return "replay_rejected"
        self.streams[stream] = timestamp
        self.mav.signing.timestamp = max(self.mav.signing.timestamp, timestamp)
        return None
