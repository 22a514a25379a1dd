"""A ground station we did not write (MAVProxy) reaches the real ArduPilot through the vessel, over a signed link.

The vessel routes between its ground-station link and the autopilot, as mavlink-router would on a companion
computer (bob_autonomy/onboard/vessel_links.py); until now only our simulated autopilot stood behind it. Here
ArduPilot's own Rover SITL does: MAVProxy, signing with the fleet's passphrase and taking signed frames only,
detects the autopilot (1:1) and the autonomy (1:191), fetches every one of ArduPilot's parameters through the
vessel (hundreds of PARAM_VALUEs in a burst, each routed and signed by the vessel) and sets one; the autopilot's own
report of the new value on its second serial port (the harness's observer) is the judge.

Skipped unless ARDUPILOT_SITL names a built `ardurover` (docs/ardupilot.md).
"""

from __future__ import annotations

import threading
import time

import pytest
from mavproxy_session import MAVPROXY, heard, signed_session
from sitl_harness import BINARY, NEEDS_SITL, RoverSitl, vessel_config

from bob_autonomy.onboard.vessel import Vessel

pytestmark = [
    *NEEDS_SITL,
    pytest.mark.skipif(MAVPROXY is None, reason="MAVProxy is not installed (pip install -e '.[dev]')"),
]
PASSPHRASE = "a long passphrase only the fleet knows"


def test_mavproxy_fetches_and_sets_real_ardupilots_parameters_through_a_signed_vessel(tmp_path) -> None:
    key_file = tmp_path / "bob.key"
    key_file.write_text(PASSPHRASE + "\n")
    with RoverSitl(BINARY, "omni", tmp_path) as sitl:
        sitl.wait_initialised()
        config = vessel_config(sitl, gcs="udpin:127.0.0.1:0", signing_key_file=str(key_file))
        vessel = Vessel(config)
        runner = threading.Thread(target=vessel.run, kwargs={"duration_s": 120.0}, daemon=True)
        runner.start()
        session = signed_session(vessel.gcs_link.local_address[1], tmp_path, PASSPHRASE, component=1)
        try:
            # MAVProxy fetches the parameters of its target (1:1) and, depending on which it detects first, also
            # those of component 191: wait for both components and for ArduPilot's set.
            detected, counts = heard(session, 60.0, lambda found, sets: len(found) == 2 and max(sets, default=0) > 500)
            assert detected == {"1:1", "1:191"}
            before = sitl.seen.params.get("MOT_SLEWRATE")
            session.send("param set MOT_SLEWRATE 37")
            deadline = time.monotonic() + 15.0
            while sitl.seen.params.get("MOT_SLEWRATE") != 37.0:
                assert time.monotonic() < deadline, f"ArduPilot never reported MOT_SLEWRATE 37 (was {before})"
                time.sleep(0.2)
        finally:
            session.close()
            vessel.stop()
            runner.join(10.0)
    ardupilot_count = max(counts)  # component 191 has 17 parameters, ArduPilot hundreds
    assert set(counts) <= {len(vessel.params), ardupilot_count}
    assert sitl.seen.param_count == ardupilot_count  # what ArduPilot says it has, on its own port
    counters = vessel.gcs.counters
    print(f"\nMAVProxy through the vessel: {counts} parameters; vessel {vessel.stats}; gcs {counters.security()}")
    assert counters.bad_signature == 0 and counters.replay_rejected == 0 and counters.authenticated > 0
    assert vessel.stats.routed_to_gcs > ardupilot_count and vessel.stats.routed_to_vehicle > 0


def test_a_strict_mavproxy_hears_an_autopilot_whose_port_speaks_mavlink1_through_a_signed_vessel(tmp_path) -> None:
    """SERIAL0_PROTOCOL 1: ArduPilot sends MAVLink 1 frames, which have no room for a signature. Routed as they
    came, MAVProxy with `allow_unsigned 0` dropped every one and heard only the vessel (1:191); the vessel now
    re-frames them as MAVLink 2 and signs them (MavlinkCodec.sign_routed)."""
    key_file = tmp_path / "bob.key"
    key_file.write_text(PASSPHRASE + "\n")
    with RoverSitl(BINARY, "omni", tmp_path, params={"SERIAL0_PROTOCOL": 1}) as sitl:
        sitl.wait_initialised()
        config = vessel_config(sitl, gcs="udpin:127.0.0.1:0", signing_key_file=str(key_file))
        vessel = Vessel(config)
        markers: list[int] = []  # the first byte of each autopilot frame the vessel routed, as it arrived
        sign_routed = vessel.gcs.codec.sign_routed

        def spy(frame: bytes) -> bytes:
            markers.append(frame[0])
            return sign_routed(frame)

        vessel.gcs.codec.sign_routed = spy
        runner = threading.Thread(target=vessel.run, kwargs={"duration_s": 90.0}, daemon=True)
        runner.start()
        session = signed_session(vessel.gcs_link.local_address[1], tmp_path, PASSPHRASE, component=1)
        try:
            detected, counts = heard(session, 60.0, lambda found, sets: len(found) == 2 and max(sets, default=0) > 500)
        finally:
            session.close()
            vessel.stop()
            runner.join(10.0)
    assert detected == {"1:1", "1:191"}
    assert max(counts) == sitl.seen.param_count  # every one of ArduPilot's parameters, fetched over MAVLink 1
    v1 = sum(marker == 0xFE for marker in markers)
    print(f"\nrouted {len(markers)} autopilot frames, {v1} of them MAVLink 1; gcs {vessel.gcs.counters.security()}")
    assert v1 > 0.9 * len(markers) > 500
