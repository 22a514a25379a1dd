"""A 2-vessel `bob-sitl fleet --processes --external-gcs` run for ground stations we did not write (MAVSDK,
MAVProxy): the vessels' ground-station links all point at one UDP port, which the test's ground station binds.

Real time (speed 1): what a ground station sees is then what it would see of boats on the water, rates and delays
included. The fleet is stopped with SIGINT (as Ctrl-C), which makes every autonomy process stop its vehicle and exit,
and the fleet write its outputs (metrics.json, vehicles.tlog) into `out`.
"""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from test_process_fleet import aggregation_scenario, free_ports

from sitl.experiments.scenario import scenario_to_toml, validate_scenario

VESSELS = 2


@dataclass
class InteropFleet:
    """A running fleet: its vehicles' base port, the ground-station port, the scenario's origin (deg), where the
    outputs go, and the fleet process."""

    base_port: int
    gcs_port: int
    origin: tuple[float, float]
    out: Path
    process: subprocess.Popen

    def stop(self) -> str:
        """SIGINT, then wait (60 s at most) for the outputs; returns the fleet's console output."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
        try:
            output, _ = self.process.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            self.process.kill()
            output, _ = self.process.communicate()
        return output or ""


@contextlib.contextmanager
def interop_fleet(tmp: Path, vessels: int = VESSELS) -> Iterator[InteropFleet]:
    """Start `vessels` buoys 100 m apart (the aggregation lattice, p0 = 100 m so they hold their places), each its
    own `bob-autonomy run`, every ground-station link on one free UDP port that the caller binds; stop on exit."""
    base, (mesh, gcs) = free_ports(vessels, extra=2)
    data = aggregation_scenario(count=vessels, duration_s=3600.0).model_dump()
    data["events"] = []  # the ground station under test owns the GCS port (--external-gcs)
    scenario = validate_scenario(data, "interop fleet")
    path = tmp / "interop.toml"
    path.write_text(scenario_to_toml(scenario))
    out = tmp / "run"
    process = subprocess.Popen(
        [sys.executable, "-m", "sitl.cli", "fleet", str(path), "--processes", "--external-gcs",
         "--base-port", str(base), "--mesh-port", str(mesh), "--gcs-port", str(gcs), "--out", str(out), "--quiet"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    fleet = InteropFleet(base, gcs, (scenario.origin.lat_deg, scenario.origin.lon_deg), out, process)
    try:
        yield fleet
    finally:
        fleet.stop()


def wait_for(predicate: Callable[[], object], timeout_s: float, what: str, poll_s: float = 0.005) -> float:
    """Poll `predicate` until it is true; return how long that took (wall s). AssertionError naming `what` after
    `timeout_s`."""
    start = time.monotonic()
    while time.monotonic() - start < timeout_s:
        if predicate():
            return time.monotonic() - start
        time.sleep(poll_s)
    raise AssertionError(f"{what}: not within {timeout_s} s")
