"""Authenticated mesh packets: a fleet key, a per-sender timestamp and a truncated HMAC (issue 15).

Without authentication anyone with a radio on the fleet's channel can broadcast as any agent (the leader
of a leader-follower run included) and a recorded packet can be sent again later. With a fleet key every
packet carries, just before its CRC, a *signature trailer*:

    timestamp (uint48, little-endian, 10 us units of the mesh clock) | tag (8 bytes)

tag = HMAC-SHA256(key, every byte of the packet before the tag)[:8]: the header (version and length
included), the state, the memory fields and the timestamp. 64 bits of tag are far beyond what a radio at
XBee rates can brute-force (2^63 guesses on average, a few tens of packets a second).

The timestamp counts 10 us units like MAVLink 2 signing's (48 bits: 89 years). It comes from the *mesh
clock*, a time base every member shares: UTC (Unix time) from 2015-01-01 on a vessel (`unix_mesh_clock`;
the on-board computer keeps its clock disciplined by GPS or NTP, e.g. chrony), the simulated time in a
lockstep run. Each signer makes its timestamps strictly increasing (the last one + 1 when the clock has not
moved, as MAVLink signing does), so no two packets of one sender carry the same timestamp.

A receiver with the key accepts a packet only if (in this order, each failure counted per claimed sender
under its reason):

* ``unsigned``: it carries a signature trailer (packet version 2);
* ``bad_mac``: the tag is right for its bytes and the key;
* ``replay``: its timestamp is newer than the last one accepted from the same agent id;
* ``stale``: its timestamp is within `window_s` of the receiver's mesh clock (either side: a recording
  replayed later, or a clock far off).

The tag is checked before the timestamp is recorded, so a forged packet can never advance a sender's
stream. Keys are files in the MAVLink signing format (`bob_autonomy.ground.gcs_codec.load_signing_key`: 32 raw
bytes, or a passphrase whose SHA-256 is the key), so a fleet may reuse its ground-station signing key.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import time
from collections import Counter
from collections.abc import Callable

from bob_autonomy.ground.gcs_codec import SIGNING_EPOCH_UNIX_S, load_signing_key

__all__ = [
    "REASONS",
    "STAMP_BYTES",
    "TAG_BYTES",
    "TRAILER_BYTES",
    "AuthError",
    "MeshSigner",
    "MeshVerifier",
    "compute_tag",
    "load_mesh_key",
    "stamp_seconds",
    "unix_mesh_clock",
    "verify_tag",
]

STAMP_BYTES = 6  # uint48 timestamp, 10 us units
TAG_BYTES = 8  # truncated HMAC-SHA256
TRAILER_BYTES = STAMP_BYTES + TAG_BYTES
STAMP_UNITS_PER_S = 100_000
MAX_STAMP = (1 << (8 * STAMP_BYTES)) - 1
DEFAULT_WINDOW_S = 5.0  # a packet stamped further than this from the receiver's mesh clock is stale
REASONS = ("unsigned", "bad_mac", "replay", "stale")  # why a packet was refused, in the order checked


class AuthError(ValueError):
    """A packet refused by the fleet key's checks; `reason` is one of REASONS."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def load_mesh_key(path: str) -> bytes:
    """The 32-byte fleet key from a key file in the MAVLink signing format (32 raw bytes, or a passphrase);
    SigningKeyError naming the file when it cannot be read or is empty."""
    return load_signing_key(path)


def unix_mesh_clock() -> float:
    """The mesh clock on a vessel: seconds since 2015-01-01 UTC (the MAVLink signing epoch), from the system
    clock, which must be kept within the freshness window of the other vessels' (GPS or NTP time)."""
    return time.time() - SIGNING_EPOCH_UNIX_S


def _stamp_of(seconds: float) -> int:
    """10 us units of a mesh-clock reading (s), clamped into the 48-bit range."""
    if not math.isfinite(seconds):
        raise ValueError(f"mesh clock reading {seconds!r} is not finite")
    return min(MAX_STAMP, max(0, round(seconds * STAMP_UNITS_PER_S)))


def stamp_seconds(stamp: int) -> float:
    """A timestamp (10 us units) as mesh-clock seconds."""
    return stamp / STAMP_UNITS_PER_S


def compute_tag(key: bytes, data: bytes) -> bytes:
    """The 8-byte tag of `data` (every packet byte before the tag) under `key`."""
    return hmac.new(key, data, hashlib.sha256).digest()[:TAG_BYTES]


def _check_key(key: bytes) -> bytes:
    if not isinstance(key, bytes | bytearray) or len(key) != 32:
        raise ValueError(f"a mesh key is 32 bytes, got {len(key) if isinstance(key, bytes | bytearray) else key!r}")
    return bytes(key)


