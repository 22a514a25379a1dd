"""The on-vessel autonomy process: an agent made of a body, a network and a behaviour."""

from bob_autonomy.core.agent import Agent
from bob_autonomy.core.clock import Clock, ManualClock, WallClock
from bob_autonomy.core.interfaces import AgentState, Body, Network, Pose
from bob_autonomy.core.neighbors import NeighborTable

__all__ = ["Agent", "AgentState", "Body", "Clock", "ManualClock", "NeighborTable", "Network", "Pose", "WallClock"]
