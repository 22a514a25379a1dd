"""The BoB rule, eq. (5) of the paper: aggregation, goal seeking, leader-follower.

    v_i = H beta_i + (1/N_i) sum_{j in N_i} gamma_ij f(d_ij) + (H/N_i) sum_{j in R_i + {i}} theta_j

beta_i is the unit bearing from agent i to its goal, gamma_ij the unit vector
from i to neighbour j at distance d_ij, theta_j the unit heading vector of j,
N_i the number of neighbours heard and R_i those within p0 (d_ij <= p0). The
desired velocity is `speed_scale * v_i` m/s, capped at `max_speed`.

The pair factor, as printed, is f = (1 - H) - p0^2 / d^2. We read it as the
design note puts it, "zero at p0, attracts beyond it when H = 0, only repels
when H = 1": for H = 0, f = 1 - p0^2/d^2 (zero at p0, attraction beyond,
repulsion inside); for H = 1, f = min(0, 1 - p0^2/d^2), which repels only
inside p0 and is zero beyond. (The printed -p0^2/d^2 would repel at every
range, so an agent could never pass between fixed agents spaced 2 p0 apart;
with our reading an agent with p0 = 50 m goes through a fixed lattice spaced
100 m and one with p0 = 100 m goes around it, as in the paper's figure.)

Going around (`skirt`, not in the paper; off by default): with H = 1 and
repulsion only, eq. (5) is a potential field with local minima. An agent whose
way a fixed lattice blocks settles where the repulsion of its neighbours
cancels the goal pull, in the first pocket of the lattice's edge it meets, and
never reaches its goal. With `skirt`, the part of the goal pull that points
into the repulsion, b = max(0, -beta . n) with n the unit repulsion, is also
applied to the left of the direction to the neighbours (-n turned +90 deg),
as the obstacle-avoidance wrapper turns the blocked part of a wish along a
wall: the agent keeps the neighbours on its right and follows the edge of the
group (a bug algorithm's boundary following) until the goal is no longer
behind them. Always the same side, so it does not dither; the term starts as
soon as any neighbour is within p0 (where the repulsion starts), so the agent
follows the outer envelope of the group, which has shallower pockets than the
contour where the repulsion balances the pull.

Resilient consensus (`resilient_f` = F > 0, beyond the paper): the consensus sum
keeps only what the W-MSR rule (`behaviors.resilient`) keeps of the headings (or
courses) heard within p0: up to F on each side of the agent's own, the most
extreme by circular difference, are left out; the factor H/N_i stays the
paper's (N_i all neighbours heard), so F = 0 is eq. (5) exactly. With
`align_course` the values are courses, compared with the agent's own course (its
hull heading while it is still); a still neighbour's course (zero velocity, a
zero term in the sum) counts as equal to the agent's own and is never left out.

Neighbourhood of the pair term (`shell_range` > 0, beyond the paper, which
leaves N_i as "the neighbours"): f tends to 1 beyond p0, so every neighbour in
N_i beyond the first shell pulls, and a large N_i squeezes a lattice well below
p0: with all 44 others heard, 45 agents settle at about 0.33 p0 (a 100 m2 hull
at p0 = 5 m). A topological N_i of the k nearest squeezes less but lets the
swarm split into isolated groups of k + 1 or more (with k = 20, two groups of
about 22 whose distance apart, not the lattice, made the hull). With
`shell_range`, an agent that is inside a lattice, at least `lattice_min` agents
heard within `lattice_range` * p0, counts only those within `shell_range` * p0
(its own shell, where f balances at p0); an agent that is not (alone, or the
swarm spread far wider than p0, as just after p0 drops) counts every agent
heard (or its `nearest`), so it is drawn toward the group as a whole, which
contracts keeping each agent's bearing from the centre (as the paper's field
test notes). Eq. (5) is unchanged; only the set N_i is chosen. shell_range
1.3 lies between a hexagonal lattice's first ring (p0) and its second (sqrt(3)
p0), so the second ring enters the shell only once the spacing is below 0.75
p0. Every member of a hexagonal lattice of 19 or more spaced p0 hears 8 or more
agents within 2 p0, and a group of fewer than 7 cannot be all inside a lattice
with lattice_min 6, so such a group does not hold apart from the swarm (a group
of 7 or more could; the contraction toward the whole swarm makes it rare).
With shell_range 1.3, lattice_range 2, lattice_min 6, 45 buoys aggregate at
p0 = 5 m into one blob spaced about 0.9 p0 (hull ~800-1,050 m2, physics, seeds
1-10; see the aggregation scenario).

An agent that hears nobody has zero pair and consensus terms. Uses:
aggregation is BobRule(H=0); goal seeking BobRule(H=1, goal=(x, y));
leader-follower BobRule(H=1, leader_id=k): the goal is the position of agent
k where the agent hears it (k among its neighbour pairs), otherwise the last
position heard, kept in the memory field "goal"; never heard, no goal term.
An agent never takes itself as goal (the leader's own goal term is zero).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from behaviors.base import (
    Behavior,
    FloatArray,
    MemorySpec,
    View,
    Wish,
    heading_vectors,
    limit_speed,
    unit,
    wrap_angle,
)
from behaviors.resilient import wmsr_keep


@dataclass
class BobRule(Behavior):
    """Lattice-forming motion with an optional goal (eq. 5).

    p0: equilibrium distance between neighbours, m.
    H: heading consensus weight, 0 (position only among the others) or 1
        (go to the goal, align with neighbours within p0, repel only).
    speed_scale: m/s per unit of v_i (the desired velocity is speed_scale * v_i).
    max_speed: cap on the desired speed, m/s.
    goal: fixed goal (x, y), m, or None.
    leader_id: id of the agent whose position is the goal (leader-follower),
        or None. Not together with `goal`.
    nearest: if set, N_i is only the `nearest` closest neighbours heard (a
        topological neighbourhood; it may split a spread swarm into groups).
    align_course: if true, the consensus term aligns the direction of travel
        (unit velocity; zero when still) instead of the hull heading: for an
        omnidirectional buoy the hull heading says nothing about its motion.
    goal_radius_m: if positive, the goal term fades linearly to zero inside
        this distance of the goal (0, as printed: a unit pull at any distance,
        which piles a large group of followers onto its leader).
    skirt: if true (H = 1 only), an agent whose goal pull the repulsion of its
        neighbours opposes also moves to the left of them by the opposed part of
        the pull (unit speed scale): it goes around a blocking group instead of
        stopping in a pocket of its edge (see the module docstring).
    gabriel: if true, N_i is only the Gabriel neighbours among those heard
        (j such that no other heard agent lies inside the circle on the
        segment i-j as diameter): a local, Voronoi-like neighbourhood that keeps
        the swarm connected and gives a lattice spaced about p0, where all heard
        neighbours pull a large swarm much tighter than p0.
    shell_range: if positive, N_i of an agent inside a lattice is only the
        agents heard within shell_range * p0 (m); 0: not used (see the module
        docstring). An agent is inside a lattice when it hears at least
        `lattice_min` agents within `lattice_range` * p0 (m); otherwise N_i is
        every agent heard, or its `nearest`.

    resilient_f: F of the W-MSR rule applied to the consensus sum (H = 1): up to
        F headings heard within p0 on each side of the agent's own are left out
        (0: eq. (5) as printed).
    """

    name: ClassVar[str] = "bob-rule"
    rowwise: ClassVar[bool] = True
    memory_fields: ClassVar[dict[str, MemorySpec]] = {"goal": MemorySpec(shape=(2,))}
    p0: float = 10.0
    H: int = 0
    speed_scale: float = 0.5
    max_speed: float = 1.0
    goal: tuple[float, float] | None = None
    leader_id: int | None = None
    nearest: int | None = None
    gabriel: bool = False
    goal_radius_m: float = 0.0
    align_course: bool = False
    skirt: bool = False
    resilient_f: int = 0
    shell_range: float = 0.0
    lattice_range: float = 2.0
    lattice_min: int = 6

    def __post_init__(self) -> None:
        if self.shell_range < 0.0 or self.lattice_range <= 0.0 or self.lattice_min < 1:
            raise ValueError(
                f"shell_range must be >= 0, lattice_range > 0 and lattice_min >= 1, not "
                f"{self.shell_range!r}, {self.lattice_range!r}, {self.lattice_min!r}"
            )
        if self.shell_range and self.gabriel:
            raise ValueError("shell_range and gabriel are two different neighbourhoods: give one")
        if not isinstance(self.resilient_f, int | np.integer) or self.resilient_f < 0:
            raise ValueError(f"resilient_f must be a whole number >= 0, not {self.resilient_f!r}")
        if self.H not in (0, 1):
            raise ValueError(f"H must be 0 or 1, not {self.H!r}")
        if self.goal is not None and self.leader_id is not None:
            raise ValueError("give either a fixed goal or a leader_id, not both")
        if self.nearest is not None and self.nearest < 1:
            raise ValueError(f"nearest must be at least 1, not {self.nearest!r}")
        if self.skirt and not self.H:
            raise ValueError("skirt needs H = 1 (a goal to go around the group to)")

    def step(self, view: View) -> Wish:
        goal = self.goals(view)
        if self.shell_range > 0.0:
            view = view.restrict(
                shell_pairs(
                    view, self.shell_range * self.p0, self.lattice_range * self.p0, self.lattice_min, self.nearest
                )
            )
        elif self.nearest is not None:
            view = view.restrict(nearest_pairs(view, self.nearest))
        if self.gabriel:
            view = view.restrict(gabriel_pairs(view))
        count = view.neighbor_count()
        per_neighbour = np.divide(1.0, count, out=np.zeros_like(count), where=count > 0)
        d = view.offsets()
        d2 = np.einsum("ij,ij->i", d, d)
        v = per_neighbour[:, None] * view.sum_pairs(unit(d) * self.pair_factor(d2)[:, None])
        if self.H:
            # A leader's own goal is its position: a zero bearing, so no goal term.
            to_goal = np.where(np.isfinite(goal), goal - view.position, 0.0)
            within = view.restrict(d2 <= self.p0**2)
            if self.resilient_f:
                within = within.restrict(self.resilient_pairs(within))
            if self.align_course:
                heard = within.sum_pairs(unit(view.table.velocity[within.pair_j]))
                thetas = unit(view.table.velocity[view.rows]) + heard
            else:
                heard = within.sum_pairs(heading_vectors(view.table.heading[within.pair_j]))
                thetas = heading_vectors(view.heading) + heard
            pull = unit(to_goal)
            if self.goal_radius_m > 0.0:
                pull *= np.minimum(1.0, np.hypot(to_goal[:, 0], to_goal[:, 1]) / self.goal_radius_m)[:, None]
            if self.skirt:
                v = v + skirt_term(v, pull)
            v = v + self.H * pull + self.H * per_neighbour[:, None] * thetas
        velocity = limit_speed(self.speed_scale * v, self.max_speed)
        return Wish(velocity, np.full(view.n, np.nan), {"goal": goal})

    def resilient_pairs(self, within: View) -> np.ndarray:
        """(M,) mask of the pairs of `within` whose heading (or course) W-MSR keeps in the consensus sum."""
        if self.align_course:
            own_v, heard_v = within.table.velocity[within.rows], within.table.velocity[within.pair_j]
            own_moving = np.hypot(own_v[:, 0], own_v[:, 1]) > 0.0
            own = np.where(own_moving, np.arctan2(own_v[:, 1], own_v[:, 0]), within.heading)
            heard = np.arctan2(heard_v[:, 1], heard_v[:, 0])
            difference = wrap_angle(heard - own[within.pair_i])
            difference = np.where(np.hypot(heard_v[:, 0], heard_v[:, 1]) == 0.0, 0.0, difference)
        else:
            difference = wrap_angle(within.table.heading[within.pair_j] - within.heading[within.pair_i])
        return wmsr_keep(difference, within.pair_i, self.resilient_f)

    def pair_factor(self, d2: FloatArray) -> FloatArray:
        """(M,) f(d) from squared distances d2 (m^2); 0 for coincident agents."""
        f = 1.0 - np.divide(self.p0**2, d2, out=np.full_like(d2, np.inf), where=d2 > 0.0)
        if self.H:
            f = np.minimum(f, 0.0)
        return np.where(d2 > 0.0, f, 0.0)

    def goals(self, view: View) -> FloatArray:
        """(n, 2) each agent's goal, m (NaN if none is known); the new "goal" memory."""
        if self.goal is not None:
            return np.tile(np.asarray(self.goal, dtype=float), (view.n, 1))
        remembered = view.table.memory.get("goal")
        goal = np.full((view.n, 2), np.nan) if remembered is None else remembered[view.rows].copy()
        if self.leader_id is None:
            return goal
        heard = view.table.ids[view.pair_j] == self.leader_id
        goal[view.pair_i[heard]] = view.table.position[view.pair_j[heard]]
        is_self = view.table.ids[view.rows] == self.leader_id
        goal[is_self] = view.position[is_self]
        return goal


