"""RC input of a simulated vehicle (sitl.vehicles.mavlink_vehicle): RC_CHANNELS_OVERRIDE and MANUAL_CONTROL from the
ground station, the RC map and calibration read from the parameters, and the motor demands they make
(Rover/radio.cpp, Rover/mode.cpp get_pilot_input, GCS_Common.cpp handle_rc_channels_override)."""

from __future__ import annotations

import numpy as np

from firmware_bridge.commands import ROVER_MODES
from sitl.vehicles.autopilot_rc import (
    PilotOutput,
    input_expo,
    norm_input_dz,
    pilot_demand,
    scale_angle,
    skid_outputs,
)
from sitl.vehicles.vehicle_defs import (
    BUOY,
    DRIVING_MODES,
    MOTORBOAT,
)

# The angle of each role's channel (Rover/radio.cpp set_control_channels: steering SERVO_MAX, throttle and lateral
# 100): ArduPilot keeps what it reads as an integer in these units (autopilot_rc.scale_angle).
ANGLE_FULL_SCALE = {"steer": 4500, "throttle": 100, "lateral": 100}
# What an override channel may carry: a PWM of 800-2200 us, or 0 / UINT16_MAX-1 / UINT16_MAX (release, ignore).
_VALID_OVERRIDE = frozenset(range(800, 2201)) | {0, 65534, 65535}


