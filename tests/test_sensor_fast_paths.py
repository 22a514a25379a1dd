"""`SensorSuite.sample` with its fast paths against its plain form, bit for bit, on random inputs (seeded).

The fast paths: every agent due or every truth finite (the usual case) indexes whole rows (views) instead of the
agents' rows (fancy indexing), and the finite check looks at whole arrays first. The plain form indexes by the
agents always and checks finiteness agent by agent, as the suite first did.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from bob_autonomy.core.geodesy import LocalFrame
from sitl.vehicles import sensors
from sitl.vehicles.sensors import CompassSpec, EncoderSpec, GpsSpec, ImuSpec, SensorSuite


def _plain_finite(agents, *arrays):
    """`SensorSuite._finite` as first written: the reference."""
    if agents.size == 0:
        return agents
    ok = None
    for array in arrays:
        finite = np.isfinite(array[agents])
        finite = finite.all(axis=1) if finite.ndim > 1 else finite
        ok = finite if ok is None else ok & finite
    return agents if ok.all() else agents[ok]


def _plain_world_to_body(vectors, heading_rad):
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    return np.column_stack((c * vectors[:, 0] + s * vectors[:, 1], -s * vectors[:, 0] + c * vectors[:, 1]))


def _bits(readings) -> list[bytes]:
    out = []
    for name in ("gps", "compass", "imu", "encoders"):
        reading = getattr(readings, name)
        if reading is None:
            out.append(b"none")
            continue
        for field in dataclasses.fields(reading):
            value = getattr(reading, field.name)
            out.append(b"None" if value is None else np.ascontiguousarray(value).tobytes())
    return out


def _run(seed: int, dt_s: float, tilt: bool, gps: GpsSpec) -> list[bytes]:
    rng = np.random.default_rng(seed)
    n = 17
    suite = SensorSuite(n, LocalFrame(47.0, 8.0), np.random.default_rng(seed + 1), gps, CompassSpec(),
                        ImuSpec(latency_s=0.03), EncoderSpec())  # fmt: skip
    out: list[bytes] = []
    for k in range(40):
        position, velocity, accel = (
            rng.normal(0.0, 100.0, (n, 2)),
            rng.normal(0.0, 1.0, (n, 2)),
            rng.normal(size=(n, 2)),
        )
        heading, yaw_rate, travel = rng.uniform(-4.0, 4.0, n), rng.normal(size=n), rng.normal(0.0, 3.0, (n, 2))
        if k % 3 == 1:  # a vehicle without a fix, one without a compass, an IMU overflow, a body without wheels
            position[rng.integers(n)] = np.nan
            heading[rng.integers(n)] = np.nan
            accel[rng.integers(n), 1] = np.inf
            travel[rng.integers(n)] = np.nan
        rolled = (rng.normal(0.0, 0.1, n), rng.normal(0.0, 0.1, n), rng.normal(0.0, 0.1, (n, 3))) if tilt else None
        readings = suite.sample((k + 1) * dt_s, position, velocity, accel, heading, yaw_rate, travel, tilt=rolled)
        out += _bits(readings)
    return out


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("dt_s", [0.5, 0.1, 0.013])  # every agent due at every step; some; few
@pytest.mark.parametrize("tilt", [False, True])
@pytest.mark.parametrize(
    "gps", [GpsSpec(), GpsSpec(correlated=3.0, common_noise_m=1.0, outages=((1.0, 2.0),), quantum_deg=0.0)]
)
def test_sample_matches_the_plain_suite_bit_for_bit(
    seed: int, dt_s: float, tilt: bool, gps: GpsSpec, monkeypatch: pytest.MonkeyPatch
) -> None:
    fast = _run(seed, dt_s, tilt, gps)
    monkeypatch.setattr(sensors, "_rows", lambda agents, n: agents)
    monkeypatch.setattr(SensorSuite, "_finite", staticmethod(_plain_finite))
    monkeypatch.setattr(sensors, "world_to_body", _plain_world_to_body)
    assert fast == _run(seed, dt_s, tilt, gps)
