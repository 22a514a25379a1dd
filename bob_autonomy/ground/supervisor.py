"""What a vessel does on top of its behaviour: the ground station's parameters and commands, and safety.

- The behaviour is built from the parameters (BOB_BEHAVIOR, and for the BoB
  rule p0, H, speeds, goal, leader) over the base choice from the vessel's
  configuration; it is rebuilt whenever a parameter or the goals change.
- The final velocity: the behaviour's while it runs; hold position while it is
  stopped; on ground-station loss the configured action (continue, hold, return
  to the rally point); inside an enabled fence the command is limited at the
  fence, outside it the configured action brings the vessel back.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from behaviors.base import Behavior
from bob_autonomy.core.behavior_config import BehaviorChoice
from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.ground.params import BEHAVIOR_NAMES, ParameterStore
from bob_autonomy.ground.safety import inside_polygon, limit_to_fence, return_inside, towards

logger = logging.getLogger(__name__)

CONTINUE, HOLD, RETURN_TO_RALLY = 0, 1, 2
HOLD_SPEED_MPS = 0.3  # most speed used to get back to a hold point


def behavior_params(choice: BehaviorChoice, frame: LocalFrame) -> dict[str, float]:
    """The parameter values (BOB_*) that select `choice`: its index, and for the BoB rule p0, H, speeds, goal
    (lat/lon through `frame`) and leader (system id = agent id + 1). For mission scripts and fleet runners."""
    if choice.behavior not in BEHAVIOR_NAMES:
        raise ValueError(f"behaviour {choice.behavior!r} has no BOB_BEHAVIOR index; known: {BEHAVIOR_NAMES}")
    values: dict[str, float] = {"BOB_BEHAVIOR": BEHAVIOR_NAMES.index(choice.behavior)}
    if choice.behavior != "bob-rule":
        return values
    p = choice.params
    for key, name in (("p0", "BOB_P0_M"), ("H", "BOB_H"), ("speed_scale", "BOB_SPD_SCALE")):
        if key in p:
            values[name] = float(p[key])
    if "max_speed" in p:
        values["BOB_MAX_SPD_MPS"] = float(p["max_speed"])
    if "goal_radius_m" in p:
        values["BOB_GOAL_R_M"] = float(p["goal_radius_m"])
    values["BOB_LEADER_ID"] = float(p["leader_id"]) + 1 if p.get("leader_id") is not None else 0
    goal = p.get("goal")
    if goal is not None:
        lat, lon = frame.to_geodetic(float(goal[0]), float(goal[1]))
        values["BOB_GOAL_LAT"], values["BOB_GOAL_LON"] = float(lat), float(lon)
    else:
        values["BOB_GOAL_LAT"] = values["BOB_GOAL_LON"] = 0.0
    return values


class Supervisor:
    """The behaviour from the parameters, and the safety layer between it and the controller."""

    def __init__(self, params: ParameterStore, base: BehaviorChoice, frame: LocalFrame) -> None:
        self.params, self.base, self.frame = params, base, frame
        self._dirty = True
        self._behavior: Behavior | None = None
        self.hold_point: np.ndarray | None = None
        self.mode = "behavior"
        params.on_change(self._changed)

    def _changed(self, *_args: Any) -> None:
        self._dirty = True

    def _local(self, lat: float, lon: float) -> np.ndarray:
        x, y = self.frame.to_local(lat, lon)
        return np.array([float(x), float(y)])

    def behavior(self) -> Behavior:
        """The behaviour the parameters select (rebuilt after a change; the old one stays if the new is bad)."""
        if self._dirty or self._behavior is None:
            self._dirty = False
            try:
                self._behavior = self._build()
            except ValueError as error:
                logger.error("parameters give no valid behaviour (%s); keeping the previous one", error)
                if self._behavior is None:
                    self._behavior = self.base.build()
        return self._behavior

    def _build(self) -> Behavior:
        name = self.params.behavior_name
        params: dict[str, Any] = dict(self.base.params) if name == self.base.behavior else {}
        if name == "bob-rule":
            get = self.params.get
            params.update(p0=float(get("BOB_P0_M")), H=int(get("BOB_H")), speed_scale=float(get("BOB_SPD_SCALE")))
            params.update(max_speed=float(get("BOB_MAX_SPD_MPS")), goal_radius_m=float(get("BOB_GOAL_R_M")))
            leader = int(get("BOB_LEADER_ID"))
            goals = self.params.goals
            params["leader_id"] = leader - 1 if leader > 0 else None
            params["goal"] = tuple(self._local(*goals[0])) if goals and leader == 0 else None
        # The configured wrappers (collision and obstacle avoidance) are kept: no parameter carries them.
        choice = {key: getattr(self.base, key) for key in BehaviorChoice.model_fields}
        return BehaviorChoice(**{**choice, "behavior": name, "params": params}).build()

    def _fence(self) -> np.ndarray | None:
        fence = self.params.fence
        if not int(self.params.get("BOB_FENCE_EN")) or len(fence) < 3:
            return None
        return np.array([self._local(lat, lon) for lat, lon in fence])

    def _rally(self) -> np.ndarray | None:
        lat, lon = float(self.params.get("BOB_RALLY_LAT")), float(self.params.get("BOB_RALLY_LON"))
        return None if lat == 0.0 and lon == 0.0 else self._local(lat, lon)

    def _hold(self, position: np.ndarray) -> np.ndarray:
        if self.hold_point is None:
            self.hold_point = position.copy()
        return towards(position, self.hold_point, HOLD_SPEED_MPS)

    def _act(self, action: int, position: np.ndarray, why: str) -> np.ndarray:
        """Velocity for a failsafe action; return-to-rally without a rally point holds."""
        rally = self._rally() if action == RETURN_TO_RALLY else None
        if rally is not None:
            self.mode = f"{why}: return to rally"
            return towards(position, rally, float(self.params.get("BOB_RTL_SPD_MPS")))
        self.mode = f"{why}: hold"
        return self._hold(position)

    def velocity(self, position: np.ndarray, wish: np.ndarray, running: bool, gcs_lost: bool) -> np.ndarray:
        """The velocity (2,) m/s to command, from the behaviour's wish (2,) m/s at the estimated position (2,) m."""
        position = np.asarray(position, dtype=float)
        if not np.all(np.isfinite(position)):
            self.mode = "no position: stop"
            return np.zeros(2)
        fence = self._fence()
        speed = max(float(self.params.get("BOB_RTL_SPD_MPS")), HOLD_SPEED_MPS)
        fence_action = int(self.params.get("BOB_FENCE_ACT"))
        if fence is not None and fence_action != CONTINUE and not inside_polygon(position, fence):
            self.hold_point = None
            rally = self._rally() if fence_action == RETURN_TO_RALLY else None
            if rally is not None and inside_polygon(rally, fence):
                self.mode = "fence breached: return to rally"
                return towards(position, rally, speed)
            self.mode = "fence breached: back inside"
            return return_inside(position, fence, speed)
        gcs_action = int(self.params.get("BOB_GCS_FS_ACT"))
        if gcs_lost and gcs_action != CONTINUE:
            velocity = self._act(gcs_action, position, "ground station lost")
        elif not running:
            self.mode = "stopped: hold"
            velocity = self._hold(position)
        else:
            self.mode = "behavior"
            self.hold_point = None
            velocity = np.nan_to_num(np.asarray(wish, dtype=float))
        if fence is not None:
            velocity = limit_to_fence(position, velocity, fence)
        return velocity if all(math.isfinite(v) for v in velocity) else np.zeros(2)
