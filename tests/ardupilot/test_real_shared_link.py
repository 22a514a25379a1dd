"""Others on the vessel's autopilot: an operator behind the same router, and a ground station that sets a parameter.

On many boats the companion computer runs MAVProxy (or mavlink-router) on the autopilot's port and hands the
link to both the autonomy and the operator (`mavproxy.py --master=/dev/ttyAMA0 --out=udp:...`). The router passes
every autopilot frame to every output, so the autonomy also hears the COMMAND_ACKs ArduPilot addresses to the
operator (target_system, target_component: the command's sender, GCS_Common.cpp handle_command_long). The vessel
takes only those addressed to itself (bob_autonomy/onboard/autopilot.py `_addressed_to_us`): before, it took
any, and an operator's accepted ARM_DISARM could end its own refused start-up as armed
(tests/test_autopilot_session.py). Here ArduPilot's Rover SITL is the autopilot and MAVProxy the router and the
operator's console: the operator changes mode three times while the vessel drives, and the vessel, which
arms and sets its streams on its own acks, reaches its goal and counts the operator's acks as someone else's.

ArduPilot also sends a parameter's new value to every active link when anyone sets it: a ground station that sets
RC3_TRIM while the vessel drives is heard, and the vessel learns its autopilot's profile again, so its next
overrides are made with the new neutral (bob_autonomy/onboard/autopilot.py `_take_param`; before, the profile
was read once at the start). MOT_THR_MAX lowered so is planned within from the next step.

Skipped unless ARDUPILOT_SITL names a built `ardurover` (docs/ardupilot.md).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import replace

import pytest
from mavproxy_session import MAVPROXY, MavproxySession
from pymavlink import mavutil
from sitl_harness import BINARY, NEEDS_SITL, RoverSitl, free_udp_port, local_xy, vessel_config

from bob_autonomy.core.behavior_config import BehaviorChoice
from bob_autonomy.onboard.vessel import Vessel

pytestmark = [
    *NEEDS_SITL,
    pytest.mark.skipif(MAVPROXY is None, reason="MAVProxy is not installed (pip install -e '.[dev]')"),
]
GOAL = (25.0, 0.0)  # m east, north of HOME


def test_the_vessel_behind_mavproxy_takes_only_the_acks_ardupilot_addresses_to_it(tmp_path) -> None:
    with RoverSitl(BINARY, "omni", tmp_path) as sitl:
        sitl.wait_initialised()
        port = free_udp_port()
        # MAVProxy on the autopilot's SERIAL0, the vessel on one of its outputs; no stream requests of its own
        # (--streamrate=-1: they would reset the rates the autonomy asks for, as on ArduPilot's own port).
        router = MavproxySession(
            f"tcp:127.0.0.1:{sitl.serial0}",
            tmp_path,
            component=1,
            extra=(f"--out=udpin:127.0.0.1:{port}", "--streamrate=-1", "--source-system=255"),
        )
        vessel = Vessel(vessel_config(sitl, goal=GOAL, vehicle=f"udpout:127.0.0.1:{port}"))
        runner = threading.Thread(target=vessel.run, kwargs={"duration_s": 120.0}, daemon=True)
        try:
            router.expect(r"Detected vehicle 1:1", 30.0)
            runner.start()
            deadline = time.monotonic() + 90.0
            while not (sitl.seen.modes and sitl.seen.modes[-1][2]):
                assert time.monotonic() < deadline, "the vessel never armed ArduPilot through MAVProxy"
                time.sleep(0.5)
            for _ in range(3):  # the operator: MANUAL again (the vessel drives in MANUAL), answered to MAVProxy
                router.command("mode MANUAL", r"Got COMMAND_ACK: DO_SET_MODE: ACCEPTED", 10.0)
            deadline = time.monotonic() + 90.0
            while math.dist(local_xy(*sitl.seen.positions[-1][1:3]), GOAL) > 5.0:
                assert time.monotonic() < deadline, f"never within 5 m of {GOAL}: at {sitl.seen.positions[-1]}"
                time.sleep(0.5)
            session = vessel.autopilot
        finally:
            vessel.stop()
            if runner.is_alive():
                runner.join(10.0)
            router.close()
    taken = sorted({command for _t, command, _r in session.acks})
    print(f"\nacks taken {len(session.acks)} (commands {taken}), for others {session.acks_for_others}")
    assert session.acks_for_others >= 3  # the operator's DO_SET_MODE answers, addressed to MAVProxy
    assert session.intervals_accepted  # its own SET_MESSAGE_INTERVAL answers were taken
    mode = 176  # MAV_CMD_DO_SET_MODE: the vessel's own (at its start-up) only
    assert sum(1 for _t, command, _r in session.acks if command == mode) <= 2


def _set_while_driving(sitl: RoverSitl, vessel: Vessel, goal, name: bytes, value: float, param_type: int) -> float:
    """Run `vessel` (its ground-station link on a UDP port); once it has armed ArduPilot and sent 100 overrides, a
    ground station (pymavlink, through the vessel's routing) sets parameter `name`; then wait until the vessel is
    within 5 m of `goal` and has heard a change. Returns when the parameter was set (time.monotonic)."""
    runner = threading.Thread(target=vessel.run, kwargs={"duration_s": 150.0}, daemon=True)
    runner.start()
    station = mavutil.mavlink_connection(
        f"udpout:127.0.0.1:{vessel.gcs_link.local_address[1]}", source_system=255, source_component=190
    )
    try:
        deadline = time.monotonic() + 90.0
        while not (sitl.seen.modes and sitl.seen.modes[-1][2]) or vessel.stats.commands < 100:
            assert time.monotonic() < deadline, "the vessel never armed ArduPilot and drove"
            station.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            time.sleep(0.5)
        set_at = time.monotonic()
        station.mav.param_set_send(1, 1, name, value, param_type)
        deadline = time.monotonic() + 120.0
        while math.dist(local_xy(*sitl.seen.positions[-1][1:3]), goal) > 5.0 or not vessel.autopilot.param_changes:
            assert time.monotonic() < deadline, f"at {sitl.seen.positions[-1]}, {vessel.autopilot.param_changes}"
            time.sleep(0.5)
    finally:
        station.close()
        vessel.stop()
        runner.join(10.0)
    return set_at


def test_a_parameter_a_ground_station_sets_on_real_ardupilot_is_adopted_by_the_driving_vessel(tmp_path) -> None:
    """ArduPilot sends a parameter's new value to every active link (GCS_Param.cpp GCS::send_parameter_value):
    a ground station sets RC3_TRIM, the throttle channel's neutral, while the vessel drives; the vessel hears
    ArduPilot's PARAM_VALUE, makes its next overrides with it and still reaches its goal."""
    with RoverSitl(BINARY, "omni", tmp_path) as sitl:
        sitl.wait_initialised()
        vessel = Vessel(vessel_config(sitl, goal=GOAL, gcs="udpin:127.0.0.1:0"))
        _set_while_driving(sitl, vessel, GOAL, b"RC3_TRIM", 1550.0, mavutil.mavlink.MAV_PARAM_TYPE_INT16)
    print(f"\nchanges heard {vessel.autopilot.param_changes}; ArduPilot's RC3_TRIM {sitl.seen.params.get('RC3_TRIM')}")
    assert vessel.autopilot.param_changes == [("RC3_TRIM", 1500.0, 1550.0)]
    assert vessel.autopilot.profile.values["RC3_TRIM"] == 1550.0


def test_a_throttle_ceiling_set_on_real_ardupilot_while_driving_is_planned_within(tmp_path) -> None:
    """An operator lowers MOT_THR_MAX to 30 while the vessel drives an omni rover at well over 30 % throttle;
    ArduPilot clips its throttle there from then on and sends the new value to every link. The vessel's controller
    plans within 30 % from its next step: the throttle input ArduPilot reports (RC_CHANNELS chan3) stays within
    30 % of its throw, and the vessel still reaches its goal."""
    far = (50.0, 0.0)
    with RoverSitl(BINARY, "omni", tmp_path) as sitl:
        sitl.wait_initialised()
        config = vessel_config(sitl, goal=far, gcs="udpin:127.0.0.1:0")
        fast = BehaviorChoice(behavior="bob-rule", params={**config.behavior.params, "max_speed": 4.0})
        vessel = Vessel(replace(config, behavior=fast))
        set_at = _set_while_driving(sitl, vessel, far, b"MOT_THR_MAX", 30.0, mavutil.mavlink.MAV_PARAM_TYPE_INT8)
    throttle = vessel.autopilot.profile.rc_map.range_of(3)
    ceiling = 0.3 * (throttle.max_us - throttle.trim_us - throttle.dead_zone_us) + throttle.dead_zone_us + 1
    before = [abs(chans[2] - throttle.trim_us) for t, chans in sitl.seen.rc if t < set_at]
    after = [abs(chans[2] - throttle.trim_us) for t, chans in sitl.seen.rc if t > set_at + 2.0]
    print(f"\nthrottle input from trim before {max(before)} us, after at most {max(after)} us (ceiling {ceiling:.0f})")
    assert vessel.autopilot.param_changes == [("MOT_THR_MAX", 100.0, 30.0)]
    assert vessel.config.max_thrust_fraction == 0.3
    assert max(before) > ceiling and len(after) > 20 and max(after) <= ceiling
