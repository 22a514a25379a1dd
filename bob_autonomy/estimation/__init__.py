"""State estimation: the buoy and eBot extended Kalman filters."""
