"""The autonomy process over real UDP: mesh packets, and a Vessel driving a simulated vehicle's autopilot.

The vehicle here is `sitl.vehicles.mavlink_vehicle.SimulatedVehicle` (the simulator's autopilot) on a real UDP
socket, moving a point-mass buoy; the Vessel is the code `bob-autonomy run` executes.
"""

from __future__ import annotations

import math
import socket
import subprocess
import sys
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from vessel_helpers import ORIGIN, SCALE, StandInVehicle

from bob_autonomy.core.behavior_config import BehaviorChoice
from bob_autonomy.core.clock import ScaledWallClock
from bob_autonomy.core.interfaces import AgentState, Pose
from bob_autonomy.network.mesh import (
    MAX_PACKET_BYTES,
    PacketError,
    PacketReader,
    decode_state,
    encode_state,
    packet_agent_id,
)
from bob_autonomy.onboard.vessel import VehicleError, Vessel, VesselConfig
from firmware_bridge.readings import CompassReading, GpsFix, ImuReading

# Real time, sockets and processes: in one xdist worker, so that they never compete with each other.
pytestmark = pytest.mark.xdist_group("realtime")


def _state(agent: int = 7, memory: dict | None = None) -> AgentState:
    return AgentState(agent, 12.5, Pose(101.25, -40.5, 1.0, 0.25, -0.5), memory or {})


# -- mesh packets ----------------------------------------------------------------------------------------


def test_packet_round_trip_keeps_the_state_to_float32() -> None:
    memory = {"target_light": np.array([3.0, 4.0]), "heading_goal": np.array([0.5])}
    packet = encode_state(_state(memory=memory), ["heading_goal", "target_light"])
    assert len(packet) <= MAX_PACKET_BYTES
    state = decode_state(packet, ["heading_goal", "target_light"])
    assert state.agent_id == 7 and state.t == 12.5
    assert (state.pose.x, state.pose.y, state.pose.vx, state.pose.vy) == (101.25, -40.5, 0.25, -0.5)
    assert state.pose.heading == pytest.approx(1.0, abs=1e-7)
    np.testing.assert_array_equal(state.memory["target_light"], [3.0, 4.0])
    np.testing.assert_array_equal(state.memory["heading_goal"], [0.5])
    assert packet_agent_id(packet) == 7


def test_corrupt_packets_are_rejected_with_the_reason() -> None:
    packet = bytearray(encode_state(_state(), []))
    packet[20] ^= 0x40
    with pytest.raises(PacketError, match="CRC"):
        decode_state(bytes(packet), [])
    assert packet_agent_id(bytes(packet)) is None
    with pytest.raises(PacketError, match="shorter"):
        decode_state(b"BoB\x01", [])
    with pytest.raises(PacketError, match="the radio takes 100"):
        encode_state(_state(memory={"big": np.zeros(30)}), ["big"])


def test_stream_reader_resynchronises_after_noise() -> None:
    a, b = encode_state(_state(1), []), encode_state(_state(2), [])
    broken = bytearray(encode_state(_state(3), []))
    broken[-1] ^= 0xFF
    stream = b"noise BoB" + a + bytes(broken) + b"\x00BoB\x01\xff" + b
    reader = PacketReader()
    out = []
    for k in range(0, len(stream), 7):  # any chunking
        out += reader.feed(stream[k : k + 7])
    assert [packet_agent_id(p) for p in out] == [1, 2]
    assert reader.bad >= 2 and reader.packets == 2


# -- a Vessel against the simulator's autopilot over UDP -------------------------------------------------


def _config(port: int, **overrides) -> VesselConfig:
    choice = BehaviorChoice(behavior="bob-rule", params={"goal": [30.0, 0.0], "H": 1, "p0": 5.0, "max_speed": 1.0})
    options = {"time_scale": SCALE, "controller": "simple", "arm_timeout_s": 5.0, "heartbeat_timeout_s": 3.0}
    options.update(overrides)
    return VesselConfig(vehicle=f"udpout:127.0.0.1:{port}", system_id=1, behavior=choice, origin=ORIGIN, **options)


@pytest.fixture
def stand_in():
    vehicle = StandInVehicle()
    vehicle.start()
    yield vehicle
    vehicle.close()


