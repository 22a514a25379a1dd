"""Simulated sensors (sitl/vehicles/sensors.py): noise statistics, rates, latency, outages, biases, frames,
determinism."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from bob_autonomy.core.geodesy import LocalFrame
from sitl.vehicles.sensors import (
    CompassSpec,
    EncoderSpec,
    GpsSpec,
    ImuSpec,
    LightSpec,
    RangeSpec,
    SensorReadings,
    SensorSuite,
    encoder_ticks,
    noisy_light,
    noisy_ranges,
)

FRAME = LocalFrame(1.33, 103.92)
QUIET_IMU = ImuSpec(accel_noise_mps2=0.0, accel_bias_std_mps2=0.0, gyro_noise_radps=0.0, gyro_bias_std_radps=0.0)


def wrap(a: np.ndarray) -> np.ndarray:
    return np.mod(np.asarray(a) + np.pi, 2 * np.pi) - np.pi


@dataclass
class Truth:
    """Agents moving at constant velocity from random positions, turning at constant rates."""

    n: int
    seed: int = 0
    p0: np.ndarray = field(init=False)
    v: np.ndarray = field(init=False)
    h0: np.ndarray = field(init=False)
    w: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        rng = np.random.default_rng(self.seed)
        self.p0 = rng.uniform(-1000.0, 1000.0, (self.n, 2))
        self.v = rng.uniform(-1.0, 1.0, (self.n, 2))
        self.h0 = rng.uniform(-np.pi, np.pi, self.n)
        self.w = rng.uniform(-0.3, 0.3, self.n)

    def position(self, t: np.ndarray | float, agents: np.ndarray | None = None) -> np.ndarray:
        agents = np.arange(self.n) if agents is None else agents
        return self.p0[agents] + self.v[agents] * np.asarray(t)[..., None]

    def heading(self, t: np.ndarray | float, agents: np.ndarray | None = None) -> np.ndarray:
        agents = np.arange(self.n) if agents is None else agents
        return wrap(self.h0[agents] + self.w[agents] * t)

    def sample(self, suite: SensorSuite, t: float, travel: np.ndarray | None = None) -> SensorReadings:
        accel = np.zeros((self.n, 2))
        return suite.sample(t, self.position(t), self.v, accel, self.heading(t), self.w, travel)


def run(suite: SensorSuite, truth: Truth, duration_s: float, dt_s: float) -> list[tuple[float, SensorReadings]]:
    """(delivery time, readings) of every sample() call at t = k dt, k = 0 .. duration / dt."""
    out = []
    for k in range(round(duration_s / dt_s) + 1):
        t = k * dt_s
        out.append((t, truth.sample(suite, t)))
    return out


def collect(results: list[tuple[float, SensorReadings]], sensor: str, *names: str) -> dict[str, np.ndarray]:
    """Concatenate one sensor's delivered fields over a run, plus 'delivered_t' (delivery time per row)."""
    rows = {name: [] for name in ("agents", "t_s", *names)}
    delivered = []
    for t, readings in results:
        reading = getattr(readings, sensor)
        if reading is None:
            continue
        for name in rows:
            rows[name].append(getattr(reading, name))
        delivered.append(np.full(reading.agents.shape[0], t))
    out = {name: np.concatenate(parts) for name, parts in rows.items()}
    out["delivered_t"] = np.concatenate(delivered)
    return out


def gps_error(fixes: dict[str, np.ndarray], truth: Truth) -> np.ndarray:
    x, y = FRAME.to_local(fixes["lat_deg"], fixes["lon_deg"])
    return np.column_stack((x, y)) - truth.position(fixes["t_s"], fixes["agents"])


# ---------------------------------------------------------------- one 60 s run at dt 0.01, shared


N_RUN, T_RUN, DT_RUN = 20, 60.0, 0.01


@pytest.fixture(scope="module")
def long_run() -> tuple[Truth, list[tuple[float, SensorReadings]]]:
    truth = Truth(N_RUN, seed=1)
    suite = SensorSuite(N_RUN, FRAME, np.random.default_rng(11), encoders=None)
    return truth, run(suite, truth, T_RUN, DT_RUN)


