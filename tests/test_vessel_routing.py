"""The autonomy process routes MAVLink between its autopilot and the ground station, as mavlink-router would:
a ground station on the vessel's GCS port sees the autopilot (component 1) beside the autonomy (191), and
reaches it. The ground station here is pymavlink's own `mavutil` connection; the autopilot is the simulator's
ArduPilot-like vehicle on a real UDP socket."""

from __future__ import annotations

import threading
import time

import pytest
from pymavlink import mavutil
from vessel_helpers import ORIGIN, SCALE, StandInVehicle

from bob_autonomy.core.behavior_config import BehaviorChoice
from bob_autonomy.core.clock import ScaledWallClock
from bob_autonomy.onboard.vessel import Vessel, VesselConfig

pytestmark = pytest.mark.xdist_group("realtime")


@pytest.fixture
def routed_vessel():
    vehicle = StandInVehicle()
    vehicle.start()
    gcs = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=250, source_component=190)
    port = gcs.port.getsockname()[1]
    config = VesselConfig(
        vehicle=f"udpout:127.0.0.1:{vehicle.port}",
        system_id=1,
        behavior=BehaviorChoice(behavior="bob-rule", params={"p0": 5.0}),
        origin=ORIGIN,
        time_scale=SCALE,
        controller="simple",
        gcs=f"udpout:127.0.0.1:{port}",
    )
    vessel = Vessel(config, clock=ScaledWallClock(SCALE))
    runner = threading.Thread(target=vessel.run, daemon=True)
    runner.start()
    yield vehicle, gcs, vessel
    vessel.stop()
    runner.join(5.0)
    gcs.close()
    vehicle.close()


def _wait_for(gcs, predicate, timeout_s: float = 10.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        msg = gcs.recv_match(blocking=True, timeout=0.2)
        if msg is not None and predicate(msg):
            return msg
    return None


def test_the_ground_station_sees_and_reaches_the_autopilot_through_the_vessel(routed_vessel) -> None:
    _vehicle, gcs, vessel = routed_vessel
    seen = set()
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline and seen != {1, 191}:
        msg = gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=0.2)
        if msg is not None and msg.get_srcSystem() == 1:
            seen.add(msg.get_srcComponent())
    assert seen == {1, 191}, "a ground station on the GCS port sees the autopilot and the autonomy"
    # A parameter read addressed to the autopilot (one the vessel never reads itself) goes through the vessel
    # and its answer comes back.
    gcs.mav.param_request_read_send(1, 1, b"INITIAL_MODE", -1)
    answer = _wait_for(
        gcs, lambda m: m.get_type() == "PARAM_VALUE" and m.get_srcComponent() == 1 and m.param_id == "INITIAL_MODE"
    )
    assert answer is not None and answer.param_value == 0.0  # MANUAL, ArduPilot Rover's default
    # The vessel's own component does not take frames addressed to the autopilot alone.
    assert vessel.stats.routed_to_vehicle >= 1 and vessel.stats.routed_to_gcs > 0


def test_a_command_for_the_autopilot_is_answered_by_the_autopilot(routed_vessel) -> None:
    _vehicle, gcs, _vessel = routed_vessel
    assert _wait_for(gcs, lambda m: m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 1) is not None
    gcs.mav.command_long_send(1, 1, mavutil.mavlink.MAV_CMD_REQUEST_MESSAGE, 0, 148, 0, 0, 0, 0, 0, 0)
    version = _wait_for(gcs, lambda m: m.get_type() == "AUTOPILOT_VERSION")
    assert version is not None and version.get_srcComponent() == 1
    assert version.capabilities & mavutil.mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2


def _udp_drops(gcs) -> str:
    """Datagrams the kernel dropped for the ground station's socket (its receive buffer was full), from
    /proc/net/udp, or "unknown"."""
    port = gcs.port.getsockname()[1]
    try:
        with open("/proc/net/udp") as table:
            for line in table.readlines()[1:]:
                fields = line.split()
                if int(fields[1].split(":")[1], 16) == port:
                    return fields[-1]
    except (OSError, IndexError, ValueError):
        pass
    return "unknown"


