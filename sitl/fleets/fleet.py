"""The lockstep fleet: every agent's body, network and behaviour stepped at once.

One step: sense, read what the medium delivered, run each behaviour on its
agents (array functions, no loop over agents), move the bodies, broadcast when
due. Time is simulated and advances by dt per step; nothing sleeps; a seed fixes
every random choice, so a run is exactly repeatable.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from behaviors.base import Behavior, MemorySpec, Senses, View, Wish
from sitl.experiments.scenario import Event, Scenario, ScenarioError
from sitl.radio.medium import BroadcastMedium
from sitl.radio.mesh_security import medium_security
from sitl.row_threads import RowThreads
from sitl.vehicles.bodies import BODY_KINDS, EBOT, KinematicBodies
from sitl.world.world import FloatArray, World, points_in_polygon, polygon_segments


def build_world(scenario: Scenario, rng: np.random.Generator) -> World:
    """Walls, rooms and lights of a scenario (random light placement uses `rng`)."""
    spec = scenario.world
    segments = [polygon_segments(np.array(r.polygon)) for r in spec.rooms if r.walls]
    if spec.walls:
        segments.append(np.array(spec.walls, dtype=float))
    walls = np.concatenate(segments) if segments else np.zeros((0, 2, 2))
    rooms = [np.array(r.polygon, dtype=float) for r in spec.rooms]
    lights = [
        np.array(light.position) if light.position else rng.uniform(light.box.min, light.box.max)
        for light in spec.lights
    ]
    return World(
        walls=walls,
        rooms=rooms,
        light_positions=np.array(lights).reshape(-1, 2),
        light_power_w=np.array([light.power_w for light in spec.lights]),
        light_height_m=spec.light_height_m,
    )


def initial_poses(scenario: Scenario, world: World, rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    """Start positions (N, 2) m and headings (N,) rad: drawn in each group's box (at least its min_separation_m from
    each other and from every agent of the groups before it), or on its lattice."""
    positions: list[FloatArray] = []
    headings = []
    for group in scenario.groups:
        box, lattice = group.start.box, group.start.lattice
        if lattice is not None:
            placed = lattice_sites(group.count, lattice.center, lattice.spacing_m, lattice.kind, lattice.angle_deg)
            if not world.inside_rooms(placed).all():
                raise ScenarioError(f"group {group.name!r}: lattice sites fall outside the rooms")
        else:
            taken = np.concatenate(positions) if positions else np.empty((0, 2))
            separation = group.start.min_separation_m
            placed = _sample_separated(group.count, box.min, box.max, separation, world, rng, taken)
        positions.append(placed)
        if group.start.heading_deg == "random":
            headings.append(rng.uniform(-np.pi, np.pi, group.count))
        else:
            headings.append(np.full(group.count, np.radians(group.start.heading_deg)))
    return np.concatenate(positions), np.concatenate(headings)


START_DRAWS = 20  # random start draws tried before a start box counts as too small (_sample_separated)


def lattice_sites(n: int, center, spacing_m: float, kind: str = "triangular", angle_deg: float = 0.0) -> FloatArray:
    """(n, 2) the n sites of a regular lattice nearest `center` (m), one of them at `center`.

    kind: "triangular" or "square", sites `spacing_m` (m) from their nearest
    neighbours; the lattice is turned by `angle_deg` (deg, counter-clockwise)
    about `center`. Sites at equal distance are taken in order of bearing from
    east, counter-clockwise (deterministic: no random draw).
    """
    if kind not in ("triangular", "square"):
        raise ValueError(f"unknown lattice kind {kind!r}")
    reach = int(np.ceil(np.sqrt(n))) + 2  # rows and columns each side: more sites than needed
    i, j = np.meshgrid(np.arange(-reach, reach + 1), np.arange(-reach, reach + 1), indexing="ij")
    i, j = i.ravel().astype(float), j.ravel().astype(float)
    shear, row_height = (0.5, np.sqrt(3.0) / 2.0) if kind == "triangular" else (0.0, 1.0)
    local = np.column_stack((i + shear * j, row_height * j))
    radius = np.round(np.hypot(local[:, 0], local[:, 1]), 9)
    bearing = np.round(np.mod(np.arctan2(local[:, 1], local[:, 0]), 2.0 * np.pi), 9)
    chosen = local[np.lexsort((bearing, radius))[:n]] * spacing_m
    turn = np.radians(angle_deg)
    rotation = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    return chosen @ rotation.T + np.asarray(center, dtype=float)


def _sample_separated(
    n: int, lo, hi, separation: float, world: World, rng: np.random.Generator, taken: FloatArray | None = None
) -> FloatArray:
    """n points uniform in a box, inside the rooms, at least `separation` m apart and from the points `taken`
    (k, 2) m (agents already placed; rejection).

    Points are added one by one (200 n candidates); a draw that jams (no room left for the next point, as 16
    points 80 m apart in a 360 m box can at some seeds) starts again from scratch with the same generator, up
    to START_DRAWS times: a draw that succeeds at the first try is unchanged."""
    for _ in range(START_DRAWS):
        points: list[FloatArray] = []
        for _ in range(200 * n):
            if len(points) == n:
                break
            candidate = rng.uniform(lo, hi)
            if not world.inside_rooms(candidate[None])[0]:
                continue
            if separation:
                near = np.array(points).reshape(-1, 2)
                if taken is not None:
                    near = np.concatenate((taken, near))
                if len(near) and np.min(np.hypot(*(near - candidate).T)) < separation:
                    continue
            points.append(candidate)
        if len(points) == n:
            return np.array(points)
    raise ScenarioError(
        f"cannot place {n} agents {separation} m apart (and from the agents placed before them) in box {lo}..{hi} "
        f"({START_DRAWS} tries): "
        "lower min_separation_m, enlarge the start box or start fewer agents there"
    )


def motorboat_params(scenario: Scenario) -> list:
    """The MotorboatParams of every motorboat of the scenario, in fleet row order."""
    return [g.motorboat_params() for g in scenario.groups if g.body == "motorboat" for _ in range(g.count)]


def make_bodies(
    scenario: Scenario,
    kinds: NDArray[np.int_],
    position: FloatArray,
    heading: FloatArray,
    vessel_processes: int = 1,
) -> KinematicBodies:
    """Kinematic or physical bodies, as the scenario's fidelity says (physics draws from its own stream).
    vessel_processes: processes the buoys' vessel side is spread over (physics; the same results)."""
    boats = motorboat_params(scenario)
    if scenario.fidelity == "kinematic":
        bodies = KinematicBodies(kinds, position, heading)
        bodies.max_speed[bodies.motorboats] = [b.top_speed_mps for b in boats]
        bodies.turning_radius[bodies.motorboats] = [b.turning_radius_m for b in boats]
        return bodies
    from sitl.vehicles.physical_bodies import PhysicalBodies

    rng = np.random.default_rng([scenario.seed, 2])
    thrust = np.concatenate([np.full(g.count, g.thrust_fraction) for g in scenario.groups])
    return PhysicalBodies(
        kinds,
        position,
        heading,
        scenario.environment.build(np.random.default_rng([scenario.seed, 3])),
        scenario.origin.frame(),
        rng,
        thrust,
        scenario.sensors.specs(),
        estimator=scenario.vessel.estimator,
        controller=scenario.vessel.controller,
        dt_s=scenario.dt_s,
        link=scenario.vessel.link,
        motorboat_params=boats,
        vessel_processes=vessel_processes,
    )


