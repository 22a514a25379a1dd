"""ArduPilot's SITL motorboat rolling in its simulated waves: the vessel's levelled IMU reads the hull's own
acceleration, not gravity, and its GPS fixes moved from the antenna to the IMU are where the hull is.

The motorboat model (libraries/SITL/SIM_Sailboat.cpp `update_wave`, SIM_WAVE_*) rolls and pitches the hull while
armed, and its accelerometer sees dcm^T (a - g), so the planar x, y of SCALED_IMU carry g sin(tilt). With no
throttle and no wind the hull's horizontal acceleration is about zero (checked on its track). The vessel's
decoder reads ATTITUDE (roll, pitch, body rates) and SCALED_IMU (all three axes), and
`bob_autonomy.estimation.tilt.TiltTracker` levels each IMU reading with the attitude carried to its time. A wrong
sign of roll or pitch, or of an axis, would leave about twice the tilt's gravity in the levelled reading.

Skipped unless ARDUPILOT_SITL names a built `ardurover` (docs/ardupilot.md).
"""

from __future__ import annotations

import socket
import time

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from sitl_harness import BINARY, NEEDS_SITL, RoverSitl, local_xy

from bob_autonomy.estimation.antenna import antenna_offsets
from bob_autonomy.estimation.tilt import TiltTracker
from firmware_bridge.autopilot_requests import set_message_interval
from firmware_bridge.commands import Encoder, command_long_arm
from firmware_bridge.decoder import TelemetryDecoder
from firmware_bridge.readings import CompassReading, GpsFix, ImuReading

pytestmark = NEEDS_SITL


def test_a_motorboat_rolling_in_ardupilots_waves_reads_no_acceleration_once_levelled(tmp_path) -> None:
    """Waves every 5 s from 45 deg off the bow (roll and pitch both), no wind, armed at zero throttle; 20 s of
    SCALED_IMU at 25 Hz and ATTITUDE at 20 Hz, as the vessel asks for them. In a run of 2026-11-28: tilt up to
    4.7 deg; planar accelerometer 0.34 and 0.54 m/s^2 RMS, levelled 0.018 and 0.019 (the IMU's own noise)."""
    params = {"SIM_WAVE_ENABLE": 1, "SIM_WAVE_SPEED": 2.0, "SIM_WAVE_DIR": 45, "SIM_WIND_SPD": 0}
    with RoverSitl(BINARY, "motorboat", tmp_path, params=params) as sitl:
        sitl.wait_initialised()
        with socket.create_connection(("127.0.0.1", sitl.serial0), timeout=5.0) as link:
            encoder = Encoder()
            link.sendall(set_message_interval(encoder, 1, mavlink.MAVLINK_MSG_ID_ATTITUDE, 20.0))
            link.sendall(set_message_interval(encoder, 1, mavlink.MAVLINK_MSG_ID_SCALED_IMU, 25.0))
            link.sendall(command_long_arm(True, force=True, encoder=encoder))  # the waves run only while armed
            decoder = TelemetryDecoder(source_system=1, source_component=1)  # as a vessel
            tracker = TiltTracker(1)
            tilt, planar, levelled = [], [], []
            start = time.monotonic()
            while time.monotonic() - start < 28.0:
                for reading in decoder.feed(link.recv(65536)):
                    settled = time.monotonic() - start > 8.0  # armed, and the waves under way
                    if isinstance(reading, CompassReading):
                        tracker.note(reading)
                        if settled:
                            tilt.append((reading.roll_rad[0], reading.pitch_rad[0]))
                    elif isinstance(reading, ImuReading) and settled:
                        planar.append(reading.accel_body_mps2[0])
                        levelled.append(tracker.level(reading).accel_body_mps2[0])
        track = [(t, local_xy(lat, lon)) for t, lat, lon, _ in sitl.seen.positions if t - start > 8.0]
    assert len(planar) > 400 and len(tilt) > 300, (len(planar), len(tilt))
    assert tracker.unlevelled <= 2  # at most the first readings, before an ATTITUDE
    most_tilt = np.degrees(np.max(np.abs(tilt), axis=0))
    assert np.all(most_tilt > 2.0), most_tilt  # both roll and pitch
    # The hull's true acceleration, from the autopilot's own positions: a parabola's over the window. (It may
    # coast slowly, as here at 0.1-0.25 m/s; its hull drag slows it by about 0.01 m/s^2.)
    times, xy = np.array([t for t, _ in track]), np.array([p for _, p in track])
    true_accel = [2.0 * np.polyfit(times - times[0], xy[:, axis], 2)[0] for axis in (0, 1)]
    assert np.all(np.abs(true_accel) < 0.03), true_accel
    planar_rms = np.sqrt(np.mean(np.square(planar), axis=0))
    levelled_rms = np.sqrt(np.mean(np.square(levelled), axis=0))
    print(f"tilt up to {most_tilt} deg; planar RMS {planar_rms} m/s^2, levelled {levelled_rms}")
    assert np.all(planar_rms > 0.2), planar_rms
    assert np.all(levelled_rms < 0.05) and np.all(levelled_rms < planar_rms / 8), (levelled_rms, planar_rms)


