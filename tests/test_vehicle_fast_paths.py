"""The simulated autopilot's hot paths against their plain forms, on random inputs (seeded): `stream` with the
schedule's `due` and `sent` inlined against the loop over `StreamSchedule.due_among` and `sent`; the RC input read
once per PWM and calibration against `scale_angle` and `norm_input_dz` called every time; `RcInput.apply_override`
against ArduPilot's channel-by-channel rule."""

from __future__ import annotations

import math

import numpy as np
import pytest
from autopilot_helpers import Gcs
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.vehicles import vehicle_streams
from sitl.vehicles.autopilot_rc import OVERRIDE_CHANNELS, UINT16_MAX, RcInput, norm_input_dz, scale_angle
from sitl.vehicles.mavlink_vehicle import SimulatedVehicle
from sitl.vehicles.vehicle_defs import PRODUCED_IN_ORDER
from sitl.vehicles.vehicle_rc_input import ANGLE_FULL_SCALE

m = mavlink
STREAMED = [m.MAVLINK_MSG_ID_ATTITUDE, m.MAVLINK_MSG_ID_GPS_RAW_INT, m.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
            m.MAVLINK_MSG_ID_SCALED_IMU, m.MAVLINK_MSG_ID_RAW_IMU, m.MAVLINK_MSG_ID_RC_CHANNELS,
            m.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, m.MAVLINK_MSG_ID_VFR_HUD, m.MAVLINK_MSG_ID_SYS_STATUS,
            m.MAVLINK_MSG_ID_HEARTBEAT, m.MAVLINK_MSG_ID_SYSTEM_TIME, m.MAVLINK_MSG_ID_WHEEL_DISTANCE,
            m.MAVLINK_MSG_ID_DISTANCE_SENSOR, m.MAVLINK_MSG_ID_HOME_POSITION]  # fmt: skip


def _plain_stream(v: SimulatedVehicle, t_s: float) -> bytes:
    """`SimulatedVehicle.stream` as it was before `due` and `sent` were inlined: the reference."""
    v._tick(t_s)
    out = bytearray(v.outbox)
    v.outbox.clear()
    schedule = v.schedule
    for message_id in schedule.due_among(PRODUCED_IN_ORDER, t_s):
        reading_name = vehicle_streams._READING_OF.get(message_id)
        reading = None
        if reading_name is not None:
            reading = getattr(v, reading_name)
            if reading is None or not reading[0] > v._sent_reading.get(message_id, -math.inf):
                continue
        try:
            data = vehicle_streams._BUILDERS[message_id](v)
        except Exception:
            v.counters.errors += 1
            data = b""
        if data:
            out += data
            schedule.sent(message_id, t_s)
            if reading is not None:
                v._sent_reading[message_id] = reading[0]
    if v._fresh("light", v._light):
        v._sent_reading["light"] = v._light[0]
        out += v.telemetry.light(t_s, *v._light[1:])
    return bytes(out)


def _random_value(rng: np.random.Generator) -> float:
    return float(rng.choice([rng.normal(), math.nan, math.inf])) if rng.random() < 0.05 else float(rng.normal())


