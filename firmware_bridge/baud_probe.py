"""Which baud rate a serial port's MAVLink is at: for a start-up that heard nothing at the rate it was given.

A UART read at the wrong rate yields bytes, but no frame with a valid checksum. ArduPilot's TELEM ports leave the
factory at 57,600 baud (libraries/AP_SerialManager/AP_SerialManager.cpp, DEFAULT_SERIALn_BAUD), companion
computers are often wired at 921,600 or 115,200, and a USB port's rate does not matter at all.
"""

from __future__ import annotations

import time

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_bridge.links import LinkError, SerialLink

# ArduPilot's SERIALn_BAUD rates a companion link is likely at, likeliest first (about 1.2 s each)
COMMON_BAUDS = (57600, 115200, 921600, 460800, 230400, 1500000, 38400)


def heard_heartbeat(data: bytes) -> bool:
    """Whether `data` holds a whole MAVLink HEARTBEAT with a valid checksum."""
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True  # skip what does not decode instead of raising
    try:
        messages = parser.parse_buffer(data) or []
    except mavlink.MAVError:
        return False
    return any(m.get_type() == "HEARTBEAT" for m in messages)


def find_mavlink_baud(device: str, tried: int, listen_s: float = 1.2, rates=COMMON_BAUDS) -> int | None:
    """The first of `rates` (other than `tried`) at which `device` carries a MAVLink HEARTBEAT within `listen_s`
    seconds (a HEARTBEAT comes every second), or None. The port must not be open elsewhere meanwhile: a serial
    port's rate is one setting for every holder."""
    for baud in rates:
        if baud == tried:
            continue
        try:
            link = SerialLink(device, device, baud)
        except LinkError:
            return None
        try:
            heard, deadline = bytearray(), time.monotonic() + listen_s
            while time.monotonic() < deadline:
                heard += link.read(4096, 0.1)
                if heard_heartbeat(bytes(heard)):
                    return baud
        except LinkError:
            return None
        finally:
            link.close()
    return None