class RcInputHandling:
    """RC input handling, mixed into SimulatedVehicle (which holds the state it uses)."""

    def _override(self, source_system: int, raw: list[int], t_s: float) -> None:
        """An RC_CHANNELS_OVERRIDE addressed to us from `source_system`, its 18 channel values `raw`."""
        if source_system != self.gcs_system_id:
            self.counters.refused += 1  # GCS_Common.cpp handle_rc_channels_override: only from our GCS
            return
        if not _VALID_OVERRIDE.issuperset(raw):
            self.counters.rejected += 1  # stricter than ArduPilot, which clamps any value into RCx_MIN..MAX
            return
        self.rc.apply_override(raw, t_s)
        self._gcs_seen_s = t_s
        self._after_override(t_s)

    def _manual_control(self, msg, t_s: float) -> None:
        """Rover's MANUAL_CONTROL: y -> steering, z -> throttle channel, over RCx_MIN..MAX (GCS_MAVLink_Rover.cpp
        handle_manual_control_axes, GCS_Common.cpp manual_override); INT16_MAX releases the channel."""
        if msg.get_srcSystem() != self.gcs_system_id:
            self.counters.refused += 1
            return
        if any(not (-1000 <= int(a) <= 1000 or int(a) == 32767) for a in (msg.y, msg.z)):
            self.counters.rejected += 1  # ArduPilot would wrap such a value into a full deflection
            return
        for axis, param in ((msg.y, "RCMAP_ROLL"), (msg.z, "RCMAP_THROTTLE")):
            ch = self.params.get_int(param)
            if not 1 <= ch <= 8:
                continue
            value = 0
            if int(axis) != 32767:
                low, high = self.params.get_int(f"RC{ch}_MIN"), self.params.get_int(f"RC{ch}_MAX")
                value = int(low + (high - low) * (int(axis) + 1000) / 2000)
            raw = [65535] * 8 + [0] * 10
            raw[ch - 1] = value
            self.rc.apply_override(raw, t_s)
        self._gcs_seen_s = t_s
        self._after_override(t_s)

    def _after_override(self, t_s: float) -> None:
        self.rc.update(t_s, self.failsafe_s, self._trims())
        demand = self._demand(PilotOutput(*self._read_pilot()))
        self._command = demand
        self._last_command_s = t_s
        if self.armed and self.mode in DRIVING_MODES:
            self.counters.commands += 1
            self._driving_override = True
        else:
            self.counters.idle += 1

    def _rc_setup(self) -> tuple[list[int], dict[str, tuple | None], dict[tuple[str, bool, int], float]]:
        """RC1..8_TRIM, per role (channel, MIN, TRIM, MAX, DZ, REVERSED) or None for an invalid map, and the
        values read so far ((role, paddle, PWM) -> `_channel`); read again from the parameters only when one has
        changed."""
        if self._rc_cache_version != self.params.version or self._rc_cache is None:
            p = self.params
            trims = [p.get_int(f"RC{ch}_TRIM") for ch in range(1, 9)]
            roles: dict[str, tuple | None] = {}
            for role, name in (("steer", "RCMAP_ROLL"), ("throttle", "RCMAP_THROTTLE"), ("lateral", "RCMAP_YAW")):
                ch = p.get_int(name)
                roles[role] = None if not 1 <= ch <= 8 else (
                    ch, p.get_int(f"RC{ch}_MIN"), p.get_int(f"RC{ch}_TRIM"), p.get_int(f"RC{ch}_MAX"),
                    p.get_int(f"RC{ch}_DZ"), bool(p.get_int(f"RC{ch}_REVERSED")),
                )  # fmt: skip
            self._rc_cache, self._rc_cache_version = (trims, roles, {}), p.version
        return self._rc_cache

    def _trims(self) -> list[int]:
        return self._rc_setup()[0]

    def _channel(self, role: str, paddle: bool = False) -> float:
        """A role's RC input as Rover reads it (`scale_angle`, or `norm_input_dz` for a paddle), each PWM worked out
        once per parameter version: a pure function of the PWM and the calibration (at most 1,400 override PWMs)."""
        _, roles, seen = self._rc_setup()
        setup = roles[role]
        if setup is None:
            return 0.0  # RC_Channels: a dummy channel for an invalid map
        pwm = self.rc.radio_in[setup[0] - 1]
        if pwm == 0:
            return 0.0
        key = (role, paddle, pwm)
        value = seen.get(key)
        if value is None:
            calib = setup[1:]
            value = norm_input_dz(pwm, *calib) if paddle else scale_angle(pwm, *calib, ANGLE_FULL_SCALE[role])
            seen[key] = value
        return value

    def _read_pilot(self) -> tuple[float, float, float]:
        """(steering, throttle, lateral) from RC inputs 1-8 (the RCMAP roles are among them) and the parameters;
        kept while both stay as they were (asked when an override arrives and when the motors run)."""
        key = (self.params.version, self.mode, *self.rc.radio_in[:8])
        if self._pilot_cache is None or self._pilot_cache[0] != key:
            steer_type = self.params.get_int("PILOT_STEER_TYPE")
            steering, throttle = pilot_demand(self._channel, steer_type, self.skid_steer())
            if self.mode == ROVER_MODES["MANUAL"]:  # Rover/mode_manual.cpp: the steering expo, MANUAL only
                steering = input_expo(steering, float(self.params["MANUAL_STR_EXPO"]))
            lateral = self._channel("lateral") if self.omni() else 0.0
            self._pilot_cache = (key, (steering, throttle, lateral))
        return self._pilot_cache[1]

    def _steering_output(self, out: PilotOutput) -> float:
        """The steering output (SERVOn_FUNCTION 26) for motor demands `out`: a frame that steers with it (neither
        skid-steer nor omni) turns it the other way when backing up (AP_MotorsUGV::output_regular, MANUAL
        without speed scaling)."""
        regular = not self.skid_steer() and not self.omni()
        return -out.steering if regular and out.throttle < 0 else out.steering

    def _demand(self, out: PilotOutput) -> np.ndarray:
        """The actuator vector (N thrust x, y body; m/s wheels left, right; or a motorboat's throttle and ground
        steering outputs, each in [-1, 1], steering > 0 to starboard) for motor demands `out`."""
        if self.kind == MOTORBOAT:
            return np.array([out.throttle, self._steering_output(out)])
        if self.kind == BUOY:
            return np.array([out.throttle * self.max_actuator, -out.lateral * self.max_actuator])
        left, right = skid_outputs(out)
        return np.array([left * self.max_actuator, right * self.max_actuator])