@pytest.mark.parametrize("seed", range(4))
def test_stream_is_the_plain_loop_over_due_and_sent(seed: int) -> None:
    """Twins fed the same random readings (missing, late and not finite ones), intervals set, refused, stopped and
    reset, groups asked, overrides and steps of random length: the same bytes, schedules and counters."""
    rng = np.random.default_rng(seed)
    kind = ["buoy", "ebot", "motorboat"][seed % 3]
    twins = [SimulatedVehicle(1, kind, 10.0, armed=True, params={"WENC_TYPE": seed % 2}) for _ in range(2)]
    gcs = [Gcs(), Gcs()]
    t = 0.0
    for _ in range(600):
        t += float(rng.choice([0.0, 0.02, 0.05, 0.1, 0.5, 0.7]))
        event = rng.random()
        requests = []
        if event < 0.05:
            interval = int(rng.choice([0, -1, -5, 10_000, 25_000, 100_000, 333_000, 1_000_000, 70_000_000]))
            requests.append(("long", m.MAV_CMD_SET_MESSAGE_INTERVAL, int(rng.choice(STREAMED)), interval))
        elif event < 0.07:
            stream_id = int(rng.choice([0, 1, 2, 3, 6, 10, 11, 12, 99]))
            requests.append(("stream", stream_id, int(rng.integers(0, 25)), int(rng.integers(0, 3))))
        elif event < 0.3:
            requests.append(("override", int(rng.integers(1100, 1900)), int(rng.integers(1100, 1900))))
        readings = []
        if rng.random() < 0.6:
            velocity = None if rng.random() < 0.1 else (_random_value(rng), _random_value(rng))
            accuracy = (abs(_random_value(rng)), None) if rng.random() < 0.5 else ()
            readings.append(("gps", t - float(rng.choice([0.0, 0.1])), 1.3 + 1e-5 * rng.normal(), 103.9, velocity,
                             *accuracy))  # fmt: skip
        if rng.random() < 0.7:
            readings.append(("compass", t, _random_value(rng)))
        if rng.random() < 0.7:
            readings.append(("imu", t, (_random_value(rng), _random_value(rng)), _random_value(rng)))
        if rng.random() < 0.3:
            readings.append(("wheels", t, (abs(_random_value(rng)), abs(_random_value(rng)))))
        if kind == "ebot" and rng.random() < 0.3:
            readings.append(("ranges", t, tuple(abs(_random_value(rng)) for _ in range(3)), 4.0))
            readings.append(("light", t, _random_value(rng), _random_value(rng)))
        outs = []
        for v, station, stream in zip(twins, gcs, (SimulatedVehicle.stream, _plain_stream), strict=True):
            replies = bytearray()
            for request in requests:
                if request[0] == "long":
                    replies += v.receive(station.long(*request[1:]), t)
                elif request[0] == "stream":
                    frame = station.pack(station.mav.request_data_stream_encode(1, 1, *request[1:]))
                    replies += v.receive(frame, t)
                else:
                    replies += v.receive(station.override({1: request[1], 3: request[2]}), t)
            for reading in readings:
                v.observe(*reading)
            v.actuator(t)
            outs.append((bytes(replies), stream(v, t)))
        assert outs[0] == outs[1]
        a, b = twins
        assert a.schedule.next_due_s == b.schedule.next_due_s and a.schedule.interval_ms == b.schedule.interval_ms
        assert a._sent_reading == b._sent_reading and a.counters == b.counters


@pytest.mark.parametrize("seed", range(3))
def test_rc_input_read_once_per_pwm_is_the_scaling_done_every_time(seed: int) -> None:
    """`_channel` keeps each PWM's value until a parameter changes: random PWMs, calibrations, maps and paddles."""
    rng = np.random.default_rng(seed)
    v = SimulatedVehicle(1, "buoy", 10.0, armed=True)
    for _ in range(3000):
        if rng.random() < 0.02:
            ch = int(rng.integers(1, 9))
            name, value = [(f"RC{ch}_TRIM", rng.integers(1300, 1700)), (f"RC{ch}_DZ", rng.integers(0, 60)),
                           (f"RC{ch}_REVERSED", rng.integers(0, 2)), (f"RC{ch}_MIN", rng.integers(900, 1200)),
                           (f"RC{ch}_MAX", rng.integers(1800, 2100)),
                           ("RCMAP_THROTTLE", rng.integers(1, 9))][int(rng.integers(0, 6))]  # fmt: skip
            v.params.set(name, float(value))
        role = ["steer", "throttle", "lateral"][int(rng.integers(0, 3))]
        paddle = bool(rng.integers(0, 2))
        pwm = int(rng.choice([0, rng.integers(800, 2201)]))
        v.rc.radio_in[:8] = [pwm] * 8
        setup = v._rc_setup()[1][role]
        if setup is None or pwm == 0:
            expected = 0.0
        elif paddle:
            expected = norm_input_dz(pwm, *setup[1:])
        else:
            expected = scale_angle(pwm, *setup[1:], ANGLE_FULL_SCALE[role])
        assert v._channel(role, paddle) == expected


def _apply_channel_by_channel(rc: RcInput, raw: list[int], t_s: float) -> None:
    """GCS_Common.cpp handle_rc_channels_override one channel at a time: the reference for apply_override."""
    for i, value in enumerate(raw[:OVERRIDE_CHANNELS]):
        if i < 8:
            if value == UINT16_MAX:
                continue
        elif value in (0, UINT16_MAX):
            continue
        elif value == UINT16_MAX - 1:
            value = 0
        rc.override[i] = int(value)
        rc.override_t[i] = t_s
    rc.last_valid_s = t_s


@pytest.mark.parametrize("seed", range(3))
def test_apply_override_is_the_channel_by_channel_rule(seed: int) -> None:
    rng = np.random.default_rng(seed)
    fast, plain = RcInput(), RcInput()
    for k in range(500):
        count = int(rng.choice([OVERRIDE_CHANNELS, 8, 20]))
        raw = [int(rng.choice([0, UINT16_MAX, UINT16_MAX - 1, rng.integers(800, 2201)])) for _ in range(count)]
        fast.apply_override(raw, 0.1 * k)
        _apply_channel_by_channel(plain, raw, 0.1 * k)
        assert (fast.override, fast.override_t, fast.last_valid_s) == (plain.override, plain.override_t,
                                                                       plain.last_valid_s)  # fmt: skip


