"""A vessel's own estimation and control: readings in, pose estimate and actuator commands out.

The same classes run one vessel in the `bob-autonomy` process and every vessel
of a lockstep simulation at once (rows are vessels; no row ever sees another's
data). Readings are the typed readings of `firmware_bridge` (whether decoded
from MAVLink or handed over by a simulator); commands are body-frame thrust
(buoys, N) or wheel speeds (eBots, m/s), which `firmware_bridge.commands`
turns into MAVLink.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from bob_autonomy.control.buoy_mpc_batch import BuoyMpcBatch
from bob_autonomy.control.ebot_mpc import DiffDriveMpc
from bob_autonomy.control.motorboat_control import MotorboatCommand, MotorboatController, MotorboatModel, MotorboatMpc
from bob_autonomy.control.motorboat_mpc_batch import MotorboatMpcBatch
from bob_autonomy.control.mpc import BuoyMpc
from bob_autonomy.control.velocity_control import BuoyModel, BuoyVelocityController, DiffDriveController
from bob_autonomy.core.arrays import wrap
from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.estimation import BuoyEkfBank, BuoyEkfParams, EbotEkfBank
from bob_autonomy.estimation.antenna import antenna_offsets
from bob_autonomy.estimation.gps_accuracy import AccuracyEnvelope
from bob_autonomy.estimation.simple_estimator import AlphaBetaBuoyEstimator, OdometryEstimator, PoseEstimate
from bob_autonomy.estimation.tilt import TiltTracker
from bob_autonomy.onboard.imu_repeats import ImuRepeats
from firmware_bridge.decoder import WheelDistance
from firmware_bridge.readings import CompassReading, EncoderReading, GpsFix, ImuReading, SensorReadings

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
logger = logging.getLogger(__name__)
YAW_ACCEL_PSD = 2.0**2  # rad^2/s^3: the motorboat EKF's yaw-rate random walk (the gyro pins the rate)
ESTIMATORS = ("simple", "ekf")
CONTROLLERS = ("simple", "mpc")


def _check_choice(name: str, value: str, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ValueError(f"unknown {name} {value!r}; choose one of {', '.join(allowed)}")


def _flatten(readings: SensorReadings | Iterable[object]) -> list[object]:
    """The readings of a batch in order of measurement time (stable: readings of one time keep their order).

    The EKFs fuse a reading older than their clock by replaying everything after it, which gives the in-order
    result at the cost of a re-run; a GPS fix that comes with the IMU reading of a later time (its latency) is
    therefore fused first, and nothing needs replaying."""
    if isinstance(readings, SensorReadings):
        batch = [r for r in (readings.imu, readings.gps, readings.compass, readings.encoders) if r is not None]
    else:
        batch = list(readings)
    if len(batch) < 2:
        return batch
    keys, latest = [], -math.inf
    for reading in batch:  # a reading without a finite time stays after those before it
        own = _latest_time(reading)
        latest = latest if math.isnan(own) else max(latest, own)
        keys.append(latest if math.isnan(own) else own)
    order = sorted(range(len(batch)), key=keys.__getitem__)
    return [batch[k] for k in order]


def _latest_time(reading: object) -> float:
    """The latest finite measurement time of a reading's rows, s (NaN without one)."""
    times = np.asarray(getattr(reading, "t_s", np.nan), dtype=float)
    finite = times[np.isfinite(times)]
    return float(finite.max()) if finite.size else math.nan


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
        # In simulated time (no budget) a fleet's solves are made together, with the same results.
        self.mpc_batch = BuoyMpcBatch(self.mpcs) if BuoyMpcBatch.fits(self.mpcs) else None
        self.thrust_world_n = np.zeros((n, 2))  # last command, world frame (the EKF's known input)
        self.ignored = 0  # readings of kinds a buoy does not use (wheel travel, ...)
        self.last_fix_xy = np.full((n, 2), np.nan)  # the newest GPS fix of each vessel (local frame, m) and its time
        self.last_fix_t = np.full(n, -np.inf)
        self.resets = 0
        self.tilt = TiltTracker(n)  # the hulls' attitude (ATTITUDE), to level their IMU readings
        # Each GPS antenna's offset from the hull's reference point (the IMU), m, x forward, y right, z down
        # (ArduPilot's GPS1_POS_X/Y/Z less INS_POS1_X/Y/Z); fixes are moved back to the reference point by it.
        self.antenna_frd_m = np.zeros((n, 3))
        self.antenna_unplaced = 0  # fixes from an offset antenna that came with no attitude to place them by
        self.gps_accuracy = AccuracyEnvelope(n)  # the receivers' reported accuracies, held and let decay (EKF3)
        self.imu_repeats = ImuRepeats(n)  # one IMU sample sent twice (RAW_IMU and SCALED_IMU) is fused once

    def limit_throttle(self, fraction: float) -> None:
        """Plan with at most `fraction` of full thrust from now on (the autopilot's MOT_THR_MAX was changed while
        driving): the limit is an input of every solve, so the estimator and the controllers go on as they are."""
        self.max_thrust_n[:] = self.model.max_thrust_n * float(fraction)

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
        """Fuse readings (any order; each carries its measurement time and vessel rows). IMU readings are levelled
        with the hulls' attitude (`bob_autonomy.estimation.tilt`) from the compass readings that carry one."""
        batch = [r if not isinstance(r, ImuReading) else self.imu_repeats.fresh(r) for r in _flatten(readings)]
        for reading in self._levelled([r for r in batch if r is not None]):  # in time order (no needless replay)
            self._fuse(reading)

    def _fuse(self, reading: object) -> None:
        """One reading (levelled) into the estimator."""
        if isinstance(reading, ImuReading):
            if self.use_ekf:  # the accelerometer drives the prediction; the known thrust makes drift observable
                a = reading.agents
                self.estimator.predict(a, reading.t_s, reading.accel_body_mps2, self.thrust_world_n[a])
                self.estimator.update_gyro(a, reading.t_s, reading.gyro_z_radps)
        elif isinstance(reading, GpsFix):
            x, y = self.frame.to_local(reading.lat_deg, reading.lon_deg)
            xy, velocity = self._at_reference_point(reading, np.column_stack((x, y)))
            self.last_fix_xy[reading.agents] = xy
            self.last_fix_t[reading.agents] = reading.t_s
            if self.use_ekf:
                accuracy = self.gps_accuracy.apply(
                    reading.agents, reading.t_s, reading.accuracy_m, reading.speed_accuracy_mps
                )
                self.estimator.update_gps(reading.agents, reading.t_s, xy, velocity, *accuracy)
            else:
                self.estimator.update_gps(reading.agents, reading.t_s, xy, velocity)
        elif isinstance(reading, CompassReading):
            _update_compass(self.estimator, reading, self.use_ekf)
        else:
            self.ignored += 1

    def _at_reference_point(self, fix: GpsFix, xy: FloatArray) -> tuple[FloatArray, FloatArray | None]:
        """A fix's positions (k, 2) m and velocities moved from the antenna to the hull's reference point, where
        `antenna_frd_m` is set, with the attitude at the fix's time (`bob_autonomy.estimation.antenna`)."""
        rows, velocity = fix.agents, fix.velocity_mps
        offset = self.antenna_frd_m[rows]
        if not offset.any():
            return xy, velocity
        attitude, known = self.tilt.attitude_at(rows, fix.t_s)
        placed = known & offset.any(axis=1)
        self.antenna_unplaced += int(np.count_nonzero(~known & offset.any(axis=1)))
        if not placed.any():
            return xy, velocity
        k = np.flatnonzero(placed)
        moved, moving = antenna_offsets(attitude[k], self.tilt.body_rates[rows[k]], offset[k])
        xy = xy.copy()
        xy[k] -= moved
        if velocity is not None:
            velocity = velocity.copy()
            velocity[k] -= moving
        return xy, velocity

    def _levelled(self, batch: list[object]) -> list[object]:
        """The batch with its IMU readings levelled, after noting the attitude of each compass reading in it (an
        attitude is carried to the IMU reading's time, before or after it: `TiltTracker`)."""
        for reading in batch:
            if isinstance(reading, CompassReading):
                self.tilt.note(reading)
        return [self.tilt.level(r) if isinstance(r, ImuReading) else r for r in batch]

    def estimate(self, t_s: float) -> PoseEstimate:
        return self.estimator.estimate(t_s)

    def position_known(self, t_s: float) -> NDArray[np.bool_]:
        """(n,) whether each estimate holds a position: finite, and with the EKF set by a fix (an EKF that has
        fused none says (0, 0), which is no position: a vessel stepped on it would broadcast it and steer by it)."""
        known = np.isfinite(self.estimate(t_s).position).all(axis=1)
        return known & self.estimator.pos_init if self.use_ekf else known

    def heading_known(self, t_s: float) -> NDArray[np.bool_]:
        """(n,) whether each estimate holds a heading: finite, and with the EKF set by a compass reading (before
        one, the EKF says 0 rad: thrust turned into the body frame by it would push the wrong way)."""
        known = np.isfinite(self.estimate(t_s).heading)
        return known & self.estimator.heading_init if self.use_ekf else known

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
            if self.mpc_batch is not None:
                body, self.thrust_world_n = self.mpc_batch.thrust(wish_mps, velocity, water, heading, self.max_thrust_n)
                return body
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