def skirt_term(repulsion: FloatArray, pull: FloatArray) -> FloatArray:
    """(n, 2) the sideways term of `skirt`, in units of eq. (5) (times speed_scale: m/s).

    repulsion: (n, 2) the pair term of eq. (5) (H = 1: repulsion only).
    pull: (n, 2) the goal term (the unit bearing to the goal, less near it with
    goal_radius_m; zero rows: no goal). With n the unit repulsion, the opposed
    part of the pull b = max(0, -pull . n) pushes along -n turned +90 deg, to
    the left of the direction to the neighbours. Zero where there is no
    repulsion or it does not oppose the pull.
    """
    away = unit(repulsion)
    blocked = np.maximum(0.0, -np.einsum("ij,ij->i", pull, away))
    left_of_neighbours = np.column_stack((away[:, 1], -away[:, 0]))
    return blocked[:, None] * left_of_neighbours


def shell_pairs(view: View, shell_m: float, lattice_m: float, lattice_min: int, nearest: int | None) -> np.ndarray:
    """(M,) mask of the pairs in N_i with `shell_range` (see the module docstring).

    A listener with at least `lattice_min` pairs within lattice_m (m) keeps its pairs within shell_m (m);
    any other keeps all its pairs, or its `nearest` closest if that is set.
    """
    d = view.offsets()
    d2 = np.einsum("ij,ij->i", d, d)
    in_lattice = np.bincount(view.pair_i, weights=d2 <= lattice_m**2, minlength=view.n) >= lattice_min
    wide = np.ones(d2.size, dtype=bool) if nearest is None else nearest_pairs(view, nearest)
    return np.where(in_lattice[view.pair_i], d2 <= shell_m**2, wide)