def test_fixes_from_an_antenna_up_a_mast_moved_to_the_imu_are_where_ardupilots_simulator_has_the_hull(
    tmp_path,
) -> None:
    """The simulated GPS's antenna 1.5 m up and 0.5 m forward of the IMU (SIM_GPS1_POS_X/Z: libraries/SITL/SIM_GPS.cpp
    puts the fix at p + R r and adds R (w x r) to its velocity), the boat rolling in waves. Truth: SIMSTATE, the
    simulator's own position of the hull. Each fix moved by `antenna_offsets` with the attitude at the fix's time
    (ATTITUDE through `TiltTracker`). In a run of 2026-11-28 the fixes sat 0.53 m from the hull (the forward
    offset) and swung 0.05-0.08 m about that; moved, 0.02-0.03 m off, 0.015-0.03 m of swing left."""
    arm = np.array([[0.5, 0.0, -1.5]])
    params = {"SIM_WAVE_ENABLE": 1, "SIM_WAVE_SPEED": 2.0, "SIM_WAVE_DIR": 45, "SIM_WIND_SPD": 0}
    params |= {"SIM_GPS1_POS_X": arm[0, 0], "SIM_GPS1_POS_Z": arm[0, 2]}
    with RoverSitl(BINARY, "motorboat", tmp_path, params=params) as sitl:
        sitl.wait_initialised()
        with socket.create_connection(("127.0.0.1", sitl.serial0), timeout=5.0) as link:
            encoder = Encoder()
            for message, hz in ((mavlink.MAVLINK_MSG_ID_ATTITUDE, 20.0), (mavlink.MAVLINK_MSG_ID_GPS_RAW_INT, 10.0),
                                (mavlink.MAVLINK_MSG_ID_SIMSTATE, 10.0)):  # fmt: skip
                link.sendall(set_message_interval(encoder, 1, message, hz))
            link.sendall(command_long_arm(True, force=True, encoder=encoder))
            # SIM_GPS1_LAG_MS 100: each fix is 0.1 s older than ArduPilot's stamp, as GPS1_DELAY_MS would say
            decoder = TelemetryDecoder(source_system=1, source_component=1, fused_position=False, gps_lag_s=0.1)
            truth = []
            decoder.message_hook = lambda msg: (
                truth.append((time.monotonic(), *local_xy(msg.lat * 1e-7, msg.lng * 1e-7)))
                if msg.get_type() == "SIMSTATE" else None
            )  # fmt: skip
            tracker = TiltTracker(1)
            fixes = []  # (time of the fix, raw east, north, moved east, north)
            start = time.monotonic()
            while time.monotonic() - start < 28.0:
                for reading in decoder.feed(link.recv(65536)):
                    if isinstance(reading, CompassReading):
                        tracker.note(reading)
                    elif isinstance(reading, GpsFix) and time.monotonic() - start > 8.0:
                        attitude, known = tracker.attitude_at(reading.agents, reading.t_s)
                        if known[0]:
                            moved, _ = antenna_offsets(attitude, tracker.body_rates[reading.agents], arm)
                            xy = np.array(local_xy(reading.lat_deg[0], reading.lon_deg[0]))
                            fixes.append((float(reading.t_s[0]), *xy, *(xy - moved[0])))
    fixes, truth = np.array(fixes), np.array(truth)
    assert len(fixes) > 80 and len(truth) > 200, (len(fixes), len(truth))
    hull = np.column_stack([np.interp(fixes[:, 0], truth[:, 0], truth[:, axis]) for axis in (1, 2)])
    raw, moved = fixes[:, 1:3] - hull, fixes[:, 3:5] - hull
    print(f"raw fix - hull: mean {raw.mean(axis=0)}, std {raw.std(axis=0)}; moved: {moved.mean(axis=0)}, "
          f"{moved.std(axis=0)} m")  # fmt: skip
    assert np.hypot(*raw.mean(axis=0)) > 0.4  # the antenna's forward offset: the fixes are not at the hull
    assert np.hypot(*moved.mean(axis=0)) < 0.1
    assert np.all(moved.std(axis=0) < 0.05) and moved.std(axis=0).sum() < raw.std(axis=0).sum() / 2
