"""The vessel process: the link to the autopilot (telemetry in, RC overrides out), bringing the autopilot into
service, the estimation-and-control pipeline per vehicle kind, and the loop that runs one agent on one vehicle."""
