"""Simulated sensors: what a body's autonomy sees of the simulator's truth.

Ground truth comes in as arrays over the N agents of a fleet; out come noisy,
rate-limited, delayed readings, vectorized over agents (no Python loop over
agents). Everything random is drawn from the numpy Generator given to the
suite, so a run with a seed is exactly repeatable.

Sensors and their models (frames as in DESIGN.md: x east, y north in metres,
heading in radians from east, counter-clockwise, wrapped to (-pi, pi]):

- GPS (`GpsSpec`): horizontal position error per axis, white or first-order
  Gauss-Markov (`correlated` = its time constant in s: the error wanders
  slowly with stationary std `noise_m`); the erroneous local position is
  turned into WGS-84 latitude/longitude with `LocalFrame.to_geodetic` and
  quantized to `quantum_deg` (1e-7 deg is MAVLink's integer lat/lon unit).
  No fixes inside outage windows [t_start_s, t_end_s). Each fix also carries
  the ground velocity (east, north) with white noise `velocity_noise_mps`.
- Compass (`CompassSpec`): heading + a constant per-agent bias (drawn once at
  construction) + white noise, wrapped to (-pi, pi].
- IMU (`ImuSpec`): horizontal accelerometer, level (no gravity, no tilt): the
  true world-frame acceleration rotated into the body frame (x forward along
  the heading, y to the left), + constant per-axis bias + white noise; gyro:
  true yaw rate + constant bias + white noise.
- Wheel encoders (`EncoderSpec`): cumulative signed integer ticks per wheel
  (left, right), floor(travel / (2 pi r) * ticks_per_rev), from the cumulative
  wheel travel (m) the simulator integrates. Read at every `sample` call.
- Range finders (`RangeSpec`) and light sensors (`LightSpec`): helpers that add
  noise to what `sitl.vehicles.bodies.KinematicBodies.range_finders` / `light_sensors`
  return; the simulator calls them when a body senses.

Timing. Each agent samples each rate-limited sensor (GPS, compass, IMU) on its
own periodic schedule t = t0 + phase + k / rate_hz, with a random phase in
[0, 1 / rate_hz) drawn per agent and sensor, so agents are not synchronized
(t0 is the time of the first `sample` call). The simulator only knows the truth
at its steps, so a measurement scheduled inside a step (t_prev, t] is taken at
t, from the truth passed in at t, and its `t_s` is t: the time the measured
truth belongs to. It is delivered by the first `sample` call at or after
t_s + latency_s. Consequences:

- with step dt <= 1 / rate_hz, an agent gets round(T * rate_hz) readings over
  T seconds (+-1), whatever dt is;
- with dt > 1 / rate_hz, an agent gets one reading per step (the schedule
  skips the measurements it cannot take; it never bunches several readings of
  the same truth into one step);
- a reading delivered at t has t - latency_s - dt < t_s <= t - latency_s.

Agents whose truth is not finite (NaN) at a scheduled measurement get no reading
from it (e.g. a body without wheels passes NaN wheel travel).
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bob_autonomy.core.geodesy import LocalFrame
from firmware_bridge.decoder import STANDARD_GRAVITY_MPS2
from firmware_bridge.readings import CompassReading, EncoderReading, GpsFix, ImuReading, SensorReadings

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

_TIME_EPS_S = 1e-9  # tolerance on schedule and delivery times (float steps such as k * 0.01)


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise ValueError(message)


def _check_rate_latency(spec: object) -> None:
    rate, latency = spec.rate_hz, spec.latency_s  # type: ignore[attr-defined]
    name = type(spec).__name__
    _require(math.isfinite(rate) and rate > 0.0, f"{name}.rate_hz must be positive and finite; got {rate!r}")
    _require(math.isfinite(latency) and latency >= 0.0, f"{name}.latency_s must be >= 0 and finite; got {latency!r}")


def _check_nonnegative(spec: object, *names: str) -> None:
    for name in names:
        value = getattr(spec, name)
        message = f"{type(spec).__name__}.{name} must be >= 0 and finite; got {value!r}"
        _require(math.isfinite(value) and value >= 0.0, message)


# ---------------------------------------------------------------- specifications


@dataclass(frozen=True)
class GpsSpec:
    """A GPS receiver (defaults: a consumer module on a BoB buoy).

    rate_hz: fixes per second. noise_m: per-axis standard deviation (m) of the
    horizontal position error. latency_s: delay from measurement to delivery.
    quantum_deg: output resolution of latitude and longitude (0 = none).
    outages: (t_start_s, t_end_s) windows without fixes. correlated: time
    constant (s) of the first-order Gauss-Markov position error (0 = white:
    independent from fix to fix). velocity_noise_mps: per-axis standard
    deviation of the ground velocity (m/s). common_noise_m: per-axis standard
    deviation (m) of an error shared by every receiver of the fleet (same
    satellites, same atmosphere), a Gauss-Markov process with time constant
    common_time_constant_s: it moves the whole swarm's fixes together, so it
    spoils absolute but not relative positions.
    accuracy_m, speed_accuracy_mps: the one-sigma horizontal (m) and speed (m/s)
    accuracies the receiver reports with each fix (GPS_RAW_INT h_acc and vel_acc,
    as a u-blox does and ArduPilot's SITL with SIM_GPS1_ACC): None (default)
    reports its own noise, noise_m and velocity_noise_mps (a receiver cannot know
    the fleet-wide common error); a value reports that (an optimistic or a
    pessimistic receiver); 0 reports none (an old receiver, MAVLink 1).
    """

    rate_hz: float = 5.0
    noise_m: float = 2.0
    latency_s: float = 0.1
    quantum_deg: float = 1e-7
    outages: tuple[tuple[float, float], ...] = ()
    correlated: float = 0.0
    velocity_noise_mps: float = 0.1
    common_noise_m: float = 0.0
    common_time_constant_s: float = 60.0
    accuracy_m: float | None = None
    speed_accuracy_mps: float | None = None

    def __post_init__(self) -> None:
        _check_rate_latency(self)
        _check_nonnegative(self, "noise_m", "quantum_deg", "correlated", "velocity_noise_mps", "common_noise_m")
        _check_nonnegative(self, *(n for n in ("accuracy_m", "speed_accuracy_mps") if getattr(self, n) is not None))
        _require(self.common_time_constant_s > 0.0, "GpsSpec.common_time_constant_s must be positive")
        for window in self.outages:
            _require(
                len(window) == 2 and all(math.isfinite(v) for v in window) and window[0] < window[1],
                f"GpsSpec.outages: each window must be (t_start_s, t_end_s) with t_start_s < t_end_s; got {window!r}",
            )

    def in_outage(self, t_s: float) -> bool:
        """Whether a fix measured at t_s (s) falls inside an outage window [t_start_s, t_end_s)."""
        return any(start <= t_s < end for start, end in self.outages)

    def reported(self) -> tuple[float, float] | None:
        """The (horizontal m, speed m/s) accuracies the receiver reports, NaN for one it does not; None when it
        reports neither."""
        horizontal = self.noise_m if self.accuracy_m is None else self.accuracy_m
        speed = self.velocity_noise_mps if self.speed_accuracy_mps is None else self.speed_accuracy_mps
        if horizontal == 0.0 and speed == 0.0:
            return None
        return (horizontal or math.nan), (speed or math.nan)


@dataclass(frozen=True)
class CompassSpec:
    """A MEMS compass: rate_hz readings per second, white noise_deg (std), a constant
    per-agent bias drawn once with std bias_std_deg, latency_s from measurement to delivery."""

    rate_hz: float = 10.0
    noise_deg: float = 2.0
    bias_std_deg: float = 1.0
    latency_s: float = 0.0
    tilt_noise_deg: float = 0.2  # the roll and pitch an autopilot reports with it, when waves tilt the hull

    def __post_init__(self) -> None:
        _check_rate_latency(self)
        _check_nonnegative(self, "noise_deg", "bias_std_deg", "tilt_noise_deg")


@dataclass(frozen=True)
class ImuSpec:
    """A MEMS IMU (horizontal accelerometer axes and the yaw gyro): white noise std and the std of
    constant per-agent biases (drawn once) for each; rate_hz readings per second; latency_s."""

    rate_hz: float = 50.0
    accel_noise_mps2: float = 0.05
    accel_bias_std_mps2: float = 0.02
    gyro_noise_radps: float = 0.005
    gyro_bias_std_radps: float = 0.002
    latency_s: float = 0.0

    def __post_init__(self) -> None:
        _check_rate_latency(self)
        _check_nonnegative(self, "accel_noise_mps2", "accel_bias_std_mps2", "gyro_noise_radps", "gyro_bias_std_radps")


@dataclass(frozen=True)
class EncoderSpec:
    """Quadrature wheel encoders: ticks_per_rev per wheel revolution, wheel_radius_m (eBot-like)."""

    ticks_per_rev: int = 360
    wheel_radius_m: float = 0.03

    def __post_init__(self) -> None:
        _require(self.ticks_per_rev > 0, f"EncoderSpec.ticks_per_rev must be positive; got {self.ticks_per_rev!r}")
        _require(
            math.isfinite(self.wheel_radius_m) and self.wheel_radius_m > 0.0,
            f"EncoderSpec.wheel_radius_m must be positive and finite; got {self.wheel_radius_m!r}",
        )

    @property
    def metres_per_tick(self) -> float:
        return 2.0 * math.pi * self.wheel_radius_m / self.ticks_per_rev


@dataclass(frozen=True)
class RangeSpec:
    """Ultrasonic / infrared range finders: noise_m, std of the range error along each echo's direction."""

    noise_m: float = 0.01

    def __post_init__(self) -> None:
        _check_nonnegative(self, "noise_m")


@dataclass(frozen=True)
class LightSpec:
    """Light sensors: noise_rel, std of the multiplicative error (reading * (1 + noise_rel * N(0, 1)))."""

    noise_rel: float = 0.05

    def __post_init__(self) -> None:
        _check_nonnegative(self, "noise_rel")


# ---------------------------------------------------------------- readings


Reading = TypeVar("Reading", GpsFix, CompassReading, ImuReading, EncoderReading)


def _concatenate(readings: list[Reading]) -> Reading:
    """One reading holding the rows of several of the same type, in order."""
    if len(readings) == 1:
        return readings[0]
    values = {}
    for field in dataclasses.fields(readings[0]):
        parts = [getattr(r, field.name) for r in readings]
        values[field.name] = None if any(p is None for p in parts) else np.concatenate(parts)
    return type(readings[0])(**values)


# ---------------------------------------------------------------- helpers


def wrap_angle(angle_rad: ArrayLike) -> FloatArray:
    """Angles wrapped to (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(angle_rad, dtype=float), 2.0 * np.pi)


def world_to_body(vectors: FloatArray, heading_rad: FloatArray) -> FloatArray:
    """(k, 2) world-frame vectors (east, north) into the body frame (x forward along heading, y left)."""
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    x, y = vectors[:, 0], vectors[:, 1]
    body = np.empty((len(c), 2))
    body[:, 0], body[:, 1] = c * x + s * y, -s * x + c * y
    return body


def tilted_imu(
    level_accel_mps2: FloatArray, roll_rad: FloatArray, pitch_rad: FloatArray, body_rates_frd_radps: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """(specific force (k, 3) m/s^2, body rates (k, 3) rad/s), x forward, y left, z up, that an IMU on a hull tilted
    by roll and pitch (k,) rad reads when the hull accelerates at level_accel (k, 2) (forward, left in the level
    frame that yaws with it): f = R^T (a - g) with R = Ry(pitch) Rx(roll), in FRD, then flipped to ours."""
    down = np.full(len(roll_rad), -STANDARD_GRAVITY_MPS2)  # a - g, g = +9.8 m/s^2 down
    a = np.column_stack((level_accel_mps2[:, 0], -level_accel_mps2[:, 1], down))
    sr, cr, sp, cp = np.sin(roll_rad), np.cos(roll_rad), np.sin(pitch_rad), np.cos(pitch_rad)
    # R^T = Rx^T Ry^T: first undo the pitch, then the roll
    x = cp * a[:, 0] - sp * a[:, 2]
    z1 = sp * a[:, 0] + cp * a[:, 2]
    y = cr * a[:, 1] + sr * z1
    z = -sr * a[:, 1] + cr * z1
    flip = np.array([1.0, -1.0, -1.0])
    return np.column_stack((x, y, z)) * flip, body_rates_frd_radps * flip


def encoder_ticks(wheel_travel_m: ArrayLike, spec: EncoderSpec) -> NDArray[np.int64]:
    """Cumulative signed ticks floor(travel / (2 pi r) * ticks_per_rev) of cumulative wheel travel (m)."""
    travel = np.asarray(wheel_travel_m, dtype=float)
    return np.floor(travel / (2.0 * math.pi * spec.wheel_radius_m) * spec.ticks_per_rev).astype(np.int64)


def noisy_ranges(offsets: ArrayLike, rng: np.random.Generator, spec: RangeSpec | None = None) -> FloatArray:
    """Range-finder offsets (..., 2) (m, e.g. (N, 6, 2)) with Gaussian range noise along each echo's direction.

    The direction is kept; the range gets N(0, noise_m^2) added and is clipped at 0.
    NaN (no echo) stays NaN; a zero offset stays zero (no direction to move along).
    """
    spec = RangeSpec() if spec is None else spec
    offsets = np.asarray(offsets, dtype=float)
    rng_range = np.hypot(offsets[..., 0], offsets[..., 1])
    noisy = np.maximum(rng_range + spec.noise_m * rng.standard_normal(rng_range.shape), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(rng_range > 0.0, noisy / rng_range, 1.0)
    return offsets * scale[..., None]


def noisy_light(readings: ArrayLike, rng: np.random.Generator, spec: LightSpec | None = None) -> FloatArray:
    """Light readings (e.g. (N, 2), W/m^2) times (1 + noise_rel * N(0, 1)), never negative; NaN stays NaN."""
    spec = LightSpec() if spec is None else spec
    readings = np.asarray(readings, dtype=float)
    return np.maximum(readings * (1.0 + spec.noise_rel * rng.standard_normal(readings.shape)), 0.0)


# ---------------------------------------------------------------- the suite


def _rows(agents: IntArray, n: int) -> IntArray | slice:
    """An index for the rows of `agents` (sorted, distinct, out of n): a slice when it is every row, the usual case
    (a view, no fancy indexing), else agents."""
    return slice(None) if agents.shape[0] == n else agents


def _filled(k: int, value: float) -> FloatArray:
    """(k,) float array of value (np.full without its Python-level overhead)."""
    out = np.empty(k)
    out.fill(value)
    return out


class _Channel:
    """The measurement schedule and delivery queue of one rate-limited sensor over all agents."""

    def __init__(self, n_agents: int, rate_hz: float, latency_s: float, rng: np.random.Generator) -> None:
        self.period_s = 1.0 / rate_hz
        self.phase_s = rng.uniform(0.0, self.period_s, n_agents)
        self.latency_s = latency_s
        self.next_due_s: FloatArray | None = None
        self.pending: deque[tuple[float, object]] = deque()

    def due(self, t_s: float) -> IntArray:
        """Agents with a measurement scheduled in the step ending at t_s; their schedules move past t_s."""
        if self.next_due_s is None:
            self.next_due_s = t_s + self.phase_s
        limit = t_s + _TIME_EPS_S
        agents = (self.next_due_s <= limit).nonzero()[0]
        rows = _rows(agents, self.next_due_s.shape[0])
        if agents.size:
            behind = limit - self.next_due_s[rows]
            self.next_due_s[rows] += self.period_s * (np.floor(behind / self.period_s) + 1.0)
        return agents

    def push(self, t_s: float, reading: object) -> None:
        self.pending.append((t_s + self.latency_s, reading))

    def deliver(self, t_s: float):  # -> Reading | None
        ready = []
        while self.pending and self.pending[0][0] <= t_s + _TIME_EPS_S:
            ready.append(self.pending.popleft()[1])
        return _concatenate(ready) if ready else None


class SensorSuite:
    """The sensors of every agent of a fleet; see the module docstring for the models and timing.

    A sensor spec of None means the agents have no such sensor (its reading is
    always None). The generator `rng` draws the schedules' phases and the
    biases at construction and all the noise afterwards.
    """

    def __init__(
        self,
        n_agents: int,
        frame: LocalFrame,
        rng: np.random.Generator,
        gps: GpsSpec | None = GpsSpec(),
        compass: CompassSpec | None = CompassSpec(),
        imu: ImuSpec | None = ImuSpec(),
        encoders: EncoderSpec | None = EncoderSpec(),
        ranges: RangeSpec | None = RangeSpec(),
        light: LightSpec | None = LightSpec(),
    ) -> None:
        _require(int(n_agents) == n_agents and n_agents >= 0, f"n_agents must be a count; got {n_agents!r}")
        self.n_agents = int(n_agents)
        self.frame = frame
        self.rng = rng
        self.gps, self.compass, self.imu = gps, compass, imu
        self.encoders, self.ranges, self.light = encoders, ranges, light
        n = self.n_agents
        self._last_t_s: float | None = None

        self._gps = _Channel(n, gps.rate_hz, gps.latency_s, rng) if gps is not None else None
        self._gps_error_m = np.zeros((n, 2))
        self._gps_error_t_s = np.full(n, np.nan)  # time of each agent's last error draw (NaN: none yet)
        self._common_error_m = np.zeros(2)
        self._common_error_t_s: float | None = None

        self._compass = _Channel(n, compass.rate_hz, compass.latency_s, rng) if compass is not None else None
        self.compass_bias_rad = (
            np.radians(compass.bias_std_deg) * rng.standard_normal(n) if compass is not None else np.zeros(n)
        )

        self._imu = _Channel(n, imu.rate_hz, imu.latency_s, rng) if imu is not None else None
        self.accel_bias_mps2 = (
            imu.accel_bias_std_mps2 * rng.standard_normal((n, 2)) if imu is not None else np.zeros((n, 2))
        )
        self.gyro_bias_radps = imu.gyro_bias_std_radps * rng.standard_normal(n) if imu is not None else np.zeros(n)

    # ------------------------------------------------------------ sampling

    def sample(
        self,
        t_s: float,
        position_m: ArrayLike,
        velocity_mps: ArrayLike,
        accel_mps2: ArrayLike,
        heading_rad: ArrayLike,
        yaw_rate_radps: ArrayLike,
        wheel_travel_m: ArrayLike | None = None,
        *,
        tilt: tuple[FloatArray, FloatArray, FloatArray] | None = None,
    ) -> SensorReadings:
        """Measure the truth at t_s (s) where a sensor's schedule says so, and return what is delivered at t_s.

        Truth, all world frame: position_m (N, 2), velocity_mps (N, 2), accel_mps2
        (N, 2), heading_rad (N,), yaw_rate_radps (N,), and wheel_travel_m (N, 2)
        cumulative (left, right) travel of each wheel (m) or None (no encoder readings).
        tilt: (roll (N,) rad right side down, pitch (N,) rad nose up, body rates (N, 3) rad/s FRD) of hulls
        rolled by waves (sitl.world.waves), or None for level hulls: the IMU then reads all three axes of a tilted
        body (gravity in x and y) and the compass reading carries the attitude, as an autopilot's ATTITUDE does.
        Call once per simulator step with non-decreasing t_s.
        """
        t = float(t_s)
        _require(math.isfinite(t), f"t_s must be finite; got {t_s!r}")
        _require(self._last_t_s is None or t >= self._last_t_s, f"t_s went back in time: {t!r} < {self._last_t_s!r}")
        self._last_t_s = t
        n = self.n_agents
        position = self._truth(position_m, "position_m", (n, 2))
        velocity = self._truth(velocity_mps, "velocity_mps", (n, 2))
        accel = self._truth(accel_mps2, "accel_mps2", (n, 2))
        heading = self._truth(heading_rad, "heading_rad", (n,))
        yaw_rate = self._truth(yaw_rate_radps, "yaw_rate_radps", (n,))

        if self._gps is not None:
            self._measure_gps(t, position, velocity)
        if self._compass is not None:
            self._measure_compass(t, heading, tilt)
        if self._imu is not None:
            self._measure_imu(t, accel, heading, yaw_rate, tilt)
        encoders = None
        if self.encoders is not None and wheel_travel_m is not None:
            encoders = self._measure_encoders(t, self._truth(wheel_travel_m, "wheel_travel_m", (n, 2)))
        return SensorReadings(
            gps=self._gps.deliver(t) if self._gps else None,
            compass=self._compass.deliver(t) if self._compass else None,
            imu=self._imu.deliver(t) if self._imu else None,
            encoders=encoders,
        )

    @staticmethod
    def _truth(value: ArrayLike, name: str, shape: tuple[int, ...]) -> FloatArray:
        array = np.asarray(value, dtype=float)
        _require(array.shape == shape, f"{name} must have shape {shape}; got {array.shape}")
        return array

    @staticmethod
    def _finite(agents: IntArray, *arrays: FloatArray) -> IntArray:
        """The agents whose rows of every array are finite."""
        if agents.size == 0:
            return agents
        for array in arrays:  # the usual case: all the truth is finite, nothing to drop
            if not np.isfinite(array).all():
                break
        else:
            return agents
        ok = None
        for array in arrays:
            finite = np.isfinite(array[agents])
            finite = finite.all(axis=1) if finite.ndim > 1 else finite
            ok = finite if ok is None else ok & finite
        return agents if ok.all() else agents[ok]

    def _measure_gps(self, t: float, position: FloatArray, velocity: FloatArray) -> None:
        spec = self.gps
        assert spec is not None and self._gps is not None
        agents = self._gps.due(t)
        if agents.size == 0 or spec.in_outage(t):
            return
        agents = self._finite(agents, position, velocity)
        if agents.size == 0:
            return
        k = agents.size
        rows = _rows(agents, self.n_agents)
        fresh = spec.noise_m * self.rng.standard_normal((k, 2))
        if spec.correlated > 0.0:
            # Exact discretization of the first-order Gauss-Markov process over the time since the last fix.
            elapsed = t - self._gps_error_t_s[agents]
            first = np.isnan(elapsed)
            rho = np.where(first, 0.0, np.exp(-np.where(first, 0.0, elapsed) / spec.correlated))[:, None]
            error = rho * self._gps_error_m[agents] + np.sqrt(1.0 - rho**2) * fresh
        else:
            error = fresh
        self._gps_error_m[rows] = error
        self._gps_error_t_s[rows] = t
        noisy = position[rows] + error + self._common_gps_error(t, spec)
        lat, lon = self.frame.to_geodetic(noisy[:, 0], noisy[:, 1])
        if spec.quantum_deg > 0.0:
            lat = np.round(lat / spec.quantum_deg) * spec.quantum_deg
            lon = np.round(lon / spec.quantum_deg) * spec.quantum_deg
        ground_velocity = velocity[rows] + spec.velocity_noise_mps * self.rng.standard_normal((k, 2))
        reported = spec.reported()
        accuracies = (None, None) if reported is None else (_filled(k, reported[0]), _filled(k, reported[1]))
        self._gps.push(t, GpsFix(agents, _filled(k, t), lat, lon, ground_velocity, *accuracies))

    def _common_gps_error(self, t: float, spec: GpsSpec) -> FloatArray:
        """(2,) the fleet-wide GPS error at t (s): exact Gauss-Markov steps between calls."""
        if spec.common_noise_m == 0.0:
            return np.zeros(2)
        if self._common_error_t_s is None:
            self._common_error_m = spec.common_noise_m * self.rng.standard_normal(2)
        elif t > self._common_error_t_s:
            rho = math.exp(-(t - self._common_error_t_s) / spec.common_time_constant_s)
            fresh = spec.common_noise_m * self.rng.standard_normal(2)
            self._common_error_m = rho * self._common_error_m + math.sqrt(1.0 - rho**2) * fresh
        self._common_error_t_s = t
        return self._common_error_m

    def _measure_compass(self, t: float, heading: FloatArray, tilt: tuple | None = None) -> None:
        spec = self.compass
        assert spec is not None and self._compass is not None
        agents = self._finite(self._compass.due(t), heading)
        if agents.size == 0:
            return
        rows = _rows(agents, self.n_agents)
        noise = np.radians(spec.noise_deg) * self.rng.standard_normal(agents.size)
        measured = wrap_angle(heading[rows] + self.compass_bias_rad[rows] + noise)
        times = _filled(agents.size, t)
        if tilt is None:
            self._compass.push(t, CompassReading(agents, times, measured))
            return
        # an autopilot's attitude: roll and pitch to a tenth of a degree or so, its gyro's rates
        roll, pitch, body = tilt
        error = np.radians(spec.tilt_noise_deg) * self.rng.standard_normal((agents.size, 2))
        self._compass.push(t, CompassReading(agents, times, measured, roll[rows] + error[:, 0],
                                             pitch[rows] + error[:, 1], body[rows].copy()))  # fmt: skip

    def _measure_imu(
        self, t: float, accel: FloatArray, heading: FloatArray, yaw_rate: FloatArray, tilt: tuple | None = None
    ) -> None:
        spec = self.imu
        assert spec is not None and self._imu is not None
        agents = self._finite(self._imu.due(t), accel, heading, yaw_rate)
        if agents.size == 0:
            return
        k = agents.size
        rows = _rows(agents, self.n_agents)
        body = world_to_body(accel[rows], heading[rows])
        rate = yaw_rate[rows]
        if tilt is not None:  # the tilted body's specific force and rates (x forward, y left, z up)
            force, rates = tilted_imu(body, tilt[0][rows], tilt[1][rows], tilt[2][rows])
            body, rate = force[:, :2], rates[:, 2]
        body += self.accel_bias_mps2[rows] + spec.accel_noise_mps2 * self.rng.standard_normal((k, 2))
        gyro = rate + self.gyro_bias_radps[rows] + spec.gyro_noise_radps * self.rng.standard_normal(k)
        if tilt is None:
            self._imu.push(t, ImuReading(agents, _filled(k, t), body, gyro))
            return
        z = force[:, 2] + spec.accel_noise_mps2 * self.rng.standard_normal(k)
        gyro_xy = rates[:, :2] + spec.gyro_noise_radps * self.rng.standard_normal((k, 2))
        self._imu.push(t, ImuReading(agents, _filled(k, t), body, gyro, z, gyro_xy))

    def _measure_encoders(self, t: float, travel: FloatArray) -> EncoderReading | None:
        assert self.encoders is not None
        agents = self._finite(np.arange(self.n_agents), travel)
        if agents.size == 0:
            return None
        ticks = encoder_ticks(travel[_rows(agents, self.n_agents)], self.encoders)
        return EncoderReading(agents, _filled(agents.size, t), ticks)

    # ------------------------------------------------------------ range finders and light sensors

    def noisy_ranges(self, offsets: ArrayLike, rng: np.random.Generator | None = None) -> FloatArray:
        """`noisy_ranges` with this suite's RangeSpec (an unchanged copy if None); rng defaults to the suite's."""
        if self.ranges is None:
            return np.array(offsets, dtype=float)
        return noisy_ranges(offsets, self.rng if rng is None else rng, self.ranges)

    def noisy_light(self, readings: ArrayLike, rng: np.random.Generator | None = None) -> FloatArray:
        """`noisy_light` with this suite's LightSpec (an unchanged copy if None); rng defaults to the suite's."""
        if self.light is None:
            return np.array(readings, dtype=float)
        return noisy_light(readings, self.rng if rng is None else rng, self.light)
