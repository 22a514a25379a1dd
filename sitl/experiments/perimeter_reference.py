"""The best wall coverage N robots can reach in a room: the reference for perimeter defence's spread.

The perimeter-defense metric counts a wall point as covered when a robot is within `radius_m` of it.
How much of the walls N robots can cover at best (wherever they stand inside the room) says what
"covering the perimeter in the best possible manner" (the paper, with 5 robots) can mean: in the
packaged 13.5 m x 6.2 m room at 2.5 m, 5 robots cover at most 0.84 of the walls, 7 or more all of them.

    python -m sitl.experiments.perimeter_reference 5 7      # prints N, best fraction, positions (m)
"""

from __future__ import annotations

import sys

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import differential_evolution, minimize

FloatArray = NDArray[np.float64]

PACKAGED_ROOM = np.array([[0.0, 0.0], [13.5, 0.0], [13.5, 6.2], [0.0, 6.2]])


def covered_wall_length(positions: FloatArray, room: FloatArray, radius_m: float) -> float:
    """Length (m) of the room's walls within `radius_m` of at least one of `positions` (k, 2) m.

    On a wall from a to b (length L, direction u), a robot at p covers the interval of
    t = (p - a).u +- sqrt(r^2 - h^2), h its distance to the wall's line, clipped to [0, L];
    the covered length is the length of the union of those intervals, exactly.
    """
    p = np.asarray(positions, dtype=float).reshape(-1, 2)
    total = 0.0
    for a, b in zip(room, np.roll(room, -1, axis=0), strict=True):
        length = float(np.hypot(*(b - a)))
        u = (b - a) / length
        w = p - a
        t = w @ u
        h2 = np.einsum("ij,ij->i", w, w) - t**2
        reach = radius_m**2 - h2
        half = np.sqrt(np.maximum(reach, 0.0))
        lo, hi = np.clip(t - half, 0.0, length), np.clip(t + half, 0.0, length)
        keep = (reach > 0.0) & (hi > lo)
        end = 0.0
        for start, stop in sorted(zip(lo[keep], hi[keep], strict=True)):
            total += max(0.0, stop - max(start, end))
            end = max(end, stop)
    return total


def best_wall_coverage(
    n: int, radius_m: float = 2.5, room: FloatArray = PACKAGED_ROOM, margin_m: float = 0.08, seed: int = 0
) -> tuple[float, FloatArray]:
    """(fraction of the walls covered, (n, 2) positions in m) at the best placement found of n robots.

    The robots' centres stay inside the room's bounding box shrunk by `margin_m` (the eBot's radius;
    the room must be a rectangle for this bound). Found by differential evolution (scipy) and refined
    by Nelder-Mead: a lower bound on the true optimum, reached in practice for small n (seeded,
    deterministic).
    """
    lo, hi = room.min(axis=0) + margin_m, room.max(axis=0) - margin_m
    perimeter = float(np.sum(np.hypot(*(np.roll(room, -1, axis=0) - room).T)))
    bounds = [(float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1]))] * n

    def loss(x: FloatArray) -> float:
        return -covered_wall_length(x.reshape(-1, 2), room, radius_m) / perimeter

    found = differential_evolution(loss, bounds, seed=seed, maxiter=1000, popsize=20, tol=1e-10, polish=False)
    refined = minimize(loss, found.x, method="Nelder-Mead", bounds=bounds, options={"xatol": 1e-6, "fatol": 1e-9})
    x = refined.x if refined.fun <= found.fun else found.x
    return -loss(x), x.reshape(-1, 2)


def main(argv: list[str] | None = None) -> None:
    """Print the best coverage of the packaged room for each robot count given."""
    for arg in argv if argv is not None else sys.argv[1:]:
        fraction, positions = best_wall_coverage(int(arg))
        print(arg, f"{fraction:.3f}", np.round(positions, 2).tolist())


if __name__ == "__main__":
    main()
