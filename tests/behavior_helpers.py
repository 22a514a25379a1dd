"""Small builders of SwarmTable / Senses / View for behaviour tests."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from behaviors.base import Behavior, Senses, SwarmTable, View, Wish


def make_table(
    positions: Sequence[Sequence[float]],
    headings: Sequence[float] | None = None,
    ids: Sequence[int] | None = None,
    memory: dict[str, np.ndarray] | None = None,
) -> SwarmTable:
    """A table of agents at `positions` (m), headings in rad (default 0), ids 1..N by default."""
    position = np.asarray(positions, dtype=float)
    n = position.shape[0]
    return SwarmTable(
        ids=np.asarray(ids if ids is not None else np.arange(1, n + 1), dtype=np.intp),
        position=position,
        heading=np.asarray(headings if headings is not None else np.zeros(n), dtype=float),
        velocity=np.zeros((n, 2)),
        memory=dict(memory or {}),
    )


def all_pairs(n: int) -> list[tuple[int, int]]:
    """Every ordered pair (listener, heard) of distinct rows 0..n-1."""
    return [(i, j) for i in range(n) for j in range(n) if i != j]


def make_view(
    table: SwarmTable,
    pairs: Sequence[tuple[int, int]] | None = None,
    rows: Sequence[int] | None = None,
    senses: Senses | None = None,
) -> View:
    """A view updating `rows` (default all); pairs are (index into rows, table row heard)."""
    n_rows = len(table) if rows is None else len(rows)
    pairs = all_pairs(len(table)) if pairs is None else list(pairs)
    pair_array = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    return View(
        table=table,
        senses=senses if senses is not None else Senses.none(len(table)),
        rows=np.arange(n_rows, dtype=np.intp) if rows is None else np.asarray(rows, dtype=np.intp),
        pair_i=pair_array[:, 0],
        pair_j=pair_array[:, 1],
    )


def vessel_view(view: View, agent: int) -> View:
    """The view one vessel would build for `view.rows[agent]`: row 0 itself, rows 1.. whom it hears."""
    heard = view.pair_j[view.pair_i == agent]
    keep = np.concatenate(([view.rows[agent]], heard))
    table = SwarmTable(
        ids=view.table.ids[keep],
        position=view.table.position[keep],
        heading=view.table.heading[keep],
        velocity=view.table.velocity[keep],
        memory={key: value[keep] for key, value in view.table.memory.items()},
    )
    senses = Senses(obstacles=view.senses.obstacles[keep], light=view.senses.light[keep])
    k = heard.shape[0]
    return View(table, senses, np.zeros(1, dtype=np.intp), np.zeros(k, dtype=np.intp), np.arange(1, k + 1), view.t)


def assert_batch_equivalent(behavior: Behavior, view: View) -> Wish:
    """Check the whole-batch step equals each agent's step on its own vessel view; return the batch wish."""
    batch = behavior.step(view)
    for agent in range(view.n):
        alone = behavior.step(vessel_view(view, agent))
        np.testing.assert_allclose(alone.velocity[0], batch.velocity[agent], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(alone.heading[0], batch.heading[agent], rtol=1e-12, atol=1e-12)
        for key, value in batch.memory.items():
            np.testing.assert_allclose(alone.memory[key][0], value[agent], rtol=1e-12, atol=1e-12)
    return batch
