"""A behaviour chosen by name with its parameters: what a scenario group or a vessel's configuration says.

Validated with pydantic so that a bad name or parameter is a clear error that
says which; shared by the simulator's scenario files and the `bob-autonomy`
process (which gets it as JSON on its command line or from its config file).
"""

from __future__ import annotations

import dataclasses
from typing import Any

from pydantic import BaseModel, ConfigDict, TypeAdapter, model_validator

from behaviors.base import Behavior
from behaviors.collision_avoidance import AvoidCollisions
from behaviors.obstacle_avoidance import AvoidObstacles
from behaviors.registry import behavior_class, with_avoidance


def check_names(params: dict[str, Any], cls: type, what: str) -> None:
    """ValueError naming the unknown keys of `params` for dataclass `cls` (and the known ones)."""
    known = {f.name for f in dataclasses.fields(cls) if f.init} - {"inner"}
    unknown = sorted(set(params) - known)
    if unknown:
        raise ValueError(f"unknown {what}: {unknown}; known: {sorted(known)}")


def build_dataclass(cls: type, params: dict[str, Any], what: str) -> Any:
    """An instance of dataclass `cls` from `params`: names checked, values validated (ValueError if not)."""
    check_names(params, cls, what)
    return TypeAdapter(cls).validate_python(params)


class BehaviorChoice(BaseModel):
    """A behaviour by registered name, its parameters, optional collision avoidance between agents
    (`behaviors.collision_avoidance`, with `collision_params`) and optional obstacle avoidance (range finders,
    `behaviors.obstacle_avoidance`, with `avoid_params`), applied in that order: the obstacle veto is last."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    behavior: str
    params: dict[str, Any] = {}
    avoid_obstacles: bool = False
    avoid_params: dict[str, float] = {}
    avoid_collisions: bool = False
    collision_params: dict[str, float] = {}

    @model_validator(mode="after")
    def _buildable(self) -> BehaviorChoice:
        self.build()
        return self

    def build(self) -> Behavior:
        """An instance of the chosen behaviour with validated parameters (ValueError if not)."""
        try:
            cls = behavior_class(self.behavior)
        except KeyError as error:
            raise ValueError(error.args[0]) from None
        behavior = build_dataclass(cls, self.params, f"parameter(s) for {self.behavior!r}")
        if self.avoid_collisions:
            check_names(self.collision_params, AvoidCollisions, "collision_params")
            behavior = AvoidCollisions(inner=behavior, **self.collision_params)
        elif self.collision_params:
            raise ValueError("collision_params given without avoid_collisions = true")
        if not self.avoid_obstacles:
            return behavior
        check_names(self.avoid_params, AvoidObstacles, "avoid_params")
        return with_avoidance(behavior, **self.avoid_params)
