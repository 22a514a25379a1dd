"""A MAVProxy module for the interop tests (`module load mavproxy_probe`, with this directory on PYTHONPATH): it
reports what MAVProxy received from each system and component, so that a test can check every vessel on one link,
not only MAVProxy's current target (whose messages alone MAVProxy prints).

`probe` prints one line, `PROBE {json}`: per "sysid:compid", the seconds since the module was loaded, how many frames
of each message type arrived, and the last HEARTBEAT, SYS_STATUS, GPS_RAW_INT, GLOBAL_POSITION_INT, HOME_POSITION
and AUTOPILOT_VERSION as dictionaries (their MAVLink field names). Multi-vehicle: MAVProxy hands it every packet.
"""

from __future__ import annotations

import json
import time
from collections import Counter

from MAVProxy.modules.lib import mp_module

KEPT = ("HEARTBEAT", "SYS_STATUS", "GPS_RAW_INT", "GLOBAL_POSITION_INT", "HOME_POSITION", "AUTOPILOT_VERSION")


class ProbeModule(mp_module.MPModule):
    def __init__(self, mpstate) -> None:
        super().__init__(mpstate, "mavproxy_probe", "per-system report for tests", multi_vehicle=True)
        self.started = time.monotonic()
        self.counts: dict[str, Counter] = {}
        self.last: dict[str, dict] = {}
        self.add_command("probe", self.cmd_probe, "print what each system and component sent, as JSON")

    def mavlink_packet(self, m) -> None:
        kind = m.get_type()
        if kind == "BAD_DATA":
            return
        source = f"{m.get_srcSystem()}:{m.get_srcComponent()}"
        self.counts.setdefault(source, Counter())[kind] += 1
        if kind in KEPT:
            fields = m.to_dict()
            fields.pop("mavpackettype", None)
            self.last.setdefault(source, {})[kind] = fields

    def cmd_probe(self, args) -> None:
        report = {
            "elapsed_s": round(time.monotonic() - self.started, 3),
            "counts": {source: dict(counts) for source, counts in self.counts.items()},
            "last": self.last,
        }
        print("PROBE " + json.dumps(report, default=list))


def init(mpstate):
    """MAVProxy's module entry point."""
    return ProbeModule(mpstate)