def test_vessel_arms_its_vehicle_and_drives_it_to_the_goal(stand_in: StandInVehicle) -> None:
    vessel = Vessel(_config(stand_in.port), clock=ScaledWallClock(SCALE))
    stats = vessel.run(duration_s=25.0)
    assert stand_in.vehicle.armed, "the vessel armed its vehicle with COMMAND_LONG + COMMAND_ACK"
    assert stand_in.vehicle.counters.commands > 50
    assert stand_in.position[0] > 5.0, f"moved east towards the goal: {stand_in.position}"
    assert abs(stand_in.position[1]) < 5.0
    assert stats.commands > 50 and stats.step_errors == 0
    time.sleep(0.1)
    np.testing.assert_allclose(stand_in.vehicle.actuator(stand_in.vehicle._last_command_s), [0.0, 0.0], atol=1e-9)
    summary = stats.summary()
    assert summary["compute_latency_s_median"] < summary["compute_latency_s_p99"] + 1e-12
    # the vehicle link's decoder counters, those not zero: every frame decoded, none bad
    assert summary["vehicle_link_decoded"] > 100 and "vehicle_link_bad_crc" not in summary


def test_a_throttle_limit_on_the_autopilot_is_the_limit_the_vessel_plans_with(stand_in: StandInVehicle) -> None:
    """MOT_THR_MAX 50: ArduPilot clips the throttle demand to 50 % (AP_MotorsUGV::set_throttle). The vessel reads it
    at start and its controller plans with half the thrust, so no override it sends asks for more than half
    throttle or half lateral."""
    assert stand_in.vehicle.params.set("MOT_THR_MAX", 50)
    vessel = Vessel(_config(stand_in.port), clock=ScaledWallClock(SCALE))
    stats = vessel.run(duration_s=15.0)
    assert vessel.config.max_thrust_fraction == 0.5 and stats.commands > 30
    np.testing.assert_allclose(vessel.pipeline.max_thrust_n, 0.5 * vessel.pipeline.model.max_thrust_n)
    profile = vessel.autopilot.profile
    half = [round(0.5 * (profile.rc_map.range_of(ch).max_us - 1500)) + 1 for ch in (3, 4)]  # us from trim, 1 of slack
    sent = [channels for _t, channels in vessel.autopilot.sent]
    assert sent and all(abs(c[3] - 1500) <= half[0] and abs(c[4] - 1500) <= half[1] for c in sent)


def test_the_gps_lag_and_antenna_offset_the_autopilot_has_are_the_ones_the_vessel_uses(
    stand_in: StandInVehicle,
) -> None:
    """GPS1_DELAY_MS 120: the autopilot's EKF takes its fixes as measured 120 ms before it read them. The vessel
    reads it at start and dates its fixes so too (a `gps_lag_s` setting of its own wins), and still drives.
    Likewise the antenna's offset: GPS1_POS (1.5 m up, 0.5 m forward) less INS_POS1 (the IMU 0.1 m forward), by
    which it moves its fixes to the IMU (on this level hull it still drives)."""
    for name, value in (("GPS1_DELAY_MS", 120), ("GPS1_POS_X", 0.5), ("GPS1_POS_Z", -1.5), ("INS_POS1_X", 0.1)):
        assert stand_in.vehicle.params.set(name, value)
    vessel = Vessel(_config(stand_in.port), clock=ScaledWallClock(SCALE))
    stats = vessel.run(duration_s=10.0)
    assert vessel.vehicle.decoder.gps_lag_s == pytest.approx(0.12)
    assert vessel.pipeline.antenna_frd_m[0] == pytest.approx([0.4, 0.0, -1.5])
    assert stats.antenna_unplaced <= 2
    assert stats.commands > 20 and stand_in.position[0] > 1.0, f"moved east towards the goal: {stand_in.position}"
    vessel.config = replace(vessel.config, gps_lag_s=0.05)  # as `--gps-lag 0.05` would have set it
    vessel.vehicle.decoder.gps_lag_s = 0.05
    vessel._place_fixes(vessel.autopilot.profile.gps_lag_s)
    assert vessel.vehicle.decoder.gps_lag_s == 0.05