def test_rates_give_round_t_times_r_readings_per_agent(long_run) -> None:
    _, results = long_run
    for sensor, rate, latency in (("gps", 5.0, 0.1), ("compass", 10.0, 0.0), ("imu", 50.0, 0.0)):
        rows = collect(results, sensor)
        measured_by_end = np.bincount(rows["agents"], minlength=N_RUN)
        in_flight = latency * rate  # fixes measured in the last latency_s are not delivered yet
        assert np.all(np.abs(measured_by_end - (round(T_RUN * rate) - in_flight)) <= 1), sensor


def test_agents_are_not_synchronized(long_run) -> None:
    _, results = long_run
    rows = collect(results, "gps")
    first = np.array([rows["t_s"][rows["agents"] == i].min() for i in range(N_RUN)])
    assert np.unique(np.round(first, 6)).size >= N_RUN // 2
    assert first.max() <= 0.2 + DT_RUN


def test_gps_latency_is_kept_in_t_s(long_run) -> None:
    _, results = long_run
    rows = collect(results, "gps")
    age = rows["delivered_t"] - rows["t_s"]
    assert np.all(age >= 0.1 - 1e-9)
    assert np.all(age < 0.1 + DT_RUN + 1e-9)
    compass = collect(results, "compass")
    assert_allclose(compass["delivered_t"], compass["t_s"])  # no latency


def test_gps_lat_lon_are_multiples_of_the_quantum(long_run) -> None:
    _, results = long_run
    rows = collect(results, "gps", "lat_deg", "lon_deg")
    for values in (rows["lat_deg"], rows["lon_deg"]):
        units = values / 1e-7
        assert np.max(np.abs(units - np.round(units))) < 1e-6


def test_gps_white_error_statistics_match_noise_m(long_run) -> None:
    truth, results = long_run
    rows = collect(results, "gps", "lat_deg", "lon_deg")
    error = gps_error(rows, truth)
    assert error.shape[0] > 5000
    assert_allclose(error.std(axis=0), 2.0, rtol=0.1)
    assert np.all(np.abs(error.mean(axis=0)) < 4 * 2.0 / math.sqrt(error.shape[0]))
    # White: consecutive fixes of one agent are uncorrelated.
    a = error[rows["agents"] == 0]
    assert abs(np.corrcoef(a[:-1, 0], a[1:, 0])[0, 1]) < 0.25


def test_gps_ground_velocity_is_noisy_truth(long_run) -> None:
    truth, results = long_run
    rows = collect(results, "gps", "velocity_mps")
    error = rows["velocity_mps"] - truth.v[rows["agents"]]
    assert_allclose(error.std(axis=0), 0.1, rtol=0.1)


def test_compass_bias_is_constant_per_agent_and_noise_matches(long_run) -> None:
    truth, results = long_run
    rows = collect(results, "compass", "heading_rad")
    assert np.all((rows["heading_rad"] > -np.pi) & (rows["heading_rad"] <= np.pi))
    residual = wrap(rows["heading_rad"] - truth.heading(rows["t_s"], rows["agents"]))
    per_agent_bias = np.array([residual[rows["agents"] == i].mean() for i in range(N_RUN)])
    noise = residual - per_agent_bias[rows["agents"]]
    assert np.degrees(noise.std()) == pytest.approx(2.0, rel=0.1)
    assert np.degrees(np.abs(per_agent_bias).max()) < 5.0  # std 1 deg


# ---------------------------------------------------------------- rates and timing


@pytest.mark.parametrize("dt", [0.001, 0.05, 0.2])
def test_rate_does_not_depend_on_the_step(dt: float) -> None:
    truth = Truth(10)
    suite = SensorSuite(10, FRAME, np.random.default_rng(2), gps=GpsSpec(latency_s=0.0), encoders=None)
    rows = collect(run(suite, truth, 10.0, dt), "gps")
    counts = np.bincount(rows["agents"], minlength=10)
    assert np.all(np.abs(counts - 50) <= 1)


def test_slower_step_than_the_rate_gives_one_reading_per_step() -> None:
    truth = Truth(10)
    suite = SensorSuite(10, FRAME, np.random.default_rng(2), encoders=None)  # IMU 50 Hz, dt 0.1
    results = run(suite, truth, 10.0, 0.1)
    for _, readings in results[1:]:
        assert readings.imu is not None
        assert_array_equal(np.sort(readings.imu.agents), np.arange(10))


