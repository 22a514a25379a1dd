"""MAVLink 2 signing against a ground station we did not write: MAVProxy's `signing key` module.

The autonomy process reads its key from a file, and docs/gcs-protocol.md says a passphrase in that file gives the
key MAVProxy derives from the same passphrase. Until now only our own mission client (bob_autonomy.ground.mission)
had signed frames for it, so a mistake in the key derivation, the signature or the timestamps would have been made
on both sides and passed. Here MAVProxy signs and checks instead:

- with the fleet's passphrase (spaces and all: MAVProxy's console takes it in double quotes), and told to take
  signed frames only (`set allow_unsigned 0`; MAVProxy's default takes unsigned ones too), it finds the vessel's
  autonomy component and the autopilot behind it, fetches both parameter sets and sets one, every frame checked
  by the vessel and by MAVProxy: the autopilot's frames, which the vessel routes to the ground station, are signed
  by the vessel (`MavlinkCodec.sign_routed`; unsigned before, so such a MAVProxy heard only component 191);
- with another passphrase it hears nothing (the vessel answers only ground stations whose frames pass its checks)
  and changes nothing; the vessel counts its frames as wrongly signed.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
from mavproxy_session import MAVPROXY, MavproxySession
from vessel_helpers import ORIGIN, StandInVehicle

from bob_autonomy.core.behavior_config import BehaviorChoice
from bob_autonomy.core.clock import ScaledWallClock
from bob_autonomy.onboard.vessel import Vessel, VesselConfig

pytestmark = [
    pytest.mark.skipif(MAVPROXY is None, reason="MAVProxy is not installed (pip install -e '.[dev]')"),
    pytest.mark.xdist_group("realtime"),  # real time and processes: never beside the other real-time tests
]

PASSPHRASE = "a long passphrase only the fleet knows"  # the example of docs/gcs-protocol.md


@pytest.fixture
def signed_vessel(tmp_path: Path):
    """A vessel whose ground-station link (udpin) takes only frames signed with PASSPHRASE's key, beside a
    stand-in autopilot; yields (vessel, its ground-station port, the stand-in)."""
    key_file = tmp_path / "bob.key"
    key_file.write_text(PASSPHRASE + "\n")
    vehicle = StandInVehicle()
    vehicle.start()
    config = VesselConfig(
        vehicle=f"udpout:127.0.0.1:{vehicle.port}",
        system_id=1,
        behavior=BehaviorChoice(behavior="bob-rule", params={"p0": 10.0}),
        origin=ORIGIN,
        controller="simple",
        gcs="udpin:127.0.0.1:0",
        autostart=False,
        signing_key_file=str(key_file),
    )
    vessel = Vessel(config, clock=ScaledWallClock(1.0))
    runner = threading.Thread(target=vessel.run, daemon=True)
    runner.start()
    try:
        yield vessel, vessel.gcs_link.local_address[1], vehicle
    finally:
        vessel.stop()
        runner.join(5.0)
        vehicle.close()


def _signed_session(port: int, cwd: Path, passphrase: str) -> MavproxySession:
    session = MavproxySession(f"udpout:127.0.0.1:{port}", cwd)
    session.send("set param_ftp 0")  # neither component serves MAVFTP: the parameter protocol at once
    session.send("set allow_unsigned 0")  # signed frames only (RADIO_STATUS aside)
    session.command(f'signing key "{passphrase}"', r"Setup signing key")
    return session


def _heard(session: MavproxySession, timeout_s: float) -> tuple[set[str], list[int]]:
    """The components MAVProxy detected and the parameter counts it received, once it has both components and
    two parameter sets (in whatever order it prints them)."""
    detected: set[str] = set()
    counts: list[int] = []
    deadline = time.monotonic() + timeout_s
    while len(detected) < 2 or len(counts) < 2:
        found = session.expect(r"Detected vehicle (1:\d+)|Received (\d+) parameters", deadline - time.monotonic())
        if found.group(1):
            detected.add(found.group(1))
        else:
            counts.append(int(found.group(2)))
    return detected, counts


def test_mavproxy_with_the_fleet_passphrase_reads_and_sets_the_parameters_of_a_signed_vessel(
    signed_vessel, tmp_path: Path
) -> None:
    vessel, port, stand_in = signed_vessel
    session = _signed_session(port, tmp_path, PASSPHRASE)
    try:
        detected, counts = _heard(session, 40.0)
        assert detected == {"1:1", "1:191"}
        assert sorted(counts) == sorted([len(vessel.params), len(stand_in.vehicle.params)])
        session.send("param set BOB_P0_M 7.5")
        deadline = time.monotonic() + 10.0
        while vessel.params.get("BOB_P0_M") != 7.5:
            assert time.monotonic() < deadline, "the signed PARAM_SET never reached the vessel"
            time.sleep(0.2)
    finally:
        session.close()
    counters = vessel.gcs.counters
    # What MAVProxy sent before it had the key went unsigned and was dropped; everything after was signed
    # with the key the vessel derived from the same passphrase, and none of it failed the check.
    assert counters.authenticated > 0 and counters.params_set == 1
    assert counters.bad_signature == 0 and counters.replay_rejected == 0


def test_mavproxy_with_another_passphrase_hears_nothing_and_changes_nothing(signed_vessel, tmp_path: Path) -> None:
    vessel, port, _ = signed_vessel
    session = _signed_session(port, tmp_path, "not the fleet passphrase")
    try:
        deadline = time.monotonic() + 8.0
        while vessel.gcs.counters.bad_signature < 5:  # MAVProxy's heartbeats, once a second, now signed
            assert time.monotonic() < deadline, f"no wrongly signed frames counted: {vessel.gcs.counters}"
            time.sleep(0.2)
        session.send("param set BOB_P0_M 7.5")
        with pytest.raises(AssertionError, match="never printed"):
            session.expect(r"Detected vehicle 1:191", 3.0)
    finally:
        session.close()
    counters = vessel.gcs.counters
    assert counters.authenticated == 0 and counters.accepted == 0 and counters.params_set == 0
    assert vessel.params.get("BOB_P0_M") == 10.0