def test_the_ground_station_hears_a_position_only_once_a_fix_set_it(stand_in: StandInVehicle) -> None:
    """Before its first fix the EKF estimates (0, 0), finite and no position: reported, a ground station would show
    the vessel at the frame's origin. It reports nothing until a fix sets the estimate, then the fix's place; its
    heading only once a compass reading set it (the vessel steps its agent only when both are known)."""
    vessel = Vessel(_config(stand_in.port), clock=ScaledWallClock(SCALE))
    vessel.pipeline.feed([ImuReading(np.array([0]), np.array([1.0]), np.zeros((1, 2)), np.zeros(1))])
    vessel._report_position(1.0)
    assert vessel.gcs._position is None
    lat, lon = vessel.frame.to_geodetic(np.array([120.0]), np.array([-35.0]))
    vessel.pipeline.feed([GpsFix(np.array([0]), np.array([1.05]), lat, lon)])
    vessel._report_position(1.1)
    assert vessel.gcs._position is not None
    assert vessel.gcs._position[:2] == pytest.approx((float(lat[0]), float(lon[0])), abs=1e-7)
    assert vessel.gcs._position[4] is None  # no compass reading yet: the heading is unknown, not 0 (east)
    assert vessel.pipeline.position_known(1.1).all() and not vessel.pipeline.heading_known(1.1).all()
    vessel.pipeline.feed([CompassReading(np.array([0]), np.array([1.15]), np.array([1.2]))])
    vessel._report_position(1.2)
    assert vessel.gcs._position[4] == pytest.approx(1.2, abs=0.05)
    vessel.shutdown()


def test_an_autopilot_that_hears_nothing_we_send_stops_the_start_up_saying_so(stand_in: StandInVehicle) -> None:
    """A one-way link (the serial TX wire off, a radio that only receives): the autopilot's HEARTBEATs arrive and
    nothing we send is answered. Before, the start-up went on with assumed defaults and ended "would not arm"
    without a reason; now it stops once the parameters go unanswered and names the link."""
    stand_in.deaf.set()
    vessel = Vessel(_config(stand_in.port), clock=ScaledWallClock(SCALE))
    started = time.monotonic()
    with pytest.raises(VehicleError, match=r"heard \(HEARTBEAT\) but answered nothing sent to it.*TX wire"):
        vessel.run(duration_s=30.0)
    assert time.monotonic() - started < 25.0 and not stand_in.vehicle.armed


def test_an_autopilot_that_takes_mavlink_only_from_its_ground_station_is_still_started_and_driven(
    stand_in: StandInVehicle,
) -> None:
    """MAV_OPTIONS bit 0: ArduPilot takes MAVLink only from MAV_GCS_SYSID, and from its own system's components
    (GCS_Common.cpp accept_packet). With MAV_GCS_SYSID 200 the vessel cannot learn that id by asking as system
    255: against the real Rover SITL it got no answer to anything and gave up "would not arm" without saying why.
    It now asks as a component of the autopilot's own system until it knows the id, then sends as it."""
    for name, value in (("MAV_GCS_SYSID", 200), ("MAV_OPTIONS", 1)):
        assert stand_in.vehicle.params.set(name, value)
    vessel = Vessel(_config(stand_in.port), clock=ScaledWallClock(SCALE))
    stats = vessel.run(duration_s=15.0)
    assert vessel.autopilot.profile.gcs_system_id == 200 and vessel.autopilot.encoder.mav.srcSystem == 200
    assert stand_in.vehicle.armed and stand_in.vehicle.counters.commands > 30 and stats.commands > 30
    assert stand_in.position[0] > 2.0, f"moved east towards the goal: {stand_in.position}"


@pytest.mark.parametrize(("slew_rate", "per_s"), [(None, 1.0), (40, 0.4)])
def test_a_motorboat_plans_with_the_throttle_slew_its_autopilot_has(slew_rate: int | None, per_s: float) -> None:
    """MOT_SLEWRATE (default 100 %/s) limits how fast ArduPilot moves the throttle output (AP_MotorsUGV): the
    vessel reads it at start and its motorboat MPC plans with it."""
    boat = StandInVehicle(kind="motorboat")
    if slew_rate is not None:
        assert boat.vehicle.params.set("MOT_SLEWRATE", slew_rate)
    boat.start()
    try:
        vessel = Vessel(_config(boat.port, kind="motorboat", controller="mpc"), clock=ScaledWallClock(SCALE))
        stats = vessel.run(duration_s=6.0)
    finally:
        boat.close()
    assert stats.commands > 10
    assert [mpc.model.throttle_slew_per_s for mpc in vessel.pipeline.mpcs] == [per_s]


