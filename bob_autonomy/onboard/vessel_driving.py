"""How a vessel drives its autopilot (bob_autonomy.onboard.vessel): actuator commands as RC overrides, the heading hold
of omni frames, and watching that the autopilot obeys (its mode, our overrides taken, its telemetry rates)."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.core.arrays import finite_pair
from bob_autonomy.onboard.autopilot import MOTORBOAT
from bob_autonomy.onboard.pipeline import BuoyPipeline
from bob_autonomy.onboard.vehicle_link import BUOY
from firmware_bridge.commands import ROVER_MODES

if TYPE_CHECKING:
    from bob_autonomy.ground.gcs import GcsComponent
    from bob_autonomy.onboard.autopilot import AutopilotSession
    from bob_autonomy.onboard.pipeline import EbotPipeline
    from bob_autonomy.onboard.vessel import VesselConfig, VesselStats

logger = logging.getLogger("bob_autonomy.onboard.vessel")

HEADING_KP = 0.15  # steering per rad of heading error (omni frames)
HEADING_KD = 0.05  # steering per rad/s of yaw rate
HEADING_STEER_MAX = 0.15


class AutopilotDriving:
    """Commands to the autopilot and the watch on it, mixed into Vessel, which provides the attributes here."""

    config: VesselConfig
    autopilot: AutopilotSession
    gcs: GcsComponent
    max_actuator: float
    _hold_heading: bool
    _heading_ref: float | None
    _obeying: bool
    _ignoring_since: float | None
    _ignoring_warned: bool
    _armed_seen: bool | None
    _reboots_seen: int
    _param_changes_seen: int
    _thrust_fraction_asked: float
    pipeline: BuoyPipeline | EbotPipeline
    _restart_due: float | None
    stats: VesselStats
    _send: Callable[[bytes], None]  # VesselLinks
    _say: Callable[[int, str], None]  # VesselLinks

    def _override(self, actuator: np.ndarray, *, hold_heading: bool = False) -> bytes:
        """RC overrides for a buoy's body-frame thrust (x forward, y left; N), a motorboat's (throttle, steering)
        or an eBot's wheel speeds (left, right; m/s), through the autopilot's RC map and calibration
        (`AutopilotSession.override`)."""
        x, y = finite_pair(actuator)
        a = (x / self.max_actuator, y / self.max_actuator)
        if self.config.kind == MOTORBOAT:
            return self.autopilot.override(a[1], a[0], None)
        if self.config.kind == BUOY:
            steering = self._heading_hold_steering() if hold_heading else 0.0
            return self.autopilot.override(steering, a[0], -a[1])
        return self.autopilot.override((a[0] - a[1]) / 2.0, (a[0] + a[1]) / 2.0, None)

    def _heading_hold_steering(self) -> float:
        """Steering (positive = turn right) that holds the hull at the heading it had when driving began: on an
        omni frame the thrust goes in any direction, so nothing else stops the hull from wandering (issue #18).
        PD on the autopilot's own attitude (ATTITUDE: fresh and low-lag): u = -kp e + kd r, e = reference - heading
        (rad, counter-clockwise positive), r the counter-clockwise yaw rate (rad/s), |u| <= HEADING_STEER_MAX."""
        a = self.autopilot
        if not self._hold_heading or not math.isfinite(a.heading_rad) or a.clock() - a.attitude_t > 1.0:
            return 0.0
        if self._heading_ref is None:
            self._heading_ref = a.heading_rad
        error = math.remainder(self._heading_ref - a.heading_rad, 2 * math.pi)
        u = -HEADING_KP * error + HEADING_KD * a.yaw_rate_radps
        return float(np.clip(u, -HEADING_STEER_MAX, HEADING_STEER_MAX))

    def _request_streams(self) -> None:
        for frame in self.autopilot.stream_requests():
            self._send(frame)

    def _watch_restart_and_arming(self) -> None:
        """Say when the autopilot restarted under us (its clock since boot went back) and schedule its start-up
        again (`recover_after_reboot`); say when it is disarmed or armed while we drive, and ask for our streams
        again on a disarm (a restarted autopilot streams its defaults only, and their clock shows the restart)."""
        a, system = self.autopilot, self.config.system_id
        if a.reboots > self._reboots_seen:
            self._reboots_seen = a.reboots
            self.stats.autopilot_reboots += 1
            before, after = a.last_reboot or (math.nan, math.nan)
            recover = self.config.recover_after_reboot
            text = (
                f"autopilot of vehicle {system} restarted (its clock since boot went from {before:.1f} s to "
                f"{after:.1f} s): "
                + ("bringing it into service again" if recover else "neutral until it is armed again (no recovery)")
            )
            self._say(mavlink.MAV_SEVERITY_ALERT, text)
            if recover:
                self._restart_due = time.monotonic()
        armed = a.armed
        if armed is None or armed == self._armed_seen:
            return
        if self._armed_seen is True and self._restart_due is None:
            text = (
                f"vehicle {system} disarmed (a ground station, a failsafe, its RC or a restart?): neutral until it "
                "is armed again"
            )
            self._say(mavlink.MAV_SEVERITY_WARNING, text)
            self._request_streams()
        elif self._armed_seen is False and armed and self._restart_due is None:
            text = f"vehicle {system} armed again: driving"
            self._say(mavlink.MAV_SEVERITY_NOTICE, text)
        self._armed_seen = armed

    def _follow_throttle_ceiling(self) -> str:
        """Plan with the autopilot's MOT_THR_MAX as it now is, a boat's controller and estimator kept
        (`BuoyPipeline.limit_throttle`): at most it, and at most --max-thrust-fraction. Returns what is said."""
        fraction = min(self._thrust_fraction_asked, self.autopilot.profile.throttle_ceiling)
        self.config = replace(self.config, max_thrust_fraction=fraction)
        if isinstance(self.pipeline, BuoyPipeline):  # (a motorboat's is one too; an eBot's is never limited here)
            self.pipeline.limit_throttle(fraction)
        return f"the controller plans with at most {100 * fraction:.0f} % throttle from now on"

    def _watch_autopilot(self, now: float) -> None:
        """Say (log + STATUSTEXT) when the autopilot stops obeying: another mode than ours (a failsafe, a ground
        station), our overrides not taken, or telemetry too slow for the estimator."""
        self._watch_restart_and_arming()
        a = self.autopilot
        for name, before, after in a.param_changes[self._param_changes_seen :]:
            system = self.config.system_id
            changed = f"autopilot parameter {name} of vehicle {system} changed from {before:g} to {after:g}"
            if name == "MOT_THR_MAX" and self.config.kind in (BUOY, MOTORBOAT):
                text = f"{changed} (by a ground station?): {self._follow_throttle_ceiling()}"
            else:
                text = (
                    f"{changed} (by a ground station?): our RC overrides follow it now; the controller keeps the model "
                    "it was built with until the autonomy restarts"
                )
            self._say(mavlink.MAV_SEVERITY_NOTICE, text)
        self._param_changes_seen = len(a.param_changes)
        wanted = ROVER_MODES[self.config.autopilot.mode]
        obeying = a.custom_mode is None or a.custom_mode == wanted
        if obeying != self._obeying:
            if obeying:
                text = f"vehicle {self.config.system_id} back in {self.config.autopilot.mode}: driving again"
            else:
                text = (
                    f"vehicle {self.config.system_id} is in {a.mode_name()}, not {self.config.autopilot.mode}: it "
                    "ignores our commands (a failsafe or a ground station?); commanding neutral until it is back"
                )
            self._say(mavlink.MAV_SEVERITY_WARNING, text)
            self._obeying = obeying
        ignoring = a.ignoring_overrides(now)
        if ignoring and self._ignoring_since is None:
            self._ignoring_since = now
        elif not ignoring:
            if self._ignoring_warned:
                logger.warning("vehicle %d takes our RC overrides again", self.config.system_id)
            self._ignoring_since, self._ignoring_warned = None, False
        if self._ignoring_since is not None and now - self._ignoring_since > 2.0 and not self._ignoring_warned:
            self._ignoring_warned = True
            text = (
                f"vehicle {self.config.system_id} does not apply our RC overrides (its RC_CHANNELS differ): "
                f"check MAV_GCS_SYSID = {a.encoder.mav.srcSystem} and RC_OVERRIDE_TIME > 0"
            )
            self._say(mavlink.MAV_SEVERITY_ERROR, text)
        for text in a.slow_streams(now):
            self._say(mavlink.MAV_SEVERITY_WARNING, text)
        for frame in a.slow_stream_requests(now):
            self._send(frame)
