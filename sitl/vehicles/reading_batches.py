"""Readings decoded vehicle by vehicle, merged into batches over vehicles: one estimator call per kind and round.

Why: the lockstep fleet decodes each simulated vehicle's MAVLink telemetry on its
own, so every vessel's GPS fix, compass heading and IMU sample arrives as its own
one-row reading, and the estimator bank (vectorized over vessels) was entered
once per reading of each vessel: 135,000 calls for 45 buoys over 300 s. The
readings carry their agent rows and measurement times, so the same work can be
handed over as one reading per kind holding every vessel's row.

What: the k-th reading each vehicle decoded this step forms round k; within a
round, readings of the same kind (and the same optional fields) become one
reading with the rows of all of them. Every vessel's own readings keep their
order (round by round), and readings of different vessels never depended on
each other, so what each vessel's estimator computes is unchanged. Anything
that is not a reading (or a kind with no rows) passes through as it came.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from firmware_bridge.batch_decoder import Columns, Row
from firmware_bridge.readings import CompassReading, EncoderReading, GpsFix, ImuReading, LightReading, RangeReading

MERGEABLE = (GpsFix, CompassReading, ImuReading, EncoderReading, RangeReading, LightReading)


def merge_by_round(per_vehicle: Sequence[Sequence[object]], columns: Columns | None = None) -> list[object]:
    """The readings of all vehicles (each vehicle's list in its own order), merged round by round (module doc).
    Readings decoded column-wise come as `Row`s of `columns` (firmware_bridge.batch_decoder) and are merged
    alike."""
    merged: list[object] = []
    for k in range(max((len(readings) for readings in per_vehicle), default=0)):
        groups: dict[tuple, list[object]] = {}
        for readings in per_vehicle:
            if k >= len(readings):
                continue
            reading = readings[k]
            if isinstance(reading, Row):
                groups.setdefault(reading.key, []).append(reading)
                continue
            if not isinstance(reading, MERGEABLE):
                merged.append(reading)
                continue
            present = tuple(getattr(reading, f.name) is not None for f in dataclasses.fields(reading))
            groups.setdefault((type(reading), present), []).append(reading)
        merged += [_concatenate(group, columns) for group in groups.values()]
    return merged


def _concatenate(group: list[object], columns: Columns | None) -> object:
    """One reading holding the rows of all of `group` (same kind, same optional fields present), in order."""
    if all(isinstance(reading, Row) for reading in group):
        return columns.take(group[0].key, [row.index for row in group])
    group = [columns.take(r.key, [r.index]) if isinstance(r, Row) else r for r in group]
    if len(group) == 1:
        return group[0]
    first = group[0]
    values = {}
    for field in dataclasses.fields(first):
        parts = [getattr(reading, field.name) for reading in group]
        values[field.name] = None if parts[0] is None else np.concatenate([np.asarray(p) for p in parts])
    return type(first)(**values)