def test_vessel_stops_and_raises_an_alarm_when_its_vehicle_goes_silent(stand_in: StandInVehicle) -> None:
    vessel = Vessel(_config(stand_in.port, heartbeat_timeout_s=2.0), clock=ScaledWallClock(SCALE))
    _once_driving(vessel, stand_in.muted)
    stats = vessel.run(duration_s=20.0)
    assert stand_in.muted.is_set() and stats.silent_alarms == 1
    recent = stand_in.vehicle._command  # the last command the vehicle received
    np.testing.assert_allclose(recent, [0.0, 0.0], atol=1e-9)


def test_an_autopilot_heard_without_its_heartbeats_is_not_silent(stand_in: StandInVehicle) -> None:
    # Its HEARTBEATs lost on a noisy line while its GPS and ATTITUDE come: it is alive, and the vessel drives on.
    vessel = Vessel(_config(stand_in.port, heartbeat_timeout_s=2.0), clock=ScaledWallClock(SCALE))
    driving_at = _once_driving(vessel, stand_in.no_heartbeat)
    stats = vessel.run(duration_s=20.0)
    assert driving_at and stats.silent_alarms == 0
    assert stats.commands > driving_at[0] + 50  # about 18 clock s more at 10 Hz: it drove on


def test_a_parameter_a_ground_station_sets_while_driving_is_adopted_and_said(stand_in: StandInVehicle, caplog) -> None:
    """A ground station on another port of the autopilot sets RC3_TRIM (the throttle channel's neutral) while the
    vessel drives; the autopilot sends the new value to every link. The vessel's overrides follow it at once
    and it says what changed."""
    vessel = Vessel(_config(stand_in.port), clock=ScaledWallClock(SCALE))
    gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    param_set = bytes(gcs.param_set_encode(1, 1, b"RC3_TRIM", 1550.0, mavlink.MAV_PARAM_TYPE_INT16).pack(gcs))
    set_trim = threading.Event()
    driving_at = _once_driving(vessel, set_trim)
    threading.Thread(target=lambda: set_trim.wait(30.0) and stand_in.from_ground.put(param_set), daemon=True).start()
    with caplog.at_level("INFO"):
        vessel.run(duration_s=12.0)
    assert driving_at and vessel.autopilot.param_changes == [("RC3_TRIM", 1500.0, 1550.0)]
    assert vessel.autopilot.profile.values["RC3_TRIM"] == 1550.0
    said = [r.getMessage() for r in caplog.records if "RC3_TRIM" in r.getMessage()]
    assert said == [
        "autopilot parameter RC3_TRIM of vehicle 1 changed from 1500 to 1550 (by a ground station?): our RC "
        "overrides follow it now; the controller keeps the model it was built with until the autonomy restarts"
    ]