def test_no_gps_fixes_inside_an_outage() -> None:
    truth = Truth(10)
    spec = GpsSpec(outages=((10.0, 20.0), (30.0, 31.0)))
    suite = SensorSuite(10, FRAME, np.random.default_rng(3), gps=spec, encoders=None)
    rows = collect(run(suite, truth, 40.0, 0.05), "gps")
    t = rows["t_s"]
    assert not np.any((t >= 10.0) & (t < 20.0))
    assert not np.any((t >= 30.0) & (t < 31.0))
    for lo, hi in ((0.0, 10.0), (20.0, 30.0), (31.0, 39.0)):
        assert np.all(np.bincount(rows["agents"][(t >= lo) & (t < hi)], minlength=10) >= round((hi - lo) * 5) - 1)


def test_time_must_not_go_back() -> None:
    truth = Truth(2)
    suite = SensorSuite(2, FRAME, np.random.default_rng(0))
    truth.sample(suite, 1.0)
    truth.sample(suite, 1.0)  # the same time again is fine
    with pytest.raises(ValueError, match="back in time"):
        truth.sample(suite, 0.5)


# ---------------------------------------------------------------- GPS correlated error


def test_gps_gauss_markov_error_wanders_slowly_with_the_stationary_std() -> None:
    n = 1000
    truth = Truth(n, seed=4)
    spec = GpsSpec(correlated=30.0, latency_s=0.0, quantum_deg=0.0)
    suite = SensorSuite(n, FRAME, np.random.default_rng(5), gps=spec, compass=None, imu=None, encoders=None)
    rows = collect(run(suite, truth, 10.0, 0.2), "gps", "lat_deg", "lon_deg")
    error = gps_error(rows, truth)
    assert_allclose(error.std(axis=0), 2.0, rtol=0.1)
    order = np.lexsort((rows["t_s"], rows["agents"]))
    a, e = rows["agents"][order], error[order]
    same = a[1:] == a[:-1]
    lag1 = np.corrcoef(e[:-1][same, 0], e[1:][same, 0])[0, 1]
    assert lag1 > 0.98  # exp(-0.2 / 30) = 0.993


# ---------------------------------------------------------------- compass


def test_compass_bias_std_across_agents() -> None:
    n = 3000
    truth = Truth(n, seed=6)
    suite = SensorSuite(n, FRAME, np.random.default_rng(7), compass=CompassSpec(noise_deg=0.0), encoders=None)
    rows = collect(run(suite, truth, 1.0, 0.05), "compass", "heading_rad")
    residual = wrap(rows["heading_rad"] - truth.heading(rows["t_s"], rows["agents"]))
    bias = np.full(n, np.nan)
    bias[rows["agents"]] = residual
    for i in range(n):  # constant over time
        assert np.ptp(residual[rows["agents"] == i]) < 1e-12
    assert np.degrees(np.nanstd(bias)) == pytest.approx(1.0, rel=0.1)


def test_compass_wraps_to_minus_pi_pi() -> None:
    suite = SensorSuite(500, FRAME, np.random.default_rng(8), gps=None, imu=None, encoders=None)
    heading = np.full(500, np.pi - 1e-3)
    zeros = np.zeros((500, 2))
    readings = [suite.sample(k * 0.1, zeros, zeros, zeros, heading, np.zeros(500)) for k in range(3)]
    values = np.concatenate([r.compass.heading_rad for r in readings if r.compass is not None])
    assert np.all((values > -np.pi) & (values <= np.pi))
    assert np.any(values < 0.0)  # some bias pushed it past pi


# ---------------------------------------------------------------- IMU


