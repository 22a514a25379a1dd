"""The ground-station side: the vessel's MAVLink component (parameters, commands, missions, signing), its
parameters, supervisor and geofence, and the client for mission scripts."""