def _plain_failsafes(v: SimulatedVehicle, t_s: float) -> None:
    """`SimulatedVehicle._failsafes` without its early return: every check handed to FailsafeState.update."""
    from sitl.vehicles import autopilot_safety as safety

    f = v._failsafe_params()
    radio = False
    if f.thr_enable:
        ch = f.rcmap_throttle
        pwm = v.rc.radio_in[ch - 1] if 1 <= ch <= 8 else 0
        radio = pwm < f.thr_value or t_s - v.rc.last_valid_s > safety.RADIO_TIMEOUT_S
    gcs = False
    if f.gcs_enable and v._gcs_seen_s is not None:
        gcs = t_s - v._gcs_seen_s >= f.gcs_timeout_s
    may = v.mode not in (safety.HOLD, safety.RTL) or bool(f.options & 1)
    checks = [(safety.FS_RADIO, "Radio", radio)] if f.thr_enable else []
    if f.gcs_enable and v._gcs_seen_s is not None:
        checks.append((safety.FS_GCS, "GCS", gcs))
    for kind, name, on in checks:
        text = v.failsafe.update(kind, name, on, t_s, f.timeout_s, may)
        if text is None:
            continue
        if not text.startswith("!"):
            v._text(m.MAV_SEVERITY_INFO, text)
            continue
        v._text(m.MAV_SEVERITY_WARNING, text[1:])
        v.rc.clear_overrides()
        v.counters.failsafes += 1
        action = safety.failsafe_mode(v.params.get_int("FS_ACTION"), v.has_fix())
        if action == -1:
            if v.armed:
                v._disarm()
        elif action is not None:
            v.set_mode(action) or v.set_mode(safety.HOLD)


@pytest.mark.parametrize("seed", range(4))
def test_failsafe_checks_with_their_early_return_are_the_plain_checks(seed: int) -> None:
    """Twins, one with the plain failsafe checks: overrides that come and stop, GCS heartbeats that stop, the
    failsafe parameters changed, modes set, arming: the same replies, telemetry, modes, failsafes and outputs."""
    rng = np.random.default_rng(50 + seed)
    kind = ["buoy", "ebot", "motorboat"][seed % 3]
    twins = [SimulatedVehicle(1, kind, 10.0, armed=True, rc_receiver=bool(seed % 2)) for _ in range(2)]
    twins[1]._failsafes = lambda t_s, v=twins[1]: _plain_failsafes(v, t_s)
    gcs = [Gcs(), Gcs()]
    t = 0.0
    for _ in range(800):
        t += float(rng.choice([0.0, 0.05, 0.1, 0.5, 1.0, 2.5]))
        event, frames = rng.random(), []
        if event < 0.3:
            frames.append(("override", {1: int(rng.integers(900, 2100)), 3: int(rng.integers(900, 2100))}))
        elif event < 0.4:
            frames.append(("heartbeat",))
        elif event < 0.45:
            name = str(rng.choice(["FS_THR_ENABLE", "FS_GCS_ENABLE", "FS_ACTION", "FS_TIMEOUT", "FS_OPTIONS",
                                   "FS_THR_VALUE", "FS_GCS_TIMEOUT"]))  # fmt: skip
            value = {"FS_THR_ENABLE": rng.integers(0, 3), "FS_GCS_ENABLE": rng.integers(0, 3),
                     "FS_ACTION": rng.integers(0, 7), "FS_TIMEOUT": rng.uniform(0.1, 3.0),
                     "FS_OPTIONS": rng.integers(0, 2), "FS_THR_VALUE": rng.integers(900, 1200),
                     "FS_GCS_TIMEOUT": rng.uniform(1.0, 5.0)}[name]  # fmt: skip
            frames.append(("param", name, float(value)))
        elif event < 0.5:
            frames.append(("mode", int(rng.choice([0, 1, 3, 4, 5, 10, 11, 15]))))
        elif event < 0.53:
            frames.append(("arm", int(rng.integers(0, 2))))
        fix = rng.random() < 0.7
        outs = []
        for v, station in zip(twins, gcs, strict=True):
            replies = bytearray()
            for frame in frames:
                if frame[0] == "override":
                    data = station.override(frame[1])
                elif frame[0] == "heartbeat":
                    data = station.heartbeat()
                elif frame[0] == "param":
                    data = station.pack(station.mav.param_set_encode(1, 1, frame[1].encode(), frame[2], 9))
                elif frame[0] == "mode":
                    data = station.long(m.MAV_CMD_DO_SET_MODE, 1, frame[1])
                else:
                    data = station.long(m.MAV_CMD_COMPONENT_ARM_DISARM, frame[1])
                replies += v.receive(data, t)
            if fix:
                v.observe("gps", t, 1.3, 103.9, (0.1, 0.2))
            outs.append((bytes(replies), v.actuator(t).tolist(), v.stream(t)))
        assert outs[0] == outs[1]
        a, b = twins
        assert (a.mode, a.armed, a.failsafe, a.counters, a.rc.radio_in) == (b.mode, b.armed, b.failsafe, b.counters,
                                                                           b.rc.radio_in)  # fmt: skip