@pytest.mark.parametrize(
    ("heading_deg", "accel_world", "accel_body"),
    [
        (90.0, (1.0, 0.0), (0.0, -1.0)),  # facing north, accelerating east: east is to the right (body -y)
        (90.0, (0.0, 2.0), (2.0, 0.0)),  # facing north, accelerating north: straight ahead
        (0.0, (0.5, -0.3), (0.5, -0.3)),  # facing east: body = world
        (180.0, (1.0, 1.0), (-1.0, -1.0)),  # facing west: both flipped
        (45.0, (1.0, 1.0), (math.sqrt(2.0), 0.0)),  # accelerating along the heading
        (-90.0, (1.0, 0.0), (0.0, 1.0)),  # facing south, accelerating east: east is to the left
    ],
)
def test_imu_accelerometer_reads_in_the_body_frame(heading_deg, accel_world, accel_body) -> None:
    suite = SensorSuite(1, FRAME, np.random.default_rng(0), gps=None, compass=None, imu=QUIET_IMU, encoders=None)
    zeros = np.zeros((1, 2))
    reading = None
    for k in range(3):  # 50 Hz, dt 0.02: a reading each step after the first phase
        r = suite.sample(k * 0.02, zeros, zeros, np.array([accel_world]), np.radians([heading_deg]), np.array([0.3]))
        reading = r.imu or reading
    assert reading is not None
    assert_allclose(reading.accel_body_mps2[-1], accel_body, atol=1e-12)
    assert reading.gyro_z_radps[-1] == pytest.approx(0.3)


def test_imu_biases_are_constant_per_agent_and_noise_matches() -> None:
    n = 2000
    rng_truth = np.random.default_rng(9)
    accel = rng_truth.normal(0.0, 0.5, (n, 2))
    heading = rng_truth.uniform(-np.pi, np.pi, n)
    yaw_rate = rng_truth.normal(0.0, 0.2, n)
    zeros = np.zeros((n, 2))

    def readings(spec: ImuSpec) -> list:
        suite = SensorSuite(n, FRAME, np.random.default_rng(10), gps=None, compass=None, imu=spec, encoders=None)
        # The first call starts the schedules (nothing is due yet); then one reading per step (dt > 1 / 50 Hz).
        return [suite.sample(k * 0.1, zeros, zeros, accel, heading, yaw_rate).imu for k in range(6)][1:]

    c, s = np.cos(heading), np.sin(heading)
    body = np.column_stack((c * accel[:, 0] + s * accel[:, 1], -s * accel[:, 0] + c * accel[:, 1]))

    biased = readings(ImuSpec(accel_noise_mps2=0.0, gyro_noise_radps=0.0))
    gyro_bias = [r.gyro_z_radps - yaw_rate[r.agents] for r in biased]
    accel_bias = [r.accel_body_mps2 - body[r.agents] for r in biased]
    for r, g, a in zip(biased[1:], gyro_bias[1:], accel_bias[1:], strict=True):
        assert_array_equal(r.agents, biased[0].agents)
        assert_allclose(g, gyro_bias[0], atol=1e-12)
        assert_allclose(a, accel_bias[0], atol=1e-12)
    assert np.std(gyro_bias[0]) == pytest.approx(0.002, rel=0.1)
    assert_allclose(np.std(accel_bias[0], axis=0), 0.02, rtol=0.1)

    noisy = readings(ImuSpec(accel_bias_std_mps2=0.0, gyro_bias_std_radps=0.0))
    gyro_error = np.concatenate([r.gyro_z_radps - yaw_rate[r.agents] for r in noisy])
    accel_error = np.concatenate([r.accel_body_mps2 - body[r.agents] for r in noisy])
    assert np.std(gyro_error) == pytest.approx(0.005, rel=0.1)
    assert abs(np.mean(gyro_error)) < 4 * 0.005 / math.sqrt(gyro_error.size)
    assert_allclose(np.std(accel_error, axis=0), 0.05, rtol=0.1)


# ---------------------------------------------------------------- encoders


def test_encoder_ticks_follow_the_wheel_travel() -> None:
    spec = EncoderSpec(ticks_per_rev=360, wheel_radius_m=0.03)
    n = 50
    rng = np.random.default_rng(11)
    travel = rng.uniform(-2.0, 5.0, (n, 2))
    travel[7] = np.nan  # no wheels
    suite = SensorSuite(n, FRAME, np.random.default_rng(0), gps=None, compass=None, imu=None, encoders=spec)
    zeros = np.zeros((n, 2))
    reading = suite.sample(0.0, zeros, zeros, zeros, np.zeros(n), np.zeros(n), travel).encoders
    assert reading is not None
    assert 7 not in reading.agents and reading.agents.size == n - 1
    assert reading.ticks.dtype == np.int64 and reading.ticks.shape == (n - 1, 2)
    expected = np.floor(travel[reading.agents] / (2 * math.pi * 0.03) * 360)
    assert_array_equal(reading.ticks, expected)
    one_rev = 2 * math.pi * 0.03
    assert_array_equal(encoder_ticks([[one_rev * 1.0001, one_rev * 0.5001]], spec), [[360, 180]])
    assert_array_equal(encoder_ticks([[-1e-9, 1e-9]], spec), [[-1, 0]])


