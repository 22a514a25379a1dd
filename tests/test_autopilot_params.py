"""The simulated autopilot's parameter protocol (item 3; libraries/GCS_MAVLink/GCS_Param.cpp, AP_Param.cpp) with
ArduPilot Rover's names, defaults and ranges, on real frames read back by pymavlink."""

from __future__ import annotations

import math

import pytest
from autopilot_helpers import Gcs, of_type, parse, texts
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.vehicles.autopilot_params import stored_value
from sitl.vehicles.mavlink_vehicle import SimulatedVehicle

m = mavlink
INT8, INT16, INT32, REAL32 = (m.MAV_PARAM_TYPE_INT8, m.MAV_PARAM_TYPE_INT16, m.MAV_PARAM_TYPE_INT32,
                              m.MAV_PARAM_TYPE_REAL32)  # fmt: skip

# name: (buoy default, eBot default, type) as ArduPilot Rover at 90700977 has them (the source file of each is in
# sitl/vehicles/autopilot_params.py), with the frame settings of each simulated kind.
EXPECTED = {
    "FRAME_CLASS": (2, 1, INT8), "FRAME_TYPE": (2, 0, INT8), "INITIAL_MODE": (0, 0, INT8),
    "PILOT_STEER_TYPE": (0, 0, INT8), "CRUISE_SPEED": (2.0, 2.0, REAL32), "CRUISE_THROTTLE": (50, 50, INT8),
    "FS_ACTION": (2, 2, INT8), "FS_TIMEOUT": (1.5, 1.5, REAL32), "FS_THR_ENABLE": (1, 1, INT8),
    "FS_GCS_ENABLE": (0, 0, INT8), "FS_GCS_TIMEOUT": (5.0, 5.0, REAL32), "MAV_SYSID": (7, 7, INT16),
    "MAV_GCS_SYSID": (255, 255, INT16), "ARMING_CHECK": (1, 1, INT32), "RC_OVERRIDE_TIME": (3.0, 3.0, REAL32),
    "RCMAP_ROLL": (1, 1, INT8), "RCMAP_THROTTLE": (3, 3, INT8), "RCMAP_YAW": (4, 4, INT8),
    "WENC_TYPE": (0, 10, INT8), "SERVO1_FUNCTION": (33, 73, INT16), "SERVO3_FUNCTION": (35, 74, INT16),
    "MOT_SLEWRATE": (100, 100, INT16),
    "RC1_MIN": (1100, 1100, INT16), "RC1_TRIM": (1500, 1500, INT16), "RC1_MAX": (1900, 1900, INT16),
    "RC1_DZ": (30, 30, INT16), "RC2_DZ": (0, 0, INT16), "RC3_DZ": (30, 30, INT16), "RC4_DZ": (30, 30, INT16),
    "RC4_REVERSED": (0, 0, INT8),
    **{f"MAV1_{g}": (1, 1, INT16) for g in ("RAW_SENS", "EXT_STAT", "RC_CHAN", "RAW_CTRL", "POSITION", "EXTRA1",
                                           "EXTRA2", "EXTRA3")},
    "MAV1_PARAMS": (10, 10, INT16),
}  # fmt: skip


def _all(v: SimulatedVehicle) -> list:
    gcs = Gcs()
    return of_type(parse(v.receive(gcs.pack(gcs.mav.param_request_list_encode(7, 1)), 0.0)), "PARAM_VALUE")


@pytest.mark.parametrize("kind", ["buoy", "ebot"])
def test_the_list_has_ardupilots_names_defaults_and_types(kind: str) -> None:
    v = SimulatedVehicle(7, kind, 1.0)
    values = _all(v)
    assert len(values) == values[0].param_count == len(v.params)
    assert [p.param_index for p in values] == list(range(len(values)))
    by_name = {p.param_id: p for p in values}
    assert len(by_name) == len(values), "names are unique"
    column = 0 if kind == "buoy" else 1
    for name, expected in EXPECTED.items():
        assert by_name[name].param_value == pytest.approx(expected[column]), name
        assert by_name[name].param_type == expected[2], name
    for old in ("SYSID_MYGCS", "SYSID_THISMAV", "SR0_EXTRA1", "SR1_EXTRA1"):
        assert old not in by_name, f"{old} is not a current ArduPilot name"
    for ch in range(1, 5):
        assert {f"RC{ch}_{s}" for s in ("MIN", "MAX", "TRIM", "DZ", "REVERSED")} <= by_name.keys()
    assert any(t.startswith("ArduRover V4.7.0-dev") for t in texts(parse(v.stream(0.0)))), "the banner"


