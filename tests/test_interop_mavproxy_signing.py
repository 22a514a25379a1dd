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
  and changes nothing; the vessel counts its frames as wrongly signed;
- over the signed link, the rest of the field engineer's session of docs/gcs-protocol.md: a fence and a rally
  point loaded from MAVProxy's own file formats, the fence enabled, the behaviour started and paused.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mavproxy_session import MAVPROXY, heard, signed_session
from vessel_helpers import ORIGIN, StandInVehicle, ground_station_vessel_config

from bob_autonomy.core.clock import ScaledWallClock
from bob_autonomy.onboard.vessel import Vessel

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
    config = ground_station_vessel_config(vehicle.port, signing_key_file=str(key_file))
    vessel = Vessel(config, clock=ScaledWallClock(1.0))
    runner = threading.Thread(target=vessel.run, daemon=True)
    runner.start()
    try:
        yield vessel, vessel.gcs_link.local_address[1], vehicle
    finally:
        vessel.stop()
        runner.join(5.0)
        vehicle.close()


def test_mavproxy_with_the_fleet_passphrase_reads_and_sets_the_parameters_of_a_signed_vessel(
    signed_vessel, tmp_path: Path
) -> None:
    vessel, port, stand_in = signed_vessel
    session = signed_session(port, tmp_path, PASSPHRASE)
    try:
        detected, counts = heard(session, 40.0)
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
    session = signed_session(port, tmp_path, "not the fleet passphrase")
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


def _fence_file(path: Path, vertices: list[tuple[float, float]], return_point: tuple[float, float]) -> Path:
    """MAVProxy's own fence file (pymavlink mavwp MissionItemProtocol_Fence.load): "lat lon" lines, the return
    point first and the first vertex again last (MAVProxy sends the lines between as one inclusion polygon)."""
    lines = [return_point, *vertices, vertices[0]]
    path.write_text("".join(f"{lat:.7f} {lon:.7f}\n" for lat, lon in lines))
    return path


def _wait_for(what: str, condition, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"never happened: {what}"
        time.sleep(0.1)


def test_mavproxy_over_a_signed_link_loads_a_fence_and_a_rally_point_then_starts_and_pauses_the_behaviour(
    signed_vessel, tmp_path: Path
) -> None:
    vessel, port, _ = signed_vessel
    lat, lon = ORIGIN
    vertices = [
        (lat - 0.001, lon - 0.001),
        (lat - 0.001, lon + 0.001),
        (lat + 0.001, lon + 0.001),
        (lat + 0.001, lon - 0.001),
    ]
    return_point, rally = (lat + 0.0002, lon - 0.0003), (lat - 0.0004, lon + 0.0005)
    fence = _fence_file(tmp_path / "fence.txt", vertices, return_point)
    (tmp_path / "rally.txt").write_text(f"RALLY {rally[0]:.7f} {rally[1]:.7f} 0 0 0 0\n")  # MAVProxy's rally format
    session = signed_session(port, tmp_path, PASSPHRASE)
    try:
        session.expect(r"Detected vehicle 1:191", 20.0)
        session.command(f"fence load {fence}", r"MISSION_ACK: TYPE_FENCE: ACCEPTED", 15.0)
        np.testing.assert_allclose(vessel.gcs.fence, vertices, atol=2e-7)  # degE7 on the wire
        rally_now = [vessel.params.get("BOB_RALLY_LAT"), vessel.params.get("BOB_RALLY_LON")]
        np.testing.assert_allclose(rally_now, return_point, atol=1e-6)  # the fence's return point
        session.command(f"rally load {tmp_path / 'rally.txt'}", r"MISSION_ACK: TYPE_RALLY: ACCEPTED", 15.0)
        rally_now = [vessel.params.get("BOB_RALLY_LAT"), vessel.params.get("BOB_RALLY_LON")]
        np.testing.assert_allclose(rally_now, rally, atol=1e-6)
        session.send("long DO_FENCE_ENABLE 1")
        _wait_for("BOB_FENCE_EN 1", lambda: vessel.params.get("BOB_FENCE_EN") == 1)
        assert vessel.gcs.fence_enabled
        session.send("long MISSION_START")
        _wait_for("the behaviour running", lambda: vessel.gcs.behavior_running)
        session.send("long DO_PAUSE_CONTINUE 0")
        _wait_for("the behaviour paused", lambda: not vessel.gcs.behavior_running)
    finally:
        session.close()
    counters = vessel.gcs.counters
    assert counters.mission_uploads == 2 and counters.mission_errors == 0 and counters.commands >= 3
    assert counters.bad_signature == 0 and counters.commands_denied == 0