def test_encoder_ticks_are_monotone_in_travel() -> None:
    travel = np.sort(np.random.default_rng(12).uniform(-1.0, 3.0, 5000))
    ticks = encoder_ticks(travel, EncoderSpec())
    assert np.all(np.diff(ticks) >= 0)
    assert ticks[-1] - ticks[0] == pytest.approx((travel[-1] - travel[0]) / (2 * math.pi * 0.03) * 360, abs=1)


def test_no_encoder_readings_without_travel_or_spec() -> None:
    zeros = np.zeros((3, 2))
    suite = SensorSuite(3, FRAME, np.random.default_rng(0))
    assert suite.sample(0.0, zeros, zeros, zeros, np.zeros(3), np.zeros(3)).encoders is None
    suite = SensorSuite(3, FRAME, np.random.default_rng(0), encoders=None)
    assert suite.sample(0.0, zeros, zeros, zeros, np.zeros(3), np.zeros(3), zeros).encoders is None


# ---------------------------------------------------------------- range finders and light


def test_range_noise_is_along_the_echo_and_keeps_nan() -> None:
    rng = np.random.default_rng(13)
    n = 2000
    angles = rng.uniform(-np.pi, np.pi, (n, 6))
    distance = rng.uniform(0.2, 1.4, (n, 6))
    distance[rng.random((n, 6)) < 0.3] = np.nan
    offsets = np.stack((np.cos(angles), np.sin(angles)), axis=-1) * distance[..., None]
    suite = SensorSuite(n, FRAME, np.random.default_rng(14))
    noisy = suite.noisy_ranges(offsets, np.random.default_rng(15))
    assert noisy.shape == (n, 6, 2)
    assert_array_equal(np.isnan(noisy), np.isnan(offsets))
    seen = ~np.isnan(distance)
    cross = offsets[..., 0] * noisy[..., 1] - offsets[..., 1] * noisy[..., 0]
    dot = np.einsum("...i,...i->...", offsets, noisy)
    assert np.max(np.abs(cross[seen])) < 1e-12 and np.all(dot[seen] > 0.0)
    error = np.hypot(noisy[..., 0], noisy[..., 1])[seen] - distance[seen]
    assert np.std(error) == pytest.approx(0.01, rel=0.1)
    assert abs(np.mean(error)) < 4 * 0.01 / math.sqrt(error.size)


def test_light_noise_is_multiplicative_and_never_negative() -> None:
    rng = np.random.default_rng(16)
    readings = rng.uniform(0.5, 2.0, (5000, 2))
    noisy = noisy_light(readings, np.random.default_rng(17), LightSpec(noise_rel=0.05))
    assert np.std(noisy / readings - 1.0) == pytest.approx(0.05, rel=0.1)
    dim = np.full((5000, 2), 1e-3)
    dim[0, 0] = np.nan
    very_noisy = noisy_light(dim, np.random.default_rng(18), LightSpec(noise_rel=2.0))
    assert np.isnan(very_noisy[0, 0])
    assert np.all(very_noisy[1:] >= 0.0) and np.any(very_noisy[1:] == 0.0)
    suite = SensorSuite(5000, FRAME, np.random.default_rng(0))
    assert np.all(suite.noisy_light(readings, np.random.default_rng(19)) >= 0.0)


def test_range_helper_defaults_and_disabled_specs() -> None:
    offsets = np.array([[[1.0, 0.0], [np.nan, np.nan]]])
    assert_array_equal(noisy_ranges(offsets, np.random.default_rng(0), RangeSpec(noise_m=0.0)), offsets)
    suite = SensorSuite(1, FRAME, np.random.default_rng(0), ranges=None, light=None)
    assert_array_equal(suite.noisy_ranges(offsets), offsets)
    assert_array_equal(suite.noisy_light(np.array([[1.0, 2.0]])), [[1.0, 2.0]])


# ---------------------------------------------------------------- determinism and validation


