"""Fleets: every agent stepped in lockstep in one process, or one autonomy process per vessel."""