class LockstepFleet:
    """All agents of a scenario in one process, stepped in lockstep.

    threads: how a big fleet's passes over its agents and pairs are spread over threads (default: one per core
    available; the results are the same bits with any number). vessel_processes: at physics fidelity, the
    processes the buoys' estimators, controllers and MAVLink links run in (sitl.vehicles.vessel_shards; the same
    bits with any number); `close` stops them.
    """

    def __init__(self, scenario: Scenario, threads: RowThreads | None = None, vessel_processes: int = 1) -> None:
        self.scenario = scenario
        self.threads = RowThreads() if threads is None else threads
        self.rng = np.random.default_rng(scenario.seed)
        self.world = build_world(scenario, self.rng)
        position, heading = initial_poses(scenario, self.world, self.rng)
        kinds = np.concatenate([np.full(g.count, BODY_KINDS[g.body]) for g in scenario.groups])
        self.bodies = make_bodies(scenario, kinds, position, heading, vessel_processes)
        self.n = len(self.bodies)
        self.group_of = np.concatenate([np.full(g.count, k) for k, g in enumerate(scenario.groups)])
        self.group_names = [g.name for g in scenario.groups]
        self.behaviors: list[Behavior] = [g.build() for g in scenario.groups]
        self.assignment = self.group_of.copy()
        memory = self.memory_fields_of(scenario)
        net = scenario.network
        radio_rng = np.random.default_rng([scenario.seed, 1])  # its own stream: radio draws never shift the rest
        self.medium = BroadcastMedium(
            self.n,
            net.range_m,
            net.broadcast_period_s,
            net.expiry_s,
            memory,
            net.channel(),
            radio_rng,
            security=medium_security(scenario, self.group_of),  # key, plausibility, intruders, faults
        )
        self.medium.threads = self.bodies.threads = self.threads
        self.table = self.medium.table
        self.table.ids[: self.n] = np.arange(self.n)
        self.own_memory = {name: self.table.memory[name][: self.n] for name in memory}
        self.pending = sorted(scenario.events, key=lambda e: e.t_s)
        self.step_index = 0
        self.t = 0.0
        self.events_log: list[dict] = []
        self.sync_table()

    def close(self) -> None:
        """Release what the fleet holds outside this process (vessel worker processes); idempotent."""
        close = getattr(self.bodies, "close", None)
        if close is not None:
            close()

    @staticmethod
    def memory_fields_of(scenario: Scenario) -> dict[str, MemorySpec]:
        fields: dict[str, MemorySpec] = {}
        choices = [g.build() for g in scenario.groups]
        choices += [e.choice.build() for e in scenario.events if e.choice is not None]
        for behavior in choices:
            for name, spec in behavior.memory_fields.items():
                if name in fields and fields[name] != spec:
                    raise ScenarioError(f"behaviours disagree on memory field {name!r}")
                fields[name] = spec
        return fields

    @property
    def active(self) -> NDArray[np.bool_]:
        return self.bodies.active

    def behavior_names(self) -> list[str]:
        """Name of the behaviour each agent runs."""
        names = [b.name for b in self.behaviors]
        return [names[k] for k in self.assignment]

    def sync_table(self) -> None:
        """Copy the bodies' current states into table rows [0, N) (what each agent knows of itself)."""
        n = self.n
        position, heading, velocity = self.bodies.believed()
        self.table.position[:n] = position
        self.table.heading[:n] = heading
        self.table.velocity[:n] = velocity

    def senses(self) -> Senses:
        """Range finders and light sensors of the eBots; buoys sense neither (NaN)."""
        ebots = self.bodies.ebots[self.active[self.bodies.ebots]]
        has_sonar = self.bodies.ebots.size > 0
        obstacles = np.full((self.n, 6 if has_sonar else 0, 2), np.nan)
        light = np.full((self.n, 2), np.nan)
        if ebots.size:
            obstacles[ebots] = self.bodies.range_finders(ebots, self.world)
            light[ebots] = self.bodies.light_sensors(ebots, self.world)
        return Senses(obstacles=obstacles, light=light)

    def step(self) -> None:
        """Advance the whole fleet by one dt."""
        self.apply_events()
        self.sync_table()
        wish = self.decide(self.senses())
        self.finish_step(wish)

    def finish_step(self, wish: Wish) -> None:
        """Broadcast (when due) the states the decisions were made from, then move the bodies.

        Messages sent at step k are heard from step k + 1 on, exactly as an
        agent that broadcasts at the end of its update.
        """
        if self.medium.due(self.t):
            self.medium.broadcast(self.t, self.active, latency_s=self.scenario.dt_s)
        self.bodies.apply(wish.velocity, wish.heading, self.scenario.dt_s, self.world)
        self.step_index += 1
        self.t = self.step_index * self.scenario.dt_s

    def decide(self, senses: Senses) -> Wish:
        """Every active agent's wish from its behaviour (velocity m/s, heading rad)."""
        listener, message = self.medium.heard_pairs(self.t, self.active)
        velocity = np.zeros((self.n, 2))
        heading = np.full(self.n, np.nan)
        local = np.full(self.n, -1, dtype=np.intp)
        for k, behavior in enumerate(self.behaviors):
            rows = np.flatnonzero((self.assignment == k) & self.active)
            if rows.size == 0:
                continue
            if rows.size == self.n:  # one behaviour for the whole fleet: every listener is its own row
                view = View(self.table, senses, rows, listener, message, self.t)
            else:
                local[rows] = np.arange(rows.size)
                keep = local[listener] >= 0
                view = View(self.table, senses, rows, local[listener[keep]], message[keep], self.t)
                local[rows] = -1
            wish = self._behavior_step(behavior, view)
            where = slice(None) if rows.size == self.n else rows  # (a slice copies, rows scatter)
            velocity[where] = wish.velocity
            heading[where] = wish.heading
            for name, values in wish.memory.items():
                self.own_memory[name][rows] = values
        return Wish(velocity, heading)

    def _behavior_step(self, behavior: Behavior, view: View) -> Wish:
        """behavior.step(view); a row-wise behaviour's many rows in parts on the fleet's threads."""
        ranges = self.threads.ranges(view.n, view.pair_i.size) if behavior.rowwise else [(0, view.n)]
        if len(ranges) > 1:
            parts = self.threads.map(lambda lo, hi: _part_step(behavior, view, lo, hi), ranges)
            if all(part is not None for part in parts):
                return Wish.joined(parts)
        return behavior.step(view)  # one part, or pairs not in listener order

    def apply_events(self) -> None:
        """Carry out the scheduled events that are due at the current time."""
        while self.pending and self.pending[0].t_s <= self.t + 1e-9:
            event = self.pending.pop(0)
            agents = self.event_agents(event)
            if event.action == "remove":
                self.bodies.active[agents] = False
            else:
                self.behaviors.append(event.choice.build())
                self.assignment[agents] = len(self.behaviors) - 1
            self.events_log.append({"t_s": round(self.t, 6), "action": event.action, "agents": agents.tolist()})

    def event_agents(self, event: Event) -> NDArray[np.intp]:
        if event.agents is not None:
            agents = np.array(event.agents, dtype=np.intp)
            if agents.size and (agents.min() < 0 or agents.max() >= self.n):
                raise ScenarioError(f"event at t={event.t_s} s names agents outside 0..{self.n - 1}")
            return agents
        pool = self.active.copy()
        if event.group is not None:
            pool &= self.group_of == self.group_names.index(event.group)
        if event.box is not None:
            p = self.bodies.position
            lo, hi = event.box.min, event.box.max
            pool &= (p[:, 0] >= lo[0]) & (p[:, 0] <= hi[0]) & (p[:, 1] >= lo[1]) & (p[:, 1] <= hi[1])
            return np.flatnonzero(pool)
        candidates = np.flatnonzero(pool)
        count = event.count if event.count is not None else max(1, round(event.fraction * candidates.size))
        if count > candidates.size:
            raise ScenarioError(f"event at t={event.t_s} s wants {count} agents, only {candidates.size} are active")
        return np.sort(self.rng.choice(candidates, size=count, replace=False))

    def inside_rooms(self) -> NDArray[np.bool_]:
        return self.world.inside_rooms(self.bodies.position)

    def light_seen(self) -> bool:
        """Whether any agent has recorded a light target (for search metrics)."""
        light = self.own_memory.get("target_light")
        return bool(light is not None and np.any(np.isfinite(light[self.active])))


def _part_step(behavior: Behavior, view: View, lo: int, hi: int) -> Wish | None:
    """The wish of rows [lo, hi) of the view alone (None when its pairs are not in listener order)."""
    part = view.part(lo, hi)
    return None if part is None else behavior.step(part)


__all__ = ["EBOT", "LockstepFleet", "build_world", "initial_poses", "points_in_polygon"]