def readings_signature(seed: int) -> list[np.ndarray]:
    truth = Truth(8, seed=20)
    suite = SensorSuite(8, FRAME, np.random.default_rng(seed), gps=GpsSpec(correlated=5.0))
    out = []
    for k in range(200):
        t = k * 0.02
        r = truth.sample(suite, t, np.full((8, 2), 0.01 * k))
        for reading in (r.gps, r.compass, r.imu, r.encoders):
            if reading is not None:
                out.extend(np.asarray(v, dtype=float).ravel() for v in vars(reading).values() if v is not None)
    out.append(suite.noisy_ranges(np.ones((8, 6, 2))).ravel())
    out.append(suite.noisy_light(np.ones((8, 2))).ravel())
    return out


def test_same_seed_same_readings_different_seed_different() -> None:
    a, b, c = readings_signature(1), readings_signature(1), readings_signature(2)
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert_array_equal(x, y)
    assert len(a) != len(c) or any(x.shape != y.shape or not np.array_equal(x, y) for x, y in zip(a, c, strict=True))


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: GpsSpec(rate_hz=0.0), "rate_hz"),
        (lambda: GpsSpec(noise_m=-1.0), "noise_m"),
        (lambda: GpsSpec(outages=((5.0, 2.0),)), "outages"),
        (lambda: GpsSpec(correlated=math.nan), "correlated"),
        (lambda: CompassSpec(latency_s=-0.1), "latency_s"),
        (lambda: ImuSpec(gyro_noise_radps=-1.0), "gyro_noise_radps"),
        (lambda: EncoderSpec(ticks_per_rev=0), "ticks_per_rev"),
        (lambda: EncoderSpec(wheel_radius_m=0.0), "wheel_radius_m"),
        (lambda: RangeSpec(noise_m=-0.1), "noise_m"),
        (lambda: LightSpec(noise_rel=math.inf), "noise_rel"),
    ],
)
def test_bad_specs_raise(make, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        make()


def test_bad_truth_shape_raises() -> None:
    suite = SensorSuite(3, FRAME, np.random.default_rng(0))
    zeros = np.zeros((3, 2))
    with pytest.raises(ValueError, match="position_m"):
        suite.sample(0.0, np.zeros((2, 2)), zeros, zeros, np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="heading_rad"):
        suite.sample(0.0, zeros, zeros, zeros, np.zeros(4), np.zeros(3))


def test_agents_with_nan_truth_get_no_fix() -> None:
    n = 4
    suite = SensorSuite(n, FRAME, np.random.default_rng(0), gps=GpsSpec(latency_s=0.0), encoders=None)
    position = np.zeros((n, 2))
    position[2] = np.nan
    zeros = np.zeros((n, 2))
    agents = []
    for k in range(20):
        r = suite.sample(k * 0.05, position, zeros, zeros, np.zeros(n), np.zeros(n))
        if r.gps is not None:
            agents.extend(r.gps.agents.tolist())
    assert 2 not in agents and set(agents) == {0, 1, 3}


def test_common_mode_gps_error_moves_every_receiver_together() -> None:
    # Independent noise 0, common-mode 3 m: two receivers 10 m apart always read exactly 10 m apart
    # (to the 1e-7 deg quantum, ~1.1 cm), while each fix is off by metres.
    frame = LocalFrame(1.33, 103.92)
    gps = GpsSpec(rate_hz=10.0, noise_m=0.0, latency_s=0.0, common_noise_m=3.0, common_time_constant_s=30.0)
    suite = SensorSuite(2, frame, np.random.default_rng(5), gps=gps, compass=None, imu=None, encoders=None)
    truth = np.array([[0.0, 0.0], [10.0, 0.0]])
    zeros2, zeros1 = np.zeros((2, 2)), np.zeros(2)
    offsets, separations = [], []
    for step in range(1, 2001):
        fix = suite.sample(step * 0.01, truth, zeros2, zeros2, zeros1, zeros1).gps
        if fix is None or fix.agents.size < 2 or fix.t_s[0] != fix.t_s[1]:
            continue
        x, y = frame.to_local(fix.lat_deg, fix.lon_deg)
        order = np.argsort(fix.agents)
        x, y = x[order], y[order]
        offsets.append(np.hypot(x[0], y[0]))
        separations.append(np.hypot(x[1] - x[0], y[1] - y[0]))
    assert len(separations) > 10
    np.testing.assert_allclose(separations, 10.0, atol=0.03)
    assert max(offsets) > 0.5
