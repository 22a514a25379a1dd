"""The paper's swarm update rules as array functions, hardware-agnostic (numpy only)."""

from behaviors.base import Behavior, MemorySpec, Senses, SwarmTable, View, Wish
from behaviors.bob_rule import BobRule
from behaviors.coverage import AreaCoverage
from behaviors.heading_consensus import HeadingConsensus, HoldHeading
from behaviors.marching import Marching
from behaviors.obstacle_avoidance import AvoidObstacles
from behaviors.perimeter_defense import PerimeterDefense
from behaviors.search_rendezvous import SearchRendezvous
from behaviors.station_keeping import HoldPosition
from behaviors.waypoints import FollowWaypoints

__all__ = [
    "AreaCoverage",
    "AvoidObstacles",
    "Behavior",
    "BobRule",
    "FollowWaypoints",
    "HeadingConsensus",
    "HoldHeading",
    "HoldPosition",
    "Marching",
    "MemorySpec",
    "PerimeterDefense",
    "SearchRendezvous",
    "Senses",
    "SwarmTable",
    "View",
    "Wish",
]
