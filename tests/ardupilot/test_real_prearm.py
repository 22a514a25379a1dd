"""An autopilot that will not arm: the vessel reports ArduPilot's own reason, and the simulated autopilot gives the
same one.

The simulated autopilot's pre-arm checks (sitl/vehicles/autopilot_safety.py `arming_failures`) were written from
ArduPilot's source and tested against themselves. Here the real Rover SITL is given a throttle channel whose
RC3_MIN (1400 us) is above what ArduPilot's RC checks allow (RC_Channel.h RC_CALIB_MIN_LIMIT_PWM, 1300 us): it
refuses to arm and says why; the vessel must give up with that reason in its error, as the mission asks of "an
autopilot that refuses to arm", and the simulated autopilot must say the same thing for the same parameter.

Skipped unless ARDUPILOT_SITL names a built `ardurover` (docs/ardupilot.md).
"""

from __future__ import annotations

import pytest
from sitl_harness import BINARY, NEEDS_SITL, RoverSitl, vessel_config

from bob_autonomy.onboard.autopilot_start import StartOptions
from bob_autonomy.onboard.vessel import VehicleError, Vessel
from sitl.vehicles import autopilot_safety
from sitl.vehicles.mavlink_vehicle import SimulatedVehicle

pytestmark = NEEDS_SITL
BAD_CALIBRATION = {"RC3_MIN": 1400}


def test_a_pre_arm_failure_is_reported_in_ardupilots_words_which_the_simulated_autopilot_shares(tmp_path) -> None:
    with RoverSitl(BINARY, "omni", tmp_path, params=BAD_CALIBRATION) as sitl:
        sitl.wait_initialised()
        config = vessel_config(sitl, arm_timeout_s=40.0, autopilot=StartOptions(ready_timeout_s=40.0))
        with pytest.raises(VehicleError) as raised:
            Vessel(config).run(duration_s=120.0)
        said = [text for text in sitl.seen.texts if text.startswith(("PreArm", "Arm"))]
        armed = any(armed for _t, _mode, armed in sitl.seen.modes)
    simulated = autopilot_safety.arming_failures(SimulatedVehicle(1, "buoy", 45.0, params=BAD_CALIBRATION))
    print(f"\nArduPilot said {sorted(set(said))}; the vessel: {raised.value}; simulated: {simulated}")
    assert not armed
    assert simulated == ["Throttle radio min too high"]
    assert f"PreArm: {simulated[0]}" in said
    assert simulated[0] in str(raised.value) and "not ready" in str(raised.value)
