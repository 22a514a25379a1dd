"""The simulated world: walls, rooms, lights and the geofence; wind, gusts and current."""
