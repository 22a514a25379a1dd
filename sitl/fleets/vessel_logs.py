"""What the autonomy processes of a process fleet reported when they stopped, read back from their logs.

Each `bob-autonomy run` process ends its log with one line `vessel N stopped: {JSON}`
(`bob_autonomy.onboard.vessel.Vessel.shutdown`): its `VesselStats` summary, in which the ground-station
component's rejected-input counters appear as `gcs_unsigned_rejected`, `gcs_bad_signature`,
`gcs_replay_rejected`, `gcs_malformed` and `gcs_out_of_range`. A process that was killed or crashed
writes no such line: it is listed as unreported rather than counted as zero.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from pathlib import Path

from bob_autonomy.ground.gcs import GcsCounters

__all__ = ["collision_counters", "gcs_counters", "stopped_summary"]

_STOPPED = re.compile(r"vessel (\d+) stopped: (\{.*\})\s*$")


def stopped_summary(log: Path) -> dict | None:
    """The JSON summary of the last `vessel N stopped:` line of a vessel's log; None when there is none (or
    the file cannot be read)."""
    try:
        lines = Path(log).read_text(errors="replace").splitlines()
    except OSError:
        return None
    for line in reversed(lines):
        match = _STOPPED.search(line)
        if match:
            try:
                summary = json.loads(match.group(2))
            except json.JSONDecodeError:
                return None
            return summary if isinstance(summary, dict) else None
    return None


def gcs_counters(logs: Mapping[int, Path]) -> dict:
    """The ground-station components' rejected-input counters of a fleet, from the logs of its vessels
    (system id -> log file): `total` over the vessels that reported, `by_vessel` (system id as text, as JSON
    keys are), and `unreported` (system ids whose log has no stop line)."""
    names = GcsCounters.SECURITY
    total = dict.fromkeys(names, 0)
    by_vessel: dict[str, dict[str, int]] = {}
    unreported: list[int] = []
    for system_id, log in sorted(logs.items()):
        summary = stopped_summary(log)
        if summary is None:
            unreported.append(system_id)
            continue
        counters = {name: int(summary.get(f"gcs_{name}", 0)) for name in names}
        by_vessel[str(system_id)] = counters
        for name, value in counters.items():
            total[name] += value
    return {"total": total, "by_vessel": by_vessel, "unreported": unreported}


def collision_counters(logs: Mapping[int, Path]) -> dict:
    """What collision avoidance (behaviors.collision_avoidance) did in a fleet, from the logs of its vessels (system
    id -> log file): `interventions` (updates whose wish it changed) and `updates` summed over the vessels that
    reported, and `by_vessel` (system id as text: [interventions, updates]); {} when no vessel ran it."""
    by_vessel: dict[str, list[int]] = {}
    for system_id, log in sorted(logs.items()):
        summary = stopped_summary(log) or {}
        updates = int(summary.get("collision_updates", 0))
        if updates:
            by_vessel[str(system_id)] = [int(summary.get("collision_interventions", 0)), updates]
    if not by_vessel:
        return {}
    total = [sum(counts[k] for counts in by_vessel.values()) for k in (0, 1)]
    return {"interventions": total[0], "updates": total[1], "by_vessel": by_vessel}
