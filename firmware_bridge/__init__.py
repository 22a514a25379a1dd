"""The MAVLink vehicle interface: links, telemetry decoding, commands (see issue #4).

This package knows nothing of behaviours or of the simulator.
"""
