"""A scenario's events in a process fleet (sitl.fleets.process_fleet): agents removed, or told a new behaviour as the
parameters a ground station would set (PARAM_SET over each vessel's GCS link)."""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
from numpy.typing import NDArray

from behaviors.registry import behavior_class
from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.ground.supervisor import behavior_params
from sitl.experiments.scenario import BehaviorChoice, Event, ScenarioError
from sitl.fleets.fleet import LockstepFleet

BOB_RULE_CARRIED = ("p0", "H", "speed_scale", "max_speed", "goal_radius_m", "leader_id", "goal")


def behavior_parameters(base: BehaviorChoice, new: BehaviorChoice, frame: LocalFrame) -> dict[str, float]:
    """The MAVLink parameters (BOB_*) that make vessels configured with `base` run `new` (set-behavior events).

    A vessel builds its behaviour from the parameters over its configured choice
    (`bob_autonomy.ground.supervisor`): the parameters carry the behaviour's index and, for the BoB rule, p0, H,
    the speeds, the goal radius, the goal and the leader; every other parameter of the behaviour stays the
    configured one. So the parameters carried get their values from `new` (the behaviour's defaults where
    `new` leaves them out, as a lockstep run would), and `new` must agree with `base` on all the rest.
    Raises ScenarioError naming what no parameter carries.
    """
    carried = BOB_RULE_CARRIED if new.behavior == "bob-rule" else ()
    if (base.avoid_obstacles, base.avoid_params) != (new.avoid_obstacles, new.avoid_params):
        raise ScenarioError("set-behavior: obstacle avoidance cannot be changed over MAVLink")
    if (base.avoid_collisions, base.collision_params) != (new.avoid_collisions, new.collision_params):
        raise ScenarioError("set-behavior: collision avoidance cannot be changed over MAVLink")
    kept = {k: v for k, v in base.params.items() if k not in carried} if base.behavior == new.behavior else {}
    wanted = {k: v for k, v in new.params.items() if k not in carried}
    if kept != wanted:
        names = sorted(k for k in set(kept) | set(wanted) if kept.get(k) != wanted.get(k))
        raise ScenarioError(
            f"set-behavior to {new.behavior!r}: parameter(s) {names} have no MAVLink parameter and differ from "
            "what the vessels were started with"
        )
    defaults = {f.name: f.default for f in dataclasses.fields(behavior_class(new.behavior))}
    params = {**new.params, **{k: new.params.get(k, defaults.get(k)) for k in carried}}
    try:
        return behavior_params(new.model_copy(update={"params": params}), frame)
    except ValueError as error:
        raise ScenarioError(f"set-behavior: {error}") from None


class ProcessEvents:
    """The scenario's events applied to running vessels, mixed into ProcessFleet."""

    def _apply_events(self) -> None:
        """Scheduled events due now: `remove` stops the vehicle for good; `set-behavior` goes to the vessels as
        MAVLink parameters (in the background: the physics does not wait for the answers)."""
        while self.pending and self.pending[0].t_s <= self.t + 1e-9:
            event = self.pending.pop(0)
            agents = LockstepFleet.event_agents(self, event)  # same selection (and draws) as the lockstep fleet
            if event.action == "remove":
                self.bodies.stop(agents)
            else:
                self._set_behavior(event, agents)
            self.events_log.append({"t_s": round(self.t, 6), "action": event.action, "agents": agents.tolist()})

    def _set_behavior(self, event: Event, agents: NDArray[np.intp]) -> None:
        """Send the new behaviour's parameters to the vessels of `agents` (grouped by the choice they were
        started with); the answers are awaited in a thread, and how long the vessels took (simulated s from the
        event until every one had echoed every parameter) goes into metrics.json `event_delays_s`."""
        assert self.mission is not None and event.choice is not None
        work = []
        for group in sorted({int(self.group_of[a]) for a in agents}):
            vessels = [int(a) + 1 for a in agents if self.group_of[a] == group]
            work.append((vessels, behavior_parameters(self.choices[group], event.choice, self.frame)))
        self.choices.append(event.choice)
        self.names.append(event.choice.build().name)
        self.assignment[agents] = len(self.choices) - 1
        mission, t_event = self.mission, self.t

        def send() -> None:
            try:
                for vessels, params in work:
                    mission.set_params(params, vessels)
                self.event_delays_s.append(round(self.t - t_event, 3))
            except Exception as error:  # reported in metrics.json: the run goes on
                self.event_errors.append(f"t={event.t_s} s: {error}")

        thread = threading.Thread(target=send, name=f"set-behavior-{event.t_s}", daemon=True)
        thread.start()
        self._event_threads.append(thread)
