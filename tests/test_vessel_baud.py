"""A vessel whose serial link to the autopilot is at the wrong baud rate, or carries nothing, is told which.

The autopilot end of a serial cable (tests/serial_cable.py: two pseudo-terminals; bytes between ends set to
different rates arrive as noise, as a UART reading at the wrong rate sees them) sends ArduPilot's 1 Hz HEARTBEAT,
here five times a second to keep the test short.
"""

from __future__ import annotations

import threading

import pytest
import serial
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from serial_cable import SerialCable

from bob_autonomy.core.behavior_config import BehaviorChoice
from bob_autonomy.onboard.vessel import VehicleError, Vessel, VesselConfig
from firmware_bridge.baud_probe import heard_heartbeat

ORIGIN = (-35.363261, 149.165230)


def _autopilot(path, baud: int, stop: threading.Event) -> None:
    """HEARTBEATs of a Rover (system 1, component 1) on `path` at `baud`, every 0.2 s until `stop`."""
    port = serial.Serial(str(path), baudrate=baud, timeout=0)
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    while not stop.wait(0.2):
        port.write(mav.heartbeat_encode(10, 3, 0, 0, 4).pack(mav))
        mav.seq = (mav.seq + 1) % 256
    port.close()


def _vessel(path, **overrides) -> Vessel:
    choice = BehaviorChoice(behavior="bob-rule", params={"H": 1, "goal": [10.0, 0.0]})
    values = dict(vehicle=str(path), system_id=1, behavior=choice, origin=ORIGIN, arm_timeout_s=2.0)
    values.update(overrides)
    return Vessel(VesselConfig(**values))


@pytest.mark.parametrize("autopilot_baud", [921600, 115200])
def test_a_vessel_at_the_wrong_baud_rate_is_told_the_rate_its_port_carries(tmp_path, autopilot_baud: int) -> None:
    stop = threading.Event()
    with SerialCable(tmp_path) as cable:
        talker = threading.Thread(target=_autopilot, args=(cable.autopilot_path, autopilot_baud, stop), daemon=True)
        talker.start()
        try:
            vessel = _vessel(cable.companion_path)  # at the default 57600, ArduPilot's TELEM factory rate
            with pytest.raises(VehicleError) as caught:
                vessel.arm()
        finally:
            stop.set()
            talker.join(2.0)
    text = str(caught.value)
    assert "no HEARTBEAT from autopilot system 1" in text
    assert f"carries MAVLink at {autopilot_baud} baud, not 57600: start with --baud {autopilot_baud}" in text
    assert f"SERIALn_BAUD to 57 (it is {autopilot_baud // 1000} now)" in text
    assert cable.to_companion.misread > 0  # the vessel read noise, as a UART at the wrong rate does


def test_a_vessel_on_a_port_that_carries_nothing_is_told_to_check_the_wiring(tmp_path) -> None:
    with SerialCable(tmp_path) as cable:
        vessel = _vessel(cable.companion_path)
        with pytest.raises(VehicleError, match=r"Not a byte came on this port: check that it is the autopilot's"):
            vessel.arm()


def test_heard_heartbeat_takes_only_a_whole_frame_with_its_checksum() -> None:
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    frame = mav.heartbeat_encode(10, 3, 0, 0, 4).pack(mav)
    assert heard_heartbeat(b"\x13\x37" + frame + b"\xfd")
    assert not heard_heartbeat(frame[:-1])
    spoiled = bytearray(frame)
    spoiled[12] ^= 0x40
    assert not heard_heartbeat(bytes(spoiled))
