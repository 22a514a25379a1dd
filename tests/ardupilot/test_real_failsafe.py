"""When the autonomy process dies, ArduPilot's own failsafes catch the boat, as our simulated autopilot predicts.

The simulated autopilot's failsafes were written from ArduPilot's source (sitl/vehicles/mavlink_vehicle.py
`_failsafes`, tests/test_autopilot_arming.py) and only ever tested against themselves. Here the real Rover SITL,
with `FS_GCS_ENABLE` 1, drives under a real `bob-autonomy run` that is then killed (SIGKILL: no clean stop, as a
crashed companion computer). What ArduPilot reports on its own second port is compared with what the simulated
autopilot does, given ArduPilot's values of the parameters involved, when its ground station and overrides stop
at the same moment:

- the RC overrides lapse after RC_OVERRIDE_TIME, and the inputs return to the receiver's neutral;
- after FS_GCS_TIMEOUT of silence from MAV_GCS_SYSID, plus FS_TIMEOUT, the failsafe takes the boat to HOLD
  (FS_ACTION 2), and the same failsafe text is said (the simulated autopilot claims Rover names it "Radio
  Failsafe" when the radio check runs first in the loop, although the ground station is what was lost).

Skipped unless ARDUPILOT_SITL names a built `ardurover` (docs/ardupilot.md).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

from autopilot_helpers import Gcs, run, texts
from sitl_harness import BINARY, HOME, NEEDS_SITL, RoverSitl

from sitl.vehicles.mavlink_vehicle import SimulatedVehicle

pytestmark = NEEDS_SITL
HOLD = 4
FAILSAFE_PARAMS = ("RC_OVERRIDE_TIME", "FS_GCS_TIMEOUT", "FS_TIMEOUT", "FS_THR_ENABLE", "FS_ACTION", "FS_OPTIONS")
KILL_S = 10.0  # when the simulated ground station stops


def _read_params(sitl: RoverSitl, names: tuple[str, ...]) -> dict[str, float]:
    """ArduPilot's values, asked on the observer's port (PARAM_REQUEST_READ; the harness keeps each PARAM_VALUE)."""
    deadline = time.monotonic() + 10.0
    while not all(name in sitl.seen.params for name in names):
        assert time.monotonic() < deadline, f"ArduPilot did not give {names}: {sitl.seen.params}"
        for name in names:
            if name not in sitl.seen.params:
                sitl.observer.mav.param_request_read_send(1, 1, name.encode(), -1)
        time.sleep(0.5)
    return {name: sitl.seen.params[name] for name in names}


def _simulated(params: dict[str, float]) -> tuple[float, float, list[str]]:
    """The simulated autopilot under a ground station that sends a HEARTBEAT every second and an RC override every
    0.1 s until KILL_S (the vessel's rates), then nothing: (s from KILL_S until the throttle input is back at its
    neutral, s from KILL_S until HOLD, the texts said after KILL_S)."""
    vehicle = SimulatedVehicle(1, "buoy", 45.0, armed=True, params={**params, "FS_GCS_ENABLE": 1})
    gcs = Gcs()

    def vessel(t: float) -> bytes:
        data = gcs.override({3: 1700})
        return data + gcs.heartbeat() if abs(t - round(t)) < 1e-9 else data

    run(vehicle, 0.0, KILL_S, dt=0.1, every_step=vessel)
    neutral_at = hold_at = None
    said: list[str] = []
    t = KILL_S
    while t < KILL_S + 20.0 and hold_at is None:
        said += texts(run(vehicle, t, t + 0.05, dt=0.05))
        t += 0.05
        if neutral_at is None and vehicle.rc.radio_in[2] == 1500:
            neutral_at = t - KILL_S
        if vehicle.mode == HOLD:
            hold_at = t - KILL_S
    assert neutral_at is not None and hold_at is not None, (vehicle.rc.radio_in, vehicle.mode, said)
    return neutral_at, hold_at, said


def test_a_killed_vessel_is_caught_by_ardupilots_failsafes_as_the_simulated_autopilot_predicts(tmp_path) -> None:
    with RoverSitl(BINARY, "omni", tmp_path, params={"FS_GCS_ENABLE": 1}) as sitl:
        sitl.wait_initialised()
        params = _read_params(sitl, FAILSAFE_PARAMS)
        command = [
            sys.executable, "-m", "bob_autonomy.cli", "run", "--vehicle", f"tcp:127.0.0.1:{sitl.serial0}",
            "--system-id", "1", f"--origin={HOME[0]},{HOME[1]}", "--behavior", "bob-rule", "--param", "H=1",
            "--param", "goal=[200,0]", "--param", "max_speed=1.5", "--param", "speed_scale=1",
            "--log-file", str(tmp_path / "vessel.log"),
        ]  # fmt: skip
        process = subprocess.Popen(command, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        try:
            deadline = time.monotonic() + 90
            while not (sitl.seen.rc and any(abs(c - 1500) > 100 for c in sitl.seen.rc[-1][1][2:4])):
                assert time.monotonic() < deadline, "the vessel never drove"
                time.sleep(0.2)
            time.sleep(3.0)
            killed_at = time.monotonic()
            process.kill()  # SIGKILL: the companion computer gone at once
            process.wait(timeout=10)
            deadline = killed_at + 20.0
            while not any(t > killed_at and mode == HOLD for t, mode, _ in sitl.seen.modes):
                assert time.monotonic() < deadline, f"ArduPilot never went to HOLD: {sitl.seen.texts[-10:]}"
                time.sleep(0.1)
            time.sleep(1.0)  # the texts that follow
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
    real_hold = min(t for t, mode, _ in sitl.seen.modes if t > killed_at and mode == HOLD) - killed_at
    real_neutral = min(t for t, ch in sitl.seen.rc if t > killed_at and abs(ch[2] - 1500) <= 30) - killed_at
    real_texts = [text for text in sitl.seen.texts if "ailsafe" in text]
    sim_neutral, sim_hold, sim_said = _simulated(params)
    sim_texts = [text for text in sim_said if "ailsafe" in text]
    print(f"\nArduPilot {params}: throttle input neutral {real_neutral:.2f} s and HOLD {real_hold:.2f} s after the"
          f" kill, said {real_texts}; simulated: {sim_neutral:.2f} s, {sim_hold:.2f} s, said {sim_texts}")  # fmt: skip
    # The vessel's last override and HEARTBEAT came up to 0.1 s and 1 s before the kill; the observer hears
    # RC_CHANNELS at 10 Hz and HEARTBEAT at 1 Hz.
    assert abs(real_neutral - sim_neutral) <= 0.5
    assert sim_hold - 1.2 <= real_hold <= sim_hold + 1.2
    assert real_texts and real_texts[0] == sim_texts[0]