def verify_tag(key: bytes, agent_id: int, signed: bytes | None) -> int:
    """The timestamp of a packet's signed part (its bytes before the CRC; None when it has no trailer) whose
    tag is right under `key`; AuthError ``unsigned`` or ``bad_mac`` otherwise. Stateless: replay and
    freshness are `MeshVerifier`'s (or the lockstep medium's, per listener)."""
    if signed is None:
        raise AuthError("unsigned", f"agent {agent_id}: packet carries no signature; the mesh has a key")
    if len(signed) < TRAILER_BYTES:
        raise AuthError("bad_mac", f"agent {agent_id}: signed part of {len(signed)} bytes is too short")
    body, tag = signed[:-TAG_BYTES], signed[-TAG_BYTES:]
    if not hmac.compare_digest(tag, compute_tag(key, body)):
        raise AuthError("bad_mac", f"agent {agent_id}: wrong tag (another key, or bytes changed in transit)")
    return int.from_bytes(body[-STAMP_BYTES:], "little")


class MeshSigner:
    """Appends the signature trailer to this sender's packets.

    key: the 32-byte fleet key. clock: the mesh clock, s (`unix_mesh_clock` on a vessel, simulated time in a
    lockstep run).
    """

    def __init__(self, key: bytes, clock: Callable[[], float] = unix_mesh_clock) -> None:
        self.key, self.clock = _check_key(key), clock
        self.last_stamp = -1

    def next_stamp(self) -> int:
        """A timestamp newer than every one this signer has used (the clock's, or the last + 1)."""
        stamp = max(self.last_stamp + 1, _stamp_of(float(self.clock())))
        if stamp > MAX_STAMP:
            raise ValueError("the 48-bit mesh timestamp has run out (clock beyond 2104?)")
        self.last_stamp = stamp
        return stamp

    def sign(self, data: bytes) -> bytes:
        """`data` (a packet up to its trailer, already with the signed version and the final length) with the
        timestamp and tag appended."""
        signed = data + self.next_stamp().to_bytes(STAMP_BYTES, "little")
        return signed + compute_tag(self.key, signed)


class MeshVerifier:
    """Checks the signature trailer of received packets and keeps, per sender, the newest timestamp accepted.

    key: the fleet key. clock: the mesh clock, s. window_s: how far (s) a timestamp may be from the clock.
    `rejected[reason][agent_id]` counts the refused packets (REASONS) by the sender id they claimed;
    `accepted` counts the packets that passed.
    """

    def __init__(
        self, key: bytes, clock: Callable[[], float] = unix_mesh_clock, window_s: float = DEFAULT_WINDOW_S
    ) -> None:
        if not window_s > 0:
            raise ValueError(f"the freshness window must be positive, got {window_s!r} s")
        self.key, self.clock, self.window_s = _check_key(key), clock, float(window_s)
        self.last_stamp: dict[int, int] = {}
        self.rejected: dict[str, Counter[int]] = {reason: Counter() for reason in REASONS}
        self.accepted = 0

    def check(self, agent_id: int, signed: bytes | None) -> int:
        """The timestamp of a packet from `agent_id` whose bytes before the CRC are `signed` (None: the packet
        carries no trailer); AuthError (counted) if it must be refused. The sender's stream advances only
        for a packet that passes every check."""
        try:
            stamp = self._check(agent_id, signed)
        except AuthError as error:
            self.rejected[error.reason][agent_id] += 1
            raise
        self.last_stamp[agent_id] = stamp
        self.accepted += 1
        return stamp

    def _check(self, agent_id: int, signed: bytes | None) -> int:
        stamp = verify_tag(self.key, agent_id, signed)
        last = self.last_stamp.get(agent_id)
        if last is not None and stamp <= last:
            raise AuthError(
                "replay",
                f"agent {agent_id}: timestamp {stamp_seconds(stamp):.5f} s is not newer than the last accepted "
                f"({stamp_seconds(last):.5f} s)",
            )
        offset = stamp_seconds(stamp) - float(self.clock())
        if abs(offset) > self.window_s:
            raise AuthError(
                "stale",
                f"agent {agent_id}: timestamp {offset:+.3f} s from this receiver's mesh clock, outside the "
                f"+-{self.window_s:g} s window (a recording, or clocks not synchronized: check GPS/NTP time)",
            )
        return stamp

    def counters(self) -> dict[str, dict[str, int]]:
        """`rejected` as plain dicts (reason -> {agent id as text -> count}), for logs and metrics.json."""
        return {reason: {str(k): v for k, v in sorted(c.items())} for reason, c in self.rejected.items()}