@pytest.mark.parametrize("kind", ["buoy", "motorboat"])
def test_a_throttle_limit_a_ground_station_sets_while_driving_is_planned_with(kind: str, caplog) -> None:
    """A ground station lowers MOT_THR_MAX to 50 while the vessel drives at full throttle; ArduPilot clips the
    throttle to it from then on and sends the new value to every link. The vessel's controller plans with half
    throttle from the next step (its estimator kept), so the overrides it sends ask for no more, and it says so."""
    boat = StandInVehicle(kind=kind)
    boat.start()
    try:
        ahead = [60.0 * math.cos(boat.heading), 60.0 * math.sin(boat.heading)]  # the stand-in never turns
        fast = BehaviorChoice(behavior="bob-rule", params={"goal": ahead, "H": 1, "p0": 5.0, "max_speed": 3.0})
        vessel = Vessel(replace(_config(boat.port, kind=kind), behavior=fast), clock=ScaledWallClock(SCALE))
        gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        param_set = bytes(gcs.param_set_encode(1, 1, b"MOT_THR_MAX", 50.0, mavlink.MAV_PARAM_TYPE_INT8).pack(gcs))
        estimators, before, set_at = [], [], []  # the estimator driving when the limit is set, overrides sent till then

        def set_limit() -> None:
            deadline = time.monotonic() + 30.0
            while vessel.stats.commands < 30 and time.monotonic() < deadline:
                time.sleep(0.02)
            estimators.append(vessel.pipeline.estimator)
            before.extend(channels for _t, channels in list(vessel.autopilot.sent))
            set_at.append(vessel.clock.now())
            boat.from_ground.put(param_set)

        threading.Thread(target=set_limit, daemon=True).start()
        with caplog.at_level("INFO"):
            vessel.run(duration_s=12.0)
    finally:
        boat.close()
    assert vessel.autopilot.param_changes == [("MOT_THR_MAX", 100.0, 50.0)]
    assert vessel.config.max_thrust_fraction == 0.5 and estimators == [vessel.pipeline.estimator]
    pipeline = vessel.pipeline
    full = [m.max_thrust_n for m in pipeline.models] if kind == "motorboat" else [pipeline.model.max_thrust_n]
    np.testing.assert_allclose(pipeline.max_thrust_n, 0.5 * np.array(full))
    said = [r.getMessage() for r in caplog.records if "MOT_THR_MAX" in r.getMessage()]
    assert said == [
        "autopilot parameter MOT_THR_MAX of vehicle 1 changed from 100 to 50 (by a ground station?): the controller "
        "plans with at most 50 % throttle from now on"
    ]
    half = round(0.5 * (vessel.autopilot.profile.rc_map.range_of(3).max_us - 1500)) + 1  # us from trim, 1 of slack
    if kind == "buoy":  # (the stand-in motorboat's simple controller asks for little throttle: max_throttle it is)
        assert max(abs(channels[3] - 1500) for channels in before) > half, "it drove at more than half throttle"
    else:
        assert pipeline.max_throttle.tolist() == [0.5]
    after = [abs(channels[3] - 1500) for t, channels in vessel.autopilot.sent if t > set_at[0] + 0.5]
    assert len(after) > 20 and max(after) <= half


def _once_driving(vessel: Vessel, event: threading.Event) -> list[int]:
    """Set `event` (a stand-in vehicle's fault) once the vessel has sent 5 commands; returns a list that then holds
    the vessel's command count at that moment."""
    driving_at: list[int] = []

    def watch() -> None:
        while vessel.stats.commands < 5:
            time.sleep(0.02)
        driving_at.append(vessel.stats.commands)
        event.set()

    threading.Thread(target=watch, daemon=True).start()
    return driving_at


def test_an_unanswering_vehicle_is_a_clear_error() -> None:
    quiet = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    quiet.bind(("127.0.0.1", 0))
    try:
        vessel = Vessel(_config(quiet.getsockname()[1], arm_timeout_s=1.0), clock=ScaledWallClock(SCALE))
        with pytest.raises(VehicleError, match=r"no HEARTBEAT from autopilot system 1 component 1 within 1 s"):
            vessel.run(duration_s=5.0)
        vessel.shutdown()
    finally:
        quiet.close()


def test_a_vessel_on_another_autopilots_system_id_is_told_which_one_it_hears(stand_in: StandInVehicle) -> None:
    """Every ArduPilot leaves the factory as system 1; a vessel started as system 2 on it hears only system 1."""
    config = replace(_config(stand_in.port, heartbeat_timeout_s=1.0), system_id=2)
    vessel = Vessel(config, clock=ScaledWallClock(SCALE))
    with pytest.raises(VehicleError) as error:
        vessel.run(duration_s=5.0)
    vessel.shutdown()
    assert "this link carries autopilot system 1: start with --system-id 1, or set that autopilot's MAV_SYSID to 2" in (
        str(error.value)
    )


def test_the_command_line_rejects_a_bad_behaviour_clearly() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "bob_autonomy.cli", "run", "--vehicle", "udpout:127.0.0.1:5760", "--system-id", "1",
         "--behavior", "no-such-thing", "--origin", "1.3,103.9"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert result.returncode == 2
    assert "unknown behavior 'no-such-thing'" in result.stderr