def _drain(gcs, seconds: float = 0.0) -> None:
    """Read and drop what the ground station has been sent, for `seconds` and then until nothing is waiting. A
    socket nobody reads fills (the vessel routes all the autopilot's telemetry, here at 5 times its rate), and the
    kernel then drops new datagrams: a CI run under load saw an arm command's IN_PROGRESS lost that way while the
    test slept, waiting for the vehicle to arm, and an earlier one both of its answers."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        gcs.recv_match(blocking=True, timeout=0.05)
    for _ in range(100_000):  # bounded: the vessel keeps sending
        if gcs.recv_match(blocking=False) is None:
            return


def _where_it_went(vessel: Vessel, results: list[int], gcs) -> str:
    """What the vessel did with the ground station's commands, for a failed check: whether a command came in,
    was passed on, and answered, and whether the ground station's socket overflowed."""
    counters = vessel.gcs.counters
    return (
        f"answers {results}; the vessel took {counters.commands} commands in {counters.accepted} accepted frames "
        f"({counters.malformed} malformed, {counters.ignored_other_target} for others), refused "
        f"{counters.autopilot_refused}, sent {counters.sent} frames; datagrams dropped by the ground station's "
        f"socket: {_udp_drops(gcs)}; stats {vessel.stats}"
    )


def _answers_from_the_autonomy(gcs, command: int, timeout_s: float = 10.0) -> tuple[list[int], list[str]]:
    """The results of the autonomy's (component 191) COMMAND_ACKs for `command` up to its final one (not
    IN_PROGRESS), and the autonomy's STATUSTEXTs meanwhile."""
    results, texts = [], []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and (not results or results[-1] == mavutil.mavlink.MAV_RESULT_IN_PROGRESS):
        msg = gcs.recv_match(type=["COMMAND_ACK", "STATUSTEXT"], blocking=True, timeout=0.2)
        if msg is None or msg.get_srcComponent() != 191:
            continue
        if msg.get_type() == "STATUSTEXT":
            texts.append(msg.text)
        elif msg.command == command:
            results.append(msg.result)
    return results, texts


def test_an_arm_command_to_the_autonomy_gets_the_autopilots_own_answer(routed_vessel) -> None:
    """An arm or disarm sent to the autonomy's component is passed on to the autopilot: answered IN_PROGRESS at
    once, then with the autopilot's result. Before, the autonomy answered ACCEPTED itself, so a ground station was
    told a vessel armed that its autopilot had refused. Refused, the autonomy says why (the autopilot's reasons);
    unanswered (a deaf autopilot), it answers FAILED after 5 s of its clock and says so."""
    vehicle, gcs, vessel = routed_vessel
    arm_disarm = mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM
    in_progress, accepted, failed = (
        mavutil.mavlink.MAV_RESULT_IN_PROGRESS, mavutil.mavlink.MAV_RESULT_ACCEPTED, mavutil.mavlink.MAV_RESULT_FAILED
    )  # fmt: skip
    assert _wait_for(gcs, lambda m: m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 191) is not None
    deadline = time.monotonic() + 10.0
    while not vehicle.vehicle.armed:  # the vessel arms its vehicle as it starts
        assert time.monotonic() < deadline, "the vessel never armed its vehicle"
        _drain(gcs, 0.1)

    _drain(gcs)
    gcs.mav.command_long_send(1, 191, arm_disarm, 0, 0, 0, 0, 0, 0, 0, 0)  # disarm
    results, _ = _answers_from_the_autonomy(gcs, arm_disarm)
    assert results == [in_progress, accepted] and not vehicle.vehicle.armed, _where_it_went(vessel, results, gcs)

    vehicle.vehicle.params.set("RC3_MIN", 1600)  # ArduPilot's RC checks refuse to arm (above 1300 us)
    _drain(gcs)
    gcs.mav.command_long_send(1, 191, arm_disarm, 0, 1, 0, 0, 0, 0, 0, 0)
    results, texts = _answers_from_the_autonomy(gcs, arm_disarm)
    assert results == [in_progress, failed] and not vehicle.vehicle.armed, _where_it_went(vessel, results, gcs)
    said = "".join(texts)  # STATUSTEXT carries 50 characters a message: a longer text comes in chunks
    assert "vehicle 1 refused arm" in said and "Arm: Throttle radio min too high" in said, texts

    vehicle.deaf.set()  # hears nothing more: no answer comes
    _drain(gcs)
    started = time.monotonic()
    gcs.mav.command_long_send(1, 191, arm_disarm, 0, 1, 0, 0, 0, 0, 0, 0)
    results, texts = _answers_from_the_autonomy(gcs, arm_disarm)
    assert results == [in_progress, failed], _where_it_went(vessel, results, gcs)
    assert 0.8 < time.monotonic() - started < 3.0  # 5 s of the vessel's clock, which runs at SCALE (5x)
    assert "vehicle 1 did not answer arm within 5 s" in "".join(texts), texts
    assert vessel.gcs.counters.autopilot_refused == 2
