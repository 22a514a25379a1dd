"""A ground station arms and disarms real ArduPilot through the autonomy's component, and hears ArduPilot's answer.

The autonomy (component 191) passes an arm, disarm or mode command on to its autopilot; it answers IN_PROGRESS at
once and then with the autopilot's own result, and says the autopilot's reasons when it refused
(bob_autonomy/onboard/vessel_links.py `_answer_forwarded`). Before, it answered ACCEPTED as soon as it had handed
the command on. Here the autopilot is ArduPilot's Rover SITL and the ground station pymavlink's `mavutil`.

Skipped unless ARDUPILOT_SITL names a built `ardurover` (docs/ardupilot.md).
"""

from __future__ import annotations

import threading
import time

from pymavlink import mavutil
from sitl_harness import BINARY, NEEDS_SITL, RoverSitl, vessel_config

from bob_autonomy.onboard.vessel import Vessel

pytestmark = NEEDS_SITL
m = mavutil.mavlink


class Station:
    """pymavlink's mavutil on udpout to the vessel's ground-station port, beating once a second."""

    def __init__(self, port: int) -> None:
        self.link = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
        self._beat = 0.0

    def receive(self, timeout_s: float = 0.2):
        if time.monotonic() > self._beat:
            self._beat = time.monotonic() + 1.0
            self.link.mav.heartbeat_send(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        return self.link.recv_match(blocking=True, timeout=timeout_s)

    def arm(self, arm: bool, timeout_s: float = 15.0) -> tuple[list[int], str]:
        """MAV_CMD_COMPONENT_ARM_DISARM to the autonomy (1:191): its COMMAND_ACK results up to the final one, and
        what it said (STATUSTEXT chunks joined) meanwhile."""
        self.link.mav.command_long_send(1, 191, m.MAV_CMD_COMPONENT_ARM_DISARM, 0, float(arm), 0, 0, 0, 0, 0, 0)
        results, said = [], []
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and (not results or results[-1] == m.MAV_RESULT_IN_PROGRESS):
            msg = self.receive()
            if msg is None or msg.get_srcComponent() != 191:
                continue
            if msg.get_type() == "STATUSTEXT":
                said.append(msg.text)
            elif msg.get_type() == "COMMAND_ACK" and msg.command == m.MAV_CMD_COMPONENT_ARM_DISARM:
                results.append(msg.result)
        return results, "".join(said)


def _wait(station: Station, condition, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, what
        station.receive()


def test_a_ground_station_hears_real_ardupilots_own_answer_to_an_arm_sent_to_the_autonomy(tmp_path) -> None:
    with RoverSitl(BINARY, "omni", tmp_path) as sitl:
        sitl.wait_initialised()
        vessel = Vessel(vessel_config(sitl, gcs="udpin:127.0.0.1:0"))
        runner = threading.Thread(target=vessel.run, kwargs={"duration_s": 150.0}, daemon=True)
        runner.start()
        station = Station(vessel.gcs_link.local_address[1])
        try:
            armed = lambda: bool(sitl.seen.modes) and sitl.seen.modes[-1][2]  # noqa: E731
            _wait(station, armed, 90.0, "the vessel never armed ArduPilot")

            disarm, _ = station.arm(False)
            _wait(station, lambda: not armed(), 10.0, "ArduPilot never disarmed")

            # A throttle channel ArduPilot's RC checks refuse (RC_CALIB_MIN_LIMIT_PWM 1300 us), set on the autopilot
            # through the vessel's routing.
            station.link.mav.param_set_send(1, 1, b"RC3_MIN", 1400.0, m.MAV_PARAM_TYPE_INT16)
            _wait(station, lambda: sitl.seen.params.get("RC3_MIN") == 1400.0, 15.0, "ArduPilot never took RC3_MIN")
            refused, said = station.arm(True)
        finally:
            station.link.close()
            vessel.stop()
            runner.join(10.0)
        still_disarmed = not armed()
    print(f"\ndisarm: {disarm}; arm: {refused}, said {said!r}")
    assert disarm == [m.MAV_RESULT_IN_PROGRESS, m.MAV_RESULT_ACCEPTED]
    assert refused == [m.MAV_RESULT_IN_PROGRESS, m.MAV_RESULT_FAILED] and still_disarmed
    assert "vehicle 1 refused arm" in said and "Throttle radio min too high" in said
    assert vessel.gcs.counters.autopilot_refused == 1
