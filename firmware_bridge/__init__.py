"""The MAVLink vehicle interface: links, telemetry decoding, commands (see issue #4).

This package knows nothing of behaviours or of the simulator.
"""

from __future__ import annotations

import importlib
from typing import Any

# Exported lazily, so that importing firmware_bridge.readings (as the simulator does) loads neither
# pymavlink nor pyserial.
_EXPORTS = {
    "TelemetryDecoder": "decoder",
    "HeartbeatWatch": "decoder",
    "WheelDistance": "decoder",
    "Battery": "decoder",
    "Heartbeat": "decoder",
    "CommandAck": "decoder",
    "Encoder": "commands",
    "rc_override_for_thrust": "commands",
    "rc_override_for_wheels": "commands",
    "manual_control": "commands",
    "heartbeat": "commands",
    "command_long_arm": "commands",
    "set_mode": "commands",
    "thrust_from_rc": "commands",
    "wheels_from_rc": "commands",
    "open_link": "links",
    "LinkError": "links",
    "TelemetryEncoder": "telemetry",
    "TlogWriter": "tlog",
    "EbotSerial": "ebot_serial",
    "EbotMavlinkBridge": "ebot_bridge",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'firmware_bridge' has no attribute {name!r}")
    return getattr(importlib.import_module(f"firmware_bridge.{module}"), name)
