"""bob-autonomy against ArduPilot's own Rover SITL behind a link that answers late: every byte from the autopilot
held 2 s, every byte to it 0.2 s (a slow telemetry radio, or an autopilot and companion computer sharing an
overloaded host, as in a 45-vessel process fleet on 2 cores, where acceptances came up to 3.6 s late).

Skipped unless ARDUPILOT_SITL names a built `ardurover` (docs/ardupilot.md). Judged by what the autopilot itself
reports on its second serial port, which no delay touches.
"""

from __future__ import annotations

import logging

import numpy as np
from sitl_harness import BINARY, NEEDS_SITL, LaggingTcpProxy, RoverSitl, drive, vessel_config

pytestmark = NEEDS_SITL
FROM_AUTOPILOT_S, TO_AUTOPILOT_S = 2.0, 0.2


def test_the_vessel_arms_and_drives_real_ardupilot_over_a_link_that_answers_two_seconds_late(tmp_path, caplog) -> None:
    caplog.set_level(logging.INFO)
    with (
        RoverSitl(BINARY, "omni", tmp_path) as sitl,
        LaggingTcpProxy(sitl.serial0, to_target_s=TO_AUTOPILOT_S, from_target_s=FROM_AUTOPILOT_S) as proxy,
    ):
        sitl.wait_initialised()
        config = vessel_config(sitl, (20.0, 0.0), vehicle=f"tcp:127.0.0.1:{proxy.port}")
        track, _errors, vessel = drive(sitl, config, 45.0)
    # The autopilot itself says it was armed, and took the vessel's overrides: its throttle or lateral input
    # (channels 3 and 4 of the omni frame) left neutral.
    assert any(armed for _t, _mode, armed in sitl.seen.modes)
    assert vessel.stats.commands > 0
    assert any(abs(rc[2] - 1500) > 50 or abs(rc[3] - 1500) > 50 for _t, rc in sitl.seen.rc)
    texts = [r.getMessage() for r in caplog.records]
    assert not any("would not arm" in t for t in texts)
    # The autopilot's echo of our overrides arrives 2.2 s after we sent them: still an autopilot that takes them
    # (bob_autonomy.onboard.autopilot OVERRIDE_ECHO_LAG_S; a 1.5 s look-back said otherwise, every few seconds).
    assert not any("does not apply our RC overrides" in t for t in texts)
    east = [float(xy[0]) for _t, xy, _h in track]
    assert east and max(east) > 5.0, f"the vessel hardly moved towards its goal 20 m east: {east[-5:]}"
    assert np.isfinite(east).all()
