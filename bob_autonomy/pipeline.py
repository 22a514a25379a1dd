"""A vessel's own estimation and control: readings in, pose estimate and actuator commands out.

The same classes run one vessel in the `bob-autonomy` process and every vessel
of a lockstep simulation at once (rows are vessels; no row ever sees another's
data). Readings are the typed readings of `firmware_bridge` (whether decoded
from MAVLink or handed over by a simulator); commands are body-frame thrust
(buoys, N) or wheel speeds (eBots, m/s), which `firmware_bridge.commands`
turns into MAVLink.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from bob_autonomy.ekf import BuoyEkfBank, BuoyEkfParams, EbotEkfBank
from bob_autonomy.geodesy import LocalFrame
from bob_autonomy.mpc import BuoyMpc, DiffDriveMpc
from bob_autonomy.simple_estimator import AlphaBetaBuoyEstimator, OdometryEstimator, PoseEstimate
from bob_autonomy.velocity_control import BuoyModel, BuoyVelocityController, DiffDriveController
from firmware_bridge.decoder import WheelDistance
from firmware_bridge.readings import CompassReading, EncoderReading, GpsFix, ImuReading, SensorReadings

FloatArray = NDArray[np.float64]
ESTIMATORS = ("simple", "ekf")
CONTROLLERS = ("simple", "mpc")


def _check_choice(name: str, value: str, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ValueError(f"unknown {name} {value!r}; choose one of {', '.join(allowed)}")


def _flatten(readings: SensorReadings | Iterable[object]) -> list[object]:
    if isinstance(readings, SensorReadings):
        return [r for r in (readings.imu, readings.gps, readings.compass, readings.encoders) if r is not None]
    return list(readings)


class BuoyPipeline:
    """Estimator (alpha-beta or EKF) and velocity controller (proportional or MPC) of n buoys.

    max_thrust_n (n,): each vessel's thrust limit, N. dt_s: the control period, s (the MPC's step).
    mpc_time_budget_s: wall time after which a solve is discarded for the fallback (inf in simulated time).
    """

    def __init__(
        self,
        n: int,
        frame: LocalFrame,
        max_thrust_n: FloatArray,
        *,
        estimator: str = "simple",
        controller: str = "mpc",
        dt_s: float = 0.1,
        mpc_time_budget_s: float = 0.02,
        model: BuoyModel | None = None,
        on_ground: bool = False,
    ) -> None:
        _check_choice("estimator", estimator, ESTIMATORS)
        _check_choice("controller", controller, CONTROLLERS)
        self.n, self.frame = n, frame
        self.model = BuoyModel() if model is None else model
        self.on_ground = on_ground
        self.max_thrust_n = np.broadcast_to(np.asarray(max_thrust_n, dtype=float), (n,)).copy()
        self.use_ekf, self.use_mpc = estimator == "ekf", controller == "mpc"
        self.estimator = self._new_estimator()
        self.simple = BuoyVelocityController(model=self.model)
        self.mpcs = (
            [BuoyMpc(model=self.model, dt_s=dt_s, time_budget_s=mpc_time_budget_s) for _ in range(n)]
            if self.use_mpc
            else []
        )
        self.thrust_world_n = np.zeros((n, 2))  # last command, world frame (the EKF's known input)
        self.ignored = 0  # readings of kinds a buoy does not use (wheel travel, ...)
        self.last_fix_xy = np.full((n, 2), np.nan)  # the newest GPS fix of each vessel (local frame, m) and its time
        self.last_fix_t = np.full(n, -np.inf)
        self.resets = 0

    def _new_estimator(self) -> BuoyEkfBank | AlphaBetaBuoyEstimator:
        if not self.use_ekf:
            return AlphaBetaBuoyEstimator(self.n)
        params = BuoyEkfParams(model=self.model)
        if self.on_ground:
            # An omni rover on the ground: no water to drift in, and wheels that follow their commands rather
            # than a thrust against drag, so the drift states stay at zero and the drag balance is left out.
            params = replace(params, drift_psd=0.0, initial_drift_sigma_mps=1e-4, drag_balance_sigma_mps2=1e3)
        return BuoyEkfBank(self.n, params=params)

    def diverged(self, t_s: float, *, distance_m: float = 100.0, fix_age_s: float = 5.0) -> NDArray[np.bool_]:
        """(n,) whether each estimate has left the ground: not finite, or more than `distance_m` (plus what the
        vessel could travel at twice the model's top speed since the fix) from a GPS fix younger than `fix_age_s`."""
        e = self.estimate(t_s)
        bad = ~np.isfinite(e.position).all(axis=1) | ~np.isfinite(e.velocity).all(axis=1)
        age = t_s - self.last_fix_t
        fresh = age <= fix_age_s
        with np.errstate(invalid="ignore"):
            gap = np.hypot(*(e.position - self.last_fix_xy).T)
            top_speed = self.model_top_speed_mps()
            bad |= fresh & ~(gap <= distance_m + 2.0 * top_speed * np.maximum(age, 0.0))
        return bad

    def model_top_speed_mps(self) -> float:
        """Speed at which the model's drag equals full thrust, m/s."""
        m = self.model
        a, b, c = m.quadratic_drag_n_per_mps2, m.linear_drag_n_per_mps, -m.max_thrust_n
        return float((-b + np.sqrt(b * b - 4 * a * c)) / (2 * a)) if a > 0 else float(-c / b)

    def reset(self) -> None:
        """Start the estimator afresh (the next fixes set it again); for a vessel whose filter has diverged."""
        self.estimator = self._new_estimator()
        self.resets += 1

    @property
    def mpc_fallbacks(self) -> int:
        return sum(m.fallbacks for m in self.mpcs)

    def feed(self, readings: SensorReadings | Iterable[object]) -> None:
        """Fuse readings (any order; each carries its measurement time and vessel rows)."""
        for reading in _flatten(readings):
            if isinstance(reading, ImuReading):
                if self.use_ekf:  # the accelerometer drives the prediction; the known thrust makes drift observable
                    a = reading.agents
                    self.estimator.predict(a, reading.t_s, reading.accel_body_mps2, self.thrust_world_n[a])
                    self.estimator.update_gyro(a, reading.t_s, reading.gyro_z_radps)
            elif isinstance(reading, GpsFix):
                x, y = self.frame.to_local(reading.lat_deg, reading.lon_deg)
                xy = np.column_stack((x, y))
                self.last_fix_xy[reading.agents] = xy
                self.last_fix_t[reading.agents] = reading.t_s
                self.estimator.update_gps(reading.agents, reading.t_s, xy, reading.velocity_mps)
            elif isinstance(reading, CompassReading):
                _update_compass(self.estimator, reading, self.use_ekf)
            else:
                self.ignored += 1

    def estimate(self, t_s: float) -> PoseEstimate:
        return self.estimator.estimate(t_s)

    def drift(self) -> FloatArray:
        """(n, 2) estimated water drift, m/s (zero without the EKF, which is the only one to estimate it)."""
        return self.estimator.drift() if self.use_ekf else np.zeros((self.n, 2))

    def thrust(self, wish_mps: FloatArray, t_s: float, *, idle: bool = False) -> FloatArray:
        """Body-frame thrust (n, 2) N (x forward, y left) towards the wished velocities (n, 2) m/s.

        idle: before the mission starts the simple controller holds the buoys (the MPC is not warmed on zeros).
        """
        estimate = self.estimate(t_s)
        velocity, heading = estimate.velocity, estimate.heading
        if self.use_mpc and not idle:
            water = self.drift()
            results = [
                mpc.solve(wish_mps[k], velocity[k], water[k], heading[k], self.max_thrust_n[k])
                for k, mpc in enumerate(self.mpcs)
            ]
            self.thrust_world_n = np.array([r.thrust_world_n for r in results]).reshape(-1, 2)
            return np.array([r.thrust_body_n for r in results]).reshape(-1, 2)
        body = self.simple.thrust(wish_mps, velocity, heading, self.max_thrust_n)
        c, s = np.cos(np.nan_to_num(heading)), np.sin(np.nan_to_num(heading))
        self.thrust_world_n = np.column_stack((c * body[:, 0] - s * body[:, 1], s * body[:, 0] + c * body[:, 1]))
        return body


class EbotPipeline:
    """Dead reckoning (odometry or EKF) and wheel control (proportional or MPC) of n differential-drive robots.

    position_m (n, 2), heading_rad (n,): the known start poses (the paper's robots are told theirs).
    metres_per_tick: wheel travel per encoder tick, m (wheel travel in metres is converted back to ticks).
    """

    def __init__(
        self,
        position_m: FloatArray,
        heading_rad: FloatArray,
        wheel_base_m: float,
        max_wheel_speed_mps: float,
        metres_per_tick: float,
        *,
        estimator: str = "simple",
        controller: str = "mpc",
        dt_s: float = 0.1,
        mpc_time_budget_s: float = 0.02,
        frame: LocalFrame | None = None,
        gps_sigma_m: float = 2.0,
    ) -> None:
        _check_choice("estimator", estimator, ESTIMATORS)
        _check_choice("controller", controller, CONTROLLERS)
        self.frame, self.gps_sigma_m = frame, float(gps_sigma_m)
        position = np.asarray(position_m, dtype=float).reshape(-1, 2)
        self.n = position.shape[0]
        self.use_ekf, self.use_mpc = estimator == "ekf", controller == "mpc"
        self.metres_per_tick = metres_per_tick
        estimator_class = EbotEkfBank if self.use_ekf else OdometryEstimator
        self.estimator = estimator_class(position, heading_rad, wheel_base_m, metres_per_tick)
        self.simple = DiffDriveController(wheel_base_m, max_wheel_speed_mps)
        self.mpcs = (
            [
                DiffDriveMpc(wheel_base_m, max_wheel_speed_mps, dt_s=dt_s, time_budget_s=mpc_time_budget_s)
                for _ in range(self.n)
            ]
            if self.use_mpc
            else []
        )
        self.ignored = 0

    @property
    def mpc_fallbacks(self) -> int:
        return sum(m.fallbacks for m in self.mpcs)

    def feed(self, readings: SensorReadings | Iterable[object]) -> None:
        """Fuse encoder ticks (or wheel travel, m) and compass readings; GPS fixes too when the pipeline has a
        local frame and the EKF (a rover outdoors: without wheel encoders its estimate would stay at the start)."""
        for reading in _flatten(readings):
            if isinstance(reading, GpsFix) and self.frame is not None and self.use_ekf:
                x, y = self.frame.to_local(reading.lat_deg, reading.lon_deg)
                sigma = np.full(len(reading.agents), self.gps_sigma_m)
                self.estimator.update_position(reading.agents, reading.t_s, np.column_stack((x, y)), sigma)
                continue
            if isinstance(reading, EncoderReading):
                self.estimator.update_encoders(reading.agents, reading.t_s, reading.ticks)
            elif isinstance(reading, WheelDistance):  # metres, as ArduPilot reports wheel travel
                ticks = np.rint(np.asarray(reading.distance_m) / self.metres_per_tick).astype(np.int64)
                self.estimator.update_encoders(reading.agents, reading.t_s, ticks)
            elif isinstance(reading, CompassReading):
                _update_compass(self.estimator, reading, self.use_ekf)
            else:
                self.ignored += 1

    def estimate(self, t_s: float) -> PoseEstimate:
        return self.estimator.estimate(t_s)

    def wheels(
        self, wish_mps: FloatArray, wish_heading_rad: FloatArray, t_s: float, *, idle: bool = False
    ) -> FloatArray:
        """Wheel speeds (n, 2) m/s (left, right) towards the wished velocities (n, 2) m/s and headings (n,) rad."""
        heading = self.estimate(t_s).heading
        simple = self.simple.wheels(wish_mps, wish_heading_rad, heading)
        if not self.use_mpc or idle:
            return simple
        # The MPC tracks a velocity vector; turning in place to a wished heading stays the simple controller's.
        turning = ~np.isnan(wish_heading_rad) & (np.hypot(wish_mps[:, 0], wish_mps[:, 1]) < 1e-6)
        wheels = np.array([mpc.solve(wish_mps[k], heading[k]).wheels_mps for k, mpc in enumerate(self.mpcs)])
        return np.where(turning[:, None], simple, wheels.reshape(-1, 2))


def _update_compass(estimator, reading: CompassReading, timed: bool) -> None:
    """Compass headings into an estimator (the EKFs take their measurement times)."""
    if timed:
        estimator.update_compass(reading.agents, reading.heading_rad, reading.t_s)
    else:
        estimator.update_compass(reading.agents, reading.heading_rad)
