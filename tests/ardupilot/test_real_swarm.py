"""A swarm on ArduPilot's own autopilots: four Rover SITL omni rovers (the buoy's stand-in), each driven by its own
`bob-autonomy run` as on a vessel's computer, the four talking over a UDP broadcast mesh (`udpbcast`, as on an IP
radio; no relay of ours between them). They start at the corners of a 60 m square and aggregate by eq. (5) with
H = 0: each alone would stay where it is, so only the mesh can bring them together.

Skipped unless ARDUPILOT_SITL names a built `ardurover` (docs/ardupilot.md). Judged by what each autopilot itself
reports on its second serial port (GLOBAL_POSITION_INT), never by our own logs.

Eq. (5) with H = 0 balances four agents on a square of side s where sqrt(2) (1 - p0^2/s^2) + 1 - p0^2/(2 s^2) = 0,
i.e. s^2 = p0^2 (sqrt(2) + 1/2) / (sqrt(2) + 1), s = 0.89 p0 (diagonal 1.26 p0).
"""

from __future__ import annotations

import contextlib
import itertools
import math
import os
import subprocess
import sys
import time

import numpy as np
from sitl_harness import BINARY, HOME, NEEDS_SITL, RoverSitl, free_udp_port, home_at, local_xy

pytestmark = NEEDS_SITL

CORNERS = [(-30.0, -30.0), (30.0, -30.0), (30.0, 30.0), (-30.0, 30.0)]  # east, north m from HOME
P0_M = 15.0
RUN_S = 150.0  # each autonomy's run after its start-up, s
SETTLED_S = 20.0  # judged over the last this many seconds of the run
SIDE_M = P0_M / math.sqrt((math.sqrt(2) + 1) / (math.sqrt(2) + 0.5))  # eq. (5)'s square (module docstring)


def _autonomy(sitl: RoverSitl, mesh: str, log: str) -> subprocess.Popen:
    command = [
        sys.executable, "-m", "bob_autonomy.cli", "run",
        "--vehicle", f"tcp:127.0.0.1:{sitl.serial0}", "--system-id", str(sitl.system_id),
        f"--origin={HOME[0]},{HOME[1]}", "--mesh", mesh, "--broadcast-period", "0.5", "--neighbor-expiry", "3",
        "--behavior", "bob-rule", "--param", "H=0", "--param", f"p0={P0_M}", "--param", "max_speed=1.5",
        "--param", "speed_scale=1", "--arm-timeout", "60", "--duration", str(RUN_S), "--log-file", log,
    ]  # fmt: skip
    return subprocess.Popen(command, env={**os.environ, "PYTHONUNBUFFERED": "1"})


def _pairwise(points: np.ndarray) -> list[float]:
    return [float(np.hypot(*(points[i] - points[j]))) for i, j in itertools.combinations(range(len(points)), 2)]


def test_four_ardupilot_buoys_aggregate_over_a_broadcast_mesh(tmp_path) -> None:
    mesh = f"udpbcast:127.255.255.255:{free_udp_port()}"
    with contextlib.ExitStack() as stack:
        sitls = []
        for k, corner in enumerate(CORNERS):
            workdir = tmp_path / f"vessel{k + 1}"
            workdir.mkdir()
            params = {"MAV_SYSID": k + 1}  # the vessel's agent id on the mesh is its system id - 1
            sitls.append(stack.enter_context(RoverSitl(BINARY, "omni", workdir, params=params, home=home_at(*corner))))
        for sitl in sitls:
            sitl.wait_initialised()
        deadline = time.monotonic() + 60.0  # until each has a position (0, 0 before its GPS has a fix)
        while time.monotonic() < deadline:
            starts = np.array([local_xy(*sitl.seen.positions[-1][1:3]) for sitl in sitls])
            if np.allclose(starts, CORNERS, atol=3.0):
                break
            time.sleep(0.5)
        assert np.allclose(starts, CORNERS, atol=3.0), f"the rovers start at {np.round(starts, 1)}"
        started = time.monotonic()
        processes = [_autonomy(s, mesh, str(tmp_path / f"vessel{s.system_id}.log")) for s in sitls]
        try:
            codes = [p.wait(timeout=RUN_S + 120) for p in processes]
        finally:
            for p in processes:
                if p.poll() is None:
                    p.kill()
        ended = time.monotonic()
        assert codes == [0, 0, 0, 0], f"exit codes {codes}; see {tmp_path}/vessel*.log"

        def where(sitl: RoverSitl, t: float) -> np.ndarray:
            """The autopilot's own position (east, north m) last reported before wall time t."""
            _t, lat, lon, _hdg = [p for p in sitl.seen.positions if p[0] <= t][-1]
            return np.array(local_xy(lat, lon))

        closest = min(  # over the whole run, every half second
            min(_pairwise(np.array([where(s, t) for s in sitls]))) for t in np.arange(started + 1.0, ended, 0.5)
        )
        settled = [np.array([where(s, t) for s in sitls]) for t in np.arange(ended - SETTLED_S, ended, 1.0)]
        spacing = sorted(_pairwise(settled[-1]))
        moved = max(float(np.ptp(np.array([frame[k] for frame in settled]), axis=0).max()) for k in range(4))
        print(
            f"start pairs {np.round(sorted(_pairwise(starts)), 1)} m; end pairs {np.round(spacing, 1)} m "
            f"(eq. 5: sides {SIDE_M:.1f}, diagonals {SIDE_M * math.sqrt(2):.1f}); closest ever {closest:.1f} m; "
            f"largest drift over the last {SETTLED_S:g} s {moved:.1f} m"
        )
        # From 60-85 m apart to the square eq. (5) balances: four sides and two diagonals, each within 10 %.
        expected = [SIDE_M] * 4 + [SIDE_M * math.sqrt(2)] * 2
        assert np.allclose(spacing, expected, rtol=0.1), f"pairs {np.round(spacing, 1)} m, eq. (5) {expected}"
        assert closest > 0.4 * P0_M, f"two rovers came within {closest:.1f} m"
        assert moved < 3.0, f"still moving: a rover drifted {moved:.1f} m over the last {SETTLED_S:g} s"
