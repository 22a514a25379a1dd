"""The simulated vehicles: dynamics, sensors, and each vehicle's autopilot as a MAVLink endpoint."""
