"""A mission client with a signing key is not led astray by frames that prove nothing of their sender: an
unsigned RADIO_STATUS (let through, as MAVLink signing allows for radios) claiming to be a vessel's autonomy
component must not move that vessel's reply address (issue #17, item 2, on the mission-script side)."""

from __future__ import annotations

import socket
import time

import pytest

from bob_autonomy.ground.gcs_codec import MavlinkCodec
from bob_autonomy.ground.mission import MissionClient

pytestmark = pytest.mark.xdist_group("realtime")
KEY = bytes(range(32))


def test_an_unsigned_radio_status_does_not_move_a_vessels_address() -> None:
    client = MissionClient("udpin:127.0.0.1:0", signing_key=KEY)
    port = client.local_address[1]
    vessel, attacker = (socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2))
    try:
        for s in (vessel, attacker):
            s.bind(("127.0.0.1", 0))
        signed = MavlinkCodec(1, 191, signing_key=KEY)
        vessel.sendto(signed.pack(signed.mav.heartbeat_encode(18, 0, 0, 0, 4)), ("127.0.0.1", port))
        assert client.discover(1, timeout_s=5.0) == [1]
        forged = MavlinkCodec(1, 191)  # no key: an unsigned frame, as anyone can send
        for _ in range(5):
            attacker.sendto(forged.pack(forged.mav.radio_status_encode(200, 200, 100, 0, 0, 0, 0)), ("127.0.0.1", port))
        time.sleep(0.5)
        assert client._vessels[1].address == vessel.getsockname()
    finally:
        client.close()
        vessel.close()
        attacker.close()