def nearest_pairs(view: View, k: int) -> np.ndarray:
    """(M,) mask of the pairs that are among the k closest neighbours of their listener."""
    d = view.offsets()
    d2 = np.einsum("ij,ij->i", d, d)
    order = np.lexsort((d2, view.pair_i))
    listener = view.pair_i[order]
    starts = np.searchsorted(listener, listener, side="left")
    rank = np.arange(order.size) - starts
    keep = np.zeros(order.size, dtype=bool)
    keep[order] = rank < k
    return keep


def gabriel_pairs(view: View) -> np.ndarray:
    """(M,) mask of the pairs (i, j) with no other neighbour k of i inside the circle on i-j as diameter.

    k is inside when the angle i-k-j is obtuse: (p_i - p_k) . (p_j - p_k) < 0.
    Costs the sum over agents of (neighbours heard)^2.
    """
    m = view.pair_i.size
    if m == 0:
        return np.zeros(0, dtype=bool)
    order = np.argsort(view.pair_i, kind="stable")
    listener = view.pair_i[order]
    offsets = view.offsets()[order]  # p_j - p_i, grouped by listener
    starts = np.searchsorted(listener, listener, side="left")
    sizes = np.bincount(listener, minlength=view.n)[listener]
    first = np.repeat(np.arange(m), sizes)  # each pair, once per other pair of the same listener
    second = np.repeat(starts, sizes) + (np.arange(first.size) - np.repeat(np.cumsum(sizes) - sizes, sizes))
    a, b = offsets[first], offsets[second]  # a = p_j - p_i, b = p_k - p_i
    inside = (first != second) & (np.einsum("ij,ij->i", -b, a - b) < 0.0)
    blocked = np.bincount(first, weights=inside, minlength=m) > 0
    keep = np.zeros(m, dtype=bool)
    keep[order] = ~blocked
    return keep