def test_read_by_name_and_by_index_unknown_gets_nothing() -> None:
    v, gcs = SimulatedVehicle(1, "buoy", 45.0), Gcs()
    (by_name,) = parse(v.receive(gcs.pack(gcs.mav.param_request_read_encode(1, 1, b"FS_TIMEOUT", -1)), 0.0))
    assert (by_name.param_id, by_name.param_value, by_name.param_index) == ("FS_TIMEOUT", 1.5, 65535)
    index = v.params.index["RCMAP_YAW"]
    (by_index,) = parse(v.receive(gcs.pack(gcs.mav.param_request_read_encode(1, 1, b"ignored", index)), 0.0))
    assert (by_index.param_id, by_index.param_value, by_index.param_index) == ("RCMAP_YAW", 4.0, index)
    assert v.receive(gcs.pack(gcs.mav.param_request_read_encode(1, 1, b"SYSID_MYGCS", -1)), 0.0) == b""
    assert v.receive(gcs.pack(gcs.mav.param_request_read_encode(1, 1, b"", 30000)), 0.0) == b""
    assert v.receive(gcs.pack(gcs.mav.param_request_read_encode(2, 1, b"FS_TIMEOUT", -1)), 0.0) == b"", "not for me"


def _set(v: SimulatedVehicle, name: str, value: float, t: float = 0.0) -> list:
    gcs = Gcs()
    reply = v.receive(gcs.pack(gcs.mav.param_set_encode(1, 1, name.encode(), value, REAL32)), t)
    assert reply == b"", "the echo goes to every link, with the telemetry"
    return of_type(parse(v.stream(t)), "PARAM_VALUE")


@pytest.mark.parametrize(
    ("name", "value", "stored"),
    [("FS_TIMEOUT", 2.25, 2.25), ("FS_ACTION", 1.0, 1.0), ("FS_ACTION", 1.995, 2.0), ("CRUISE_THROTTLE", 70.4, 70.0),
     ("RC_OVERRIDE_TIME", -1.0, -1.0), ("RC3_MIN", 999.999, 1000.0), ("FS_OPTIONS", 1.0, 1.0)],
)  # fmt: skip
def test_set_stores_as_ardupilot_and_echoes(name: str, value: float, stored: float) -> None:
    v = SimulatedVehicle(1, "buoy", 45.0)
    (echo,) = _set(v, name, value)
    assert (echo.param_id, echo.param_index) == (name, 65535)
    assert echo.param_value == pytest.approx(stored) and v.params[name] == pytest.approx(stored)


@pytest.mark.parametrize(
    ("name", "value"),
    [("FS_TIMEOUT", 0.5), ("FRAME_CLASS", 7.0), ("RC1_MIN", 500.0), ("RCMAP_YAW", 0.0), ("MAV_GCS_SYSID", 256.0),
     ("RC_OVERRIDE_TIME", 121.0), ("MAV1_EXTRA1", 51.0), ("ARMING_CHECK", 3e9)],
)  # fmt: skip
def test_out_of_range_is_refused_with_the_unchanged_value(name: str, value: float) -> None:
    v = SimulatedVehicle(1, "buoy", 45.0)
    before = v.params[name]
    (echo,) = _set(v, name, value)
    assert echo.param_value == pytest.approx(before) and v.params[name] == before
    assert v.counters.rejected == 1


@pytest.mark.parametrize(("name", "value"), [("FS_TIMEOUT", math.nan), ("FS_TIMEOUT", math.inf), ("NO_SUCH", 1.0)])
def test_non_finite_or_unknown_is_ignored_without_a_reply(name: str, value: float) -> None:
    v = SimulatedVehicle(1, "buoy", 45.0)
    assert _set(v, name, value) == [] and v.params["FS_TIMEOUT"] == 1.5 and v.counters.rejected == 1


def test_stored_value_is_ap_params_set_float() -> None:
    assert stored_value(2.999, INT8) == 3.0 and stored_value(2.98, INT8) == 2.0 and stored_value(-2.5, INT8) == -2.0
    assert stored_value(1000.0, INT8) == 127.0 and stored_value(0.1, REAL32) == 0.1


def test_a_start_value_outside_the_range_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match=r"FS_TIMEOUT takes 1..100 \(Rover/Parameters.cpp\)"):
        SimulatedVehicle(1, "buoy", 45.0, params={"FS_TIMEOUT": 0.1})
    with pytest.raises(ValueError, match="no parameter 'SYSID_MYGCS'"):
        SimulatedVehicle(1, "buoy", 45.0, params={"SYSID_MYGCS": 200})