def _plain_observe(readings, t_s: float, vehicles: list[SimulatedVehicle], rows: list[int]) -> None:
    """What `encode_readings` hands each "ardupilot" vehicle, element by element: the reference."""
    if readings.imu is not None:
        r = readings.imu
        tilted = r.accel_z_mps2 is not None and r.gyro_xy_radps is not None
        for i, k in enumerate(r.agents):
            extra = (float(r.accel_z_mps2[i]), tuple(r.gyro_xy_radps[i].tolist())) if tilted else ()
            vehicles[rows[int(k)]].observe("imu", t_s, tuple(r.accel_body_mps2[i].tolist()), float(r.gyro_z_radps[i]),
                                           *extra)  # fmt: skip
    if readings.compass is not None:
        c = readings.compass
        tilted = c.roll_rad is not None and c.pitch_rad is not None and c.body_rates_frd_radps is not None
        for i, k in enumerate(c.agents):
            extra = ()
            if tilted:
                extra = (float(c.roll_rad[i]), float(c.pitch_rad[i]), tuple(c.body_rates_frd_radps[i].tolist()))
            vehicles[rows[int(k)]].observe("compass", t_s, float(c.heading_rad[i]), *extra)
    if readings.gps is not None:
        g = readings.gps

        def reported(values, i):
            return None if values is None or not np.isfinite(values[i]) else float(values[i])

        for i, k in enumerate(g.agents):
            velocity = None if g.velocity_mps is None else tuple(float(v) for v in g.velocity_mps[i])
            accuracy = (reported(g.accuracy_m, i), reported(g.speed_accuracy_mps, i))
            vehicles[rows[int(k)]].observe("gps", t_s, float(g.lat_deg[i]), float(g.lon_deg[i]), velocity, *accuracy)


def _state(v: SimulatedVehicle) -> str:
    """The readings a vehicle holds, with their types (a numpy scalar would show in its repr)."""
    return repr((v._imu, v._compass, v._gps, v._gps_accuracy, type(v._gps[1]) if v._gps else None))


@pytest.mark.parametrize("seed", range(4))
def test_readings_handed_over_array_by_array_are_the_element_by_element_ones(seed: int) -> None:
    from firmware_bridge.readings import CompassReading, GpsFix, ImuReading, SensorReadings
    from sitl.vehicles.vehicle_telemetry import encode_readings

    rng = np.random.default_rng(200 + seed)
    n = 7
    fast = [SimulatedVehicle(k + 1, "buoy", 10.0) for k in range(n)]
    plain = [SimulatedVehicle(k + 1, "buoy", 10.0) for k in range(n)]
    rows = [int(r) for r in rng.permutation(n)]
    for step in range(60):
        t = 0.1 * step

        def column(size, special=0.1):
            values = rng.normal(size=size)
            values[rng.random(size) < special] = rng.choice([math.nan, math.inf, -math.inf])
            return values

        def agents():
            return rng.choice(n, size=int(rng.integers(1, n + 1)), replace=False)

        tilted = bool(rng.integers(2))
        a = agents()
        imu = ImuReading(a, np.full(a.size, t), column((a.size, 2)), column(a.size),
                         column(a.size) if tilted else None, column((a.size, 2)) if tilted else None)  # fmt: skip
        a = agents()
        compass = CompassReading(a, np.full(a.size, t), column(a.size), *(
            (column(a.size), column(a.size), column((a.size, 3))) if tilted else ()))  # fmt: skip
        a = agents()
        gps = GpsFix(a, np.full(a.size, t), 1.3 + 1e-4 * column(a.size, 0), 103.9 + 1e-4 * column(a.size, 0),
                     column((a.size, 2)) if rng.random() < 0.8 else None,
                     np.abs(column(a.size, 0.4)) if rng.random() < 0.7 else None,
                     np.abs(column(a.size, 0.4)) if rng.random() < 0.7 else None)  # fmt: skip
        readings = SensorReadings(gps=gps, compass=compass, imu=imu)
        encode_readings(readings, t, fast, [bytearray() for _ in range(n)], rows)
        _plain_observe(readings, t, plain, rows)
        for x, y in zip(fast, plain, strict=True):
            assert _state(x) == _state(y)