ODOMETRY_SILENT_S = 1.0  # no wheel reading for this long: the wheels say nothing of the motion
FIX_VELOCITY_GAIN = 0.5  # share of a new fix-to-fix velocity taken into the smoothed one


class EbotPipeline:
    """Dead reckoning (odometry or EKF) and wheel control (proportional or MPC) of n differential-drive robots.

    position_m (n, 2), heading_rad (n,): the known start poses (the paper's robots are told theirs).
    metres_per_tick: wheel travel per encoder tick, m (wheel travel in metres is converted back to ticks).
    throttle_slew_per_s: the autopilot's throttle slew (MOT_SLEWRATE / 100, per s; 0: none), which the MPCs plan with.
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
        throttle_slew_per_s: float = 0.0,
    ) -> None:
        _check_choice("estimator", estimator, ESTIMATORS)
        _check_choice("controller", controller, CONTROLLERS)
        self.frame, self.gps_sigma_m = frame, float(gps_sigma_m)
        position = np.asarray(position_m, dtype=float).reshape(-1, 2)
        self.n = position.shape[0]
        self.max_wheel_speed_mps = float(max_wheel_speed_mps)
        self.throttle_slew_per_s = float(throttle_slew_per_s)
        self.last_odometry_t = np.full(self.n, -np.inf)  # newest wheel reading and GPS fix of each robot, s
        self.last_fix_t = np.full(self.n, np.nan)
        self.last_fix_xy = np.zeros((self.n, 2))
        self.fix_velocity = np.zeros((self.n, 2))  # velocity seen in the fixes, m/s (robots without encoders)
        self.use_ekf, self.use_mpc = estimator == "ekf", controller == "mpc"
        self.metres_per_tick = metres_per_tick
        estimator_class = EbotEkfBank if self.use_ekf else OdometryEstimator
        self.estimator = estimator_class(position, heading_rad, wheel_base_m, metres_per_tick)
        self.simple = DiffDriveController(wheel_base_m, max_wheel_speed_mps)
        self.mpcs = (
            [
                DiffDriveMpc(
                    wheel_base_m,
                    max_wheel_speed_mps,
                    dt_s=dt_s,
                    time_budget_s=mpc_time_budget_s,
                    throttle_slew_per_s=throttle_slew_per_s,
                )
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
                self._predict_without_odometry(reading.agents, reading.t_s, np.column_stack((x, y)))
                t_s, xy = self._at_filter_time(reading.agents, reading.t_s, np.column_stack((x, y)))
                sigma = np.full(len(reading.agents), self.gps_sigma_m)
                if reading.accuracy_m is not None:  # the receiver's own accuracy where it is worse (NaN: none)
                    sigma = np.fmax(sigma, reading.accuracy_m)
                self.estimator.update_position(reading.agents, t_s, xy, sigma)
                continue
            if isinstance(reading, (EncoderReading, WheelDistance)):
                self.last_odometry_t[reading.agents] = reading.t_s
            if isinstance(reading, EncoderReading):
                self.estimator.update_encoders(reading.agents, reading.t_s, reading.ticks)
            elif isinstance(reading, WheelDistance):  # metres, as ArduPilot reports wheel travel
                ticks = np.rint(np.asarray(reading.distance_m) / self.metres_per_tick).astype(np.int64)
                self.estimator.update_encoders(reading.agents, reading.t_s, ticks)
            elif isinstance(reading, CompassReading):
                _update_compass(self.estimator, reading, self.use_ekf)
            else:
                self.ignored += 1

    def _predict_without_odometry(self, agents: IntArray, t_s: FloatArray, xy: FloatArray) -> None:
        """When a robot's wheels say nothing (no encoders), the motion since the last fix comes from the fixes:
        the position is carried on at the velocity of the recent fixes (smoothed, FIX_VELOCITY_GAIN) and its
        variance grows by (0.5 v_max dt)^2, so a moving robot is followed without lag rather than gated."""
        times = np.broadcast_to(np.asarray(t_s, dtype=float), np.shape(agents))
        for row, (i, t) in enumerate(zip(np.asarray(agents), times, strict=True)):
            last = self.last_fix_t[i]
            dt = t - last if np.isfinite(last) else 0.0
            if dt > 0 and t - self.last_odometry_t[i] > ODOMETRY_SILENT_S:
                seen = (xy[row] - self.last_fix_xy[i]) / dt
                self.fix_velocity[i] += FIX_VELOCITY_GAIN * (seen - self.fix_velocity[i])
                growth = (0.5 * self.max_wheel_speed_mps * dt) ** 2
                self.estimator.carry(i, self.fix_velocity[i] * dt, growth, self.fix_velocity[i])
            if dt >= 0:
                self.last_fix_t[i], self.last_fix_xy[i] = t, xy[row]

    def _at_filter_time(self, agents: IntArray, t_s: FloatArray, xy: FloatArray) -> tuple[FloatArray, FloatArray]:
        """A robot without odometry takes a fix dated before its filter's time (ArduPilot's stamp of when it read
        the fix: firmware_bridge.autopilot_clock; the compass readings since were fused at their arrival) at the
        filter's time, carried there at the fixes' velocity: xy + v (t_filter - t_fix). Fused at its own time
        by replay instead, it would undo the carry between fixes (`_predict_without_odometry`), which is no
        reading the replay knows, and the estimate would fall behind the robot."""
        times = np.array(np.broadcast_to(np.asarray(t_s, dtype=float), np.shape(agents)))
        filter_t = self.estimator.t[agents]
        late = (times < filter_t) & (times - self.last_odometry_t[agents] > ODOMETRY_SILENT_S)
        if not late.any():
            return times, xy
        xy = xy.copy()
        xy[late] += self.fix_velocity[agents[late]] * (filter_t[late] - times[late])[:, None]
        times[late] = filter_t[late]
        return times, xy

    def estimate(self, t_s: float) -> PoseEstimate:
        return self.estimator.estimate(t_s)

    def position_known(self, t_s: float) -> NDArray[np.bool_]:
        """(n,) whether each estimate holds a position (an eBot's filter starts from its known place: finite)."""
        return np.isfinite(self.estimate(t_s).position).all(axis=1)

    def heading_known(self, t_s: float) -> NDArray[np.bool_]:
        """(n,) whether each estimate holds a heading (an eBot starts from its known heading: finite)."""
        return np.isfinite(self.estimate(t_s).heading)

    def wheels(
        self, wish_mps: FloatArray, wish_heading_rad: FloatArray, t_s: float, *, idle: bool = False
    ) -> FloatArray:
        """Wheel speeds (n, 2) m/s (left, right) towards the wished velocities (n, 2) m/s and headings (n,) rad."""
        heading = self.estimate(t_s).heading
        simple = self.simple.wheels(wish_mps, wish_heading_rad, heading)
        if not self.use_mpc or idle:
            return simple
        # The MPC tracks a velocity vector and may back up to do it. A robot wished a heading must face it (heading
        # consensus broadcasts the body's heading: backing up would show its neighbours the opposite one), so it
        # turns in place with the simple controller while it stands or is more than 90 deg off the wished heading,
        # and the MPC then drives it forward only.
        wished = ~np.isnan(wish_heading_rad)
        off = np.abs(wrap(np.where(wished, wish_heading_rad, heading) - heading))
        turning = wished & ((np.hypot(wish_mps[:, 0], wish_mps[:, 1]) < 1e-6) | (off > 0.5 * np.pi))
        wheels = np.array(
            [
                mpc.solve(wish_mps[k], heading[k], forward_only=bool(wished[k])).wheels_mps
                for k, mpc in enumerate(self.mpcs)
            ]
        )
        if self.throttle_slew_per_s > 0.0:
            for k in np.flatnonzero(turning):  # sent the simple command: the autopilot's slewed throttle follows it
                self.mpcs[k].sent(simple[k])
        return np.where(turning[:, None], simple, wheels.reshape(-1, 2))


def _update_compass(estimator, reading: CompassReading, timed: bool) -> None:
    """Compass headings into an estimator (the EKFs take their measurement times)."""
    if timed:
        estimator.update_compass(reading.agents, reading.heading_rad, reading.t_s)
    else:
        estimator.update_compass(reading.agents, reading.heading_rad)


class MotorboatPipeline(BuoyPipeline):
    """Estimator (alpha-beta or EKF) and steering + throttle control (proportional or MPC) of n motorboats.

    A motorboat is estimated as a buoy is (GPS, compass, gyro; the EKF's drift state is the water's), with the
    surge model of its MotorboatModel as the EKF's drag model (the thrust acts along the keel; the EKF's drag
    balance is isotropic, so its sigma is widened to `drag_balance_sigma_mps2` for the sway it does not know).
    use_accelerometer: False (default): the EKF predicts with that model and the thrust, not the accelerometer. A
    hull that pitches and rolls in waves puts gravity into a planar accelerometer (0.17 m/s^2 per degree;
    ArduPilot's SITL motorboat has waves on, Tools/autotest/default_params/motorboat.parm SIM_WAVE_ENABLE 1).
    The readings are levelled with ATTITUDE's roll and pitch (`bob_autonomy.estimation.tilt`), the gyro too, but
    the accelerometer stays out by default: GPS velocity at 10 Hz does well enough without it (with it,
    leader-follower-motorboats' position and heading errors moved by under 0.01 m and 0.001 deg RMS, seeds 1-3
    over 150 s, 2026-11-28: their error is the fleet's common GPS error).
    The controller is `bob_autonomy.control.motorboat_control`. Commands are (throttle, steering) per boat, each in
    [-1, 1], as `AutopilotSession.override` sends them. `thrust()` returns these commands too, so that the vessel
    loop drives every pipeline that estimates like a buoy alike.

    models: one MotorboatModel per boat (or one for all); the EKF uses the first one's surge model.
    max_throttle (n,): the throttle each boat may use (a weak battery: below 1). Other arguments as BuoyPipeline.
    """

    def __init__(
        self,
        n: int,
        frame: LocalFrame,
        models: MotorboatModel | Sequence[MotorboatModel] | None = None,
        max_throttle: FloatArray | float = 1.0,
        *,
        estimator: str = "simple",
        controller: str = "mpc",
        dt_s: float = 0.1,
        mpc_time_budget_s: float = 0.02,
        drag_balance_sigma_mps2: float = 0.3,
        use_accelerometer: bool = False,
    ) -> None:
        _check_choice("controller", controller, CONTROLLERS)
        each = [models or MotorboatModel()] * n if not isinstance(models, Sequence) else list(models)
        if len(each) != n:
            raise ValueError(f"{len(each)} motorboat models for {n} boats")
        self.models = each
        first = each[0] if each else MotorboatModel()
        drag = (first.linear_drag_n_per_mps, first.quadratic_drag_n_per_mps2)
        surge = BuoyModel(first.mass_kg, *drag, first.max_thrust_n)
        self.drag_balance_sigma_mps2 = drag_balance_sigma_mps2
        self.use_accelerometer = use_accelerometer
        super().__init__(n, frame, np.ones(n), estimator=estimator, controller="simple", dt_s=dt_s, model=surge)
        self.use_mpc = controller == "mpc"
        self.max_throttle = np.broadcast_to(np.asarray(max_throttle, dtype=float), (n,)).copy()
        self.max_thrust_n = np.array([m.max_thrust_n for m in each]) * self.max_throttle
        self.controllers = [MotorboatController(m) for m in each]
        step = max(dt_s, 0.5)  # the MPC plans in steps of at least 0.5 s (6 s ahead), called every dt_s
        budget = mpc_time_budget_s
        mpc = {"step_s": step, "time_budget_s": budget, "call_period_s": dt_s}
        self.mpcs = [MotorboatMpc(m, **mpc) for m in each] if self.use_mpc else []
        # In simulated time (no budget) a fleet's solves are made together, with the same results.
        self.motorboat_batch = MotorboatMpcBatch(self.mpcs) if MotorboatMpcBatch.fits(self.mpcs) else None
        self.last_commands: list[MotorboatCommand | None] = [None] * n
        self._heading_t = np.full(n, np.nan)  # for the yaw rate of the simple estimator (heading differences)
        self._heading = np.full(n, np.nan)
        self._yaw_rate = np.zeros(n)
        self.sideways_wishes = 0  # wishes for a heading the velocity does not go along (module: `check_wish`)
        self._sideways_told = np.zeros(n, dtype=bool)

    def limit_throttle(self, fraction: float) -> None:
        """Plan with at most `fraction` of full throttle from now on (MOT_THR_MAX changed while driving), every boat."""
        self.max_throttle[:] = float(fraction)
        self.max_thrust_n = np.array([m.max_thrust_n for m in self.models]) * self.max_throttle

    def check_wish(self, wish_mps: FloatArray, wish_heading_rad: FloatArray, *, tolerance_rad: float = 0.8) -> int:
        """Count (and say once per boat, on the log) the wishes a motorboat cannot follow: a heading to hold while
        still (turning in place) or while moving in another direction (moving sideways). A motorboat goes where
        it points: it follows the velocity and the heading is dropped, never silently. Returns how many now."""
        heading = np.asarray(wish_heading_rad, dtype=float).reshape(self.n)
        wish = np.nan_to_num(np.asarray(wish_mps, dtype=float).reshape(self.n, 2))
        speed = np.hypot(wish[:, 0], wish[:, 1])
        course = np.arctan2(wish[:, 1], wish[:, 0])
        off = np.abs(np.remainder(heading - course + np.pi, 2 * np.pi) - np.pi)
        bad = np.isfinite(heading) & ((speed < 0.05) | (off > tolerance_rad))
        for k in np.flatnonzero(bad & ~self._sideways_told):
            self._sideways_told[k] = True
            logger.warning(
                "motorboat %d: the behaviour wishes heading %.0f deg while moving at %.2f m/s towards %.0f deg; a "
                "motorboat cannot turn in place or move sideways: it follows the velocity, the heading is dropped",
                k, np.degrees(heading[k]), speed[k], np.degrees(course[k]),
            )  # fmt: skip
        self.sideways_wishes += int(np.count_nonzero(bad))
        return int(np.count_nonzero(bad))

    def _new_estimator(self) -> BuoyEkfBank | AlphaBetaBuoyEstimator:
        if not self.use_ekf:
            return AlphaBetaBuoyEstimator(self.n)
        # A motorboat's yaw rate changes within a fraction of a second when it steers (a buoy's hardly at all;
        # ArduPilot's SITL motorboat turns at once, up to speed / 0.9 m): a yaw-rate random walk of
        # YAW_ACCEL_PSD lets the gyro and compass follow it instead of being gated.
        params = BuoyEkfParams(
            model=self.model, drag_balance_sigma_mps2=self.drag_balance_sigma_mps2, yaw_accel_psd=YAW_ACCEL_PSD
        )
        return BuoyEkfBank(self.n, params=params)

    def _fuse(self, reading: object) -> None:
        """As a buoy does; without `use_accelerometer` an IMU reading predicts with the thrust model (no
        accelerometer) and gives its gyro."""
        if isinstance(reading, ImuReading) and self.use_ekf and not self.use_accelerometer:
            a = reading.agents
            self.estimator.predict(a, reading.t_s, None, self.thrust_world_n[a])
            self.estimator.update_gyro(a, reading.t_s, reading.gyro_z_radps)
        else:
            super()._fuse(reading)

    def yaw_rate(self, t_s: float) -> FloatArray:
        """(n,) yaw rate, rad/s: the EKF's, or the filtered heading differences of the simple estimator."""
        if self.use_ekf:
            return np.nan_to_num(self.estimator.x[:, 5].copy())
        heading = self.estimate(t_s).heading
        dt = t_s - self._heading_t
        fresh = np.isfinite(heading) & np.isfinite(self._heading) & (dt > 1e-6)
        with np.errstate(invalid="ignore", divide="ignore"):
            rate = np.where(fresh, np.remainder(heading - self._heading + np.pi, 2 * np.pi) - np.pi, 0.0) / dt
        self._yaw_rate = np.where(fresh, 0.5 * self._yaw_rate + 0.5 * np.nan_to_num(rate), self._yaw_rate)
        self._heading, self._heading_t = heading.copy(), np.full(self.n, float(t_s))
        return self._yaw_rate.copy()

    def commands(self, wish_mps: FloatArray, t_s: float, *, idle: bool = False) -> FloatArray:
        """(n, 2) throttle and steering (each in [-1, 1]; steering > 0 turns to starboard) towards the wished
        velocities (n, 2) m/s over ground. idle: before the mission starts every boat is left at neutral."""
        estimate = self.estimate(t_s)
        rate = self.yaw_rate(t_s)
        out = np.zeros((self.n, 2))
        if idle:
            self.thrust_world_n = np.zeros((self.n, 2))
            return out
        water = self.drift()
        if self.motorboat_batch is not None:
            commands = self.motorboat_batch.solve(
                wish_mps, estimate.velocity, water, estimate.heading, rate, self.max_throttle, t_s
            )
        else:
            commands = []
            for k in range(self.n):
                args = (wish_mps[k], estimate.velocity[k], water[k], estimate.heading[k], rate[k])
                if self.use_mpc:
                    commands.append(self.mpcs[k].solve(*args, max_throttle=self.max_throttle[k], t_s=t_s))
                else:
                    commands.append(self.controllers[k].command(*args, limit=self.max_throttle[k], t_s=t_s))
        for k, cmd in enumerate(commands):
            self.last_commands[k] = cmd
            out[k] = cmd.throttle, cmd.steering
        heading = np.nan_to_num(estimate.heading)
        force = np.array([m.fraction_of(t) * m.max_thrust_n for m, t in zip(self.models, out[:, 0], strict=True)])
        self.thrust_world_n = force[:, None] * np.column_stack((np.cos(heading), np.sin(heading)))
        return out

    def thrust(self, wish_mps: FloatArray, t_s: float, *, idle: bool = False) -> FloatArray:
        """The motorboat commands (throttle, steering), as `commands`: what the vessel loop asks every pipeline
        that estimates like a buoy for."""
        return self.commands(wish_mps, t_s, idle=idle)
