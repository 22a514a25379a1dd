"""Behaviours by name, so scenarios and configuration files can choose them."""

from __future__ import annotations

from behaviors.base import Behavior
from behaviors.bob_rule import BobRule
from behaviors.coverage import AreaCoverage
from behaviors.heading_consensus import HeadingConsensus, HoldHeading
from behaviors.marching import Marching
from behaviors.obstacle_avoidance import AvoidObstacles
from behaviors.perimeter_defense import PerimeterDefense
from behaviors.search_rendezvous import SearchRendezvous
from behaviors.station_keeping import HoldPosition
from behaviors.waypoints import FollowWaypoints

BEHAVIORS: dict[str, type[Behavior]] = {
    cls.name: cls
    for cls in (
        HeadingConsensus,
        HoldHeading,
        PerimeterDefense,
        BobRule,
        SearchRendezvous,
        Marching,
        AreaCoverage,
        FollowWaypoints,
        HoldPosition,
    )
}


def behavior_class(name: str) -> type[Behavior]:
    """The behaviour class registered as `name`; KeyError lists the known names."""
    try:
        return BEHAVIORS[name]
    except KeyError:
        raise KeyError(f"unknown behavior {name!r}; known: {', '.join(sorted(BEHAVIORS))}") from None


def with_avoidance(behavior: Behavior, **params: float) -> Behavior:
    """Wrap `behavior` so that it steers clear of range-finder echoes."""
    return AvoidObstacles(inner=behavior, **params)
