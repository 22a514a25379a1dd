"""Software in the loop: simulated bodies, world and network, scenarios, metrics and plots."""
