"""bob-autonomy's motorboat kind against ArduPilot's own SITL motorboat (FRAME_CLASS 2, FRAME_TYPE 0: ground
steering on SERVO1, throttle on SERVO3; libraries/SITL/SIM_Sailboat.cpp class MotorBoat).

Skipped unless ARDUPILOT_SITL names a built `ardurover` (see docs/ardupilot.md). Judged by what the autopilot
itself reports on its second serial port (GLOBAL_POSITION_INT), never by our own logs.

"Held" for a boat that cannot stop in place: over the last 15 s of each leg the boat stays within 10 m of the
goal (it drifts or circles about it: ArduPilot's SITL motorboat turns on a 0.9 m radius at full steering, its
TURN_RADIUS, and its wind is SIM_WIND_SPD 3 m/s from motorboat.parm); reaching: it came within 5 m of the goal.
"""

from __future__ import annotations

import logging

import numpy as np
from sitl_harness import BINARY, HOME, NEEDS_SITL, RoverSitl, drive

from bob_autonomy.core.behavior_config import BehaviorChoice
from bob_autonomy.onboard.vessel import Vessel, VesselConfig

pytestmark = NEEDS_SITL
ORIGIN = (HOME[0], HOME[1])
LEG_S = 75.0
HELD_S, HELD_M, REACHED_M = 15.0, 10.0, 5.0


def _run_leg(sitl: RoverSitl, goal: tuple[float, float]) -> tuple[list, Vessel]:
    params = {"H": 1, "goal": list(goal), "max_speed": 1.5, "speed_scale": 1.0}
    config = VesselConfig(
        vehicle=f"tcp:127.0.0.1:{sitl.serial0}",
        system_id=1,
        origin=ORIGIN,
        kind="motorboat",
        behavior=BehaviorChoice(behavior="bob-rule", params=params),
        arm_timeout_s=60.0,
    )
    track, _errors, vessel = drive(sitl, config, LEG_S)
    return [(t, xy) for t, xy, _hdg in track], vessel


def test_motorboat_reaches_goals_in_four_directions_and_holds_near_them(tmp_path, caplog) -> None:
    caplog.set_level(logging.WARNING, logger="bob_autonomy.control.motorboat_control")
    corners = [(50.0, 0.0), (50.0, 50.0), (0.0, 50.0), (0.0, 0.0)]  # east, north, west, south legs of 50 m
    with RoverSitl(BINARY, "motorboat", tmp_path) as sitl:
        sitl.wait_initialised()
        for goal in corners:
            track, vessel = _run_leg(sitl, goal)
            distance = [float(np.hypot(*(xy - goal))) for _t, xy in track]
            assert distance and min(distance) < REACHED_M, f"goal {goal}: closest {min(distance):.1f} m"
            held = [d for (t, _xy), d in zip(track, distance, strict=True) if t > track[-1][0] - HELD_S]
            assert held and max(held) < HELD_M, f"goal {goal}: last {HELD_S:g} s at {np.round(held, 1)}"
            fallbacks = [r.getMessage() for r in caplog.records if "fallback" in r.getMessage()]
            assert vessel.pipeline.mpc_fallbacks == 0, f"goal {goal}: MPC fallbacks {fallbacks}"
            # It drove as a motorboat: steering and throttle only, the lateral channel (4) left at its trim.
            assert all(abs(ch[3] - 1500) <= 30 for _t, ch in sitl.seen.rc[-20:])
