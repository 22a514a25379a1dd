"""The on-vessel autonomy process: an agent made of a body, a network and a behaviour."""

from bob_autonomy.agent import Agent
from bob_autonomy.clock import Clock, ManualClock, WallClock
from bob_autonomy.interfaces import AgentState, Body, Network, Pose
from bob_autonomy.neighbors import NeighborTable

__all__ = ["Agent", "AgentState", "Body", "Clock", "ManualClock", "NeighborTable", "Network", "Pose", "WallClock"]
