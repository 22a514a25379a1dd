"""bob_autonomy/estimation/: the buoy and eBot EKFs on filterpy.

The truth is simulated here with simple kinematics, independent of the filter:
a buoy of mass 35 kg (with added mass) pushed by a known, slowly turning thrust
against the nominal water drag (5 w + 40 |w| w N, w the velocity through the
water) in a constant 0.15 m/s current, its heading wandering sinusoidally.
Sensors: GPS 5 Hz (2 m per axis, ground velocity 0.1 m/s), compass 10 Hz
(2 deg), IMU 50 Hz (accelerometer in the body frame, 0.02 m/s^2; gyro 0.005
rad/s). Variants: an accelerometer bias, a nozzle that turns towards each
(held) command at a slew limit instead of the thrust following the command at
once, a current that changes. Every run is seeded. Frames: x east, y north;
heading from east, CCW. The batched filter equations are also checked against
filterpy's ExtendedKalmanFilter directly.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter

from bob_autonomy.estimation import (
    BuoyEkf,
    BuoyEkfBank,
    BuoyEkfParams,
    EbotEkf,
    EbotEkfParams,
    kalman_predict_rows,
    kalman_update_rows,
    wrap_angle,
)

DT_S = 0.02  # IMU period (50 Hz); compass every 5th step (10 Hz), GPS every 10th (5 Hz)
MASS_KG, C1, C2 = 35.0, 5.0, 40.0  # the nominal buoy (velocity_control.BuoyModel)
CURRENT_MPS = 0.15 * np.array([math.cos(math.radians(30.0)), math.sin(math.radians(30.0))])
GPS_SIGMA_M, GPS_VEL_SIGMA_MPS = 2.0, 0.1
COMPASS_SIGMA_RAD = math.radians(2.0)
ACCEL_SIGMA_MPS2, GYRO_SIGMA_RADPS = 0.02, 0.005


def thrust_at(t: float) -> np.ndarray:
    """World-frame thrust command, N: 12 N turning once every 90 s (about 0.49 m/s through the water)."""
    angle = 2.0 * math.pi * t / 90.0
    return 12.0 * np.array([math.cos(angle), math.sin(angle)])


def heading_at(t: float) -> tuple[float, float]:
    """(heading, yaw rate) of the wandering hull."""
    w = 2.0 * math.pi / 50.0
    return 0.4 + 0.8 * math.sin(w * t), 0.8 * w * math.cos(w * t)


def accel_world(vx: float, vy: float, thrust: np.ndarray, current: np.ndarray) -> tuple[float, float]:
    """Truth: (T - (c1 + c2 |w|) w) / M, w = v - current."""
    wx, wy = vx - current[0], vy - current[1]
    drag = C1 + C2 * math.hypot(wx, wy)
    return (thrust[0] - drag * wx) / MASS_KG, (thrust[1] - drag * wy) / MASS_KG


def steady_current(t: float) -> np.ndarray:
    return CURRENT_MPS


def body(vector: np.ndarray, heading: float) -> np.ndarray:
    c, s = math.cos(heading), math.sin(heading)
    return np.array([c * vector[0] + s * vector[1], -s * vector[0] + c * vector[1]])


@dataclass
class Run:
    """What a simulated run recorded, one row per 50 Hz step (t, truth, estimate, covariance checks)."""

    t: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    heading: np.ndarray
    est_position: np.ndarray
    est_heading: np.ndarray
    est_drift: np.ndarray
    pos_trace: np.ndarray
    min_eig: np.ndarray
    asymmetry: np.ndarray
    gps_t: np.ndarray
    gps_error: np.ndarray  # raw fix minus truth (k, 2)
    gps_est_error: np.ndarray  # estimate right after the fix minus truth (k, 2)
    outcomes: dict = field(default_factory=dict)  # t -> outcome of the GPS fix at t


def simulate(
    duration_s: float,
    seed: int,
    *,
    accel: bool = True,
    thrust_known: bool = True,
    gps_velocity: bool = True,
    outage: tuple[float, float] | None = None,
    gps_offset=None,  # callable t -> (2,) extra GPS error, m
    ekf: BuoyEkf | None = None,
    check_covariance: bool = False,
    accel_bias: tuple[float, float] = (0.0, 0.0),  # body frame, m/s^2
    command=thrust_at,  # callable t -> (2,) world-frame thrust command, N
    slew_radps: float | None = None,  # the nozzle's slew limit (None: the thrust is the command, at once)
    current=steady_current,  # callable t -> (2,) current, m/s
    on_step=None,  # callable (t, filter) run before each step's readings
) -> tuple[BuoyEkf, Run]:
    rng = np.random.default_rng(seed)
    f = BuoyEkf() if ekf is None else ekf
    px, py = 10.0, -5.0
    vx, vy = current(0.0)
    nozzle = 0.0  # body-frame angle of the nozzle, forward at power-up
    thrust = command(0.0)
    rec: dict[str, list] = {k: [] for k in Run.__dataclass_fields__ if k != "outcomes"}
    outcomes = {}
    n = round(duration_s / DT_S)
    for k in range(n + 1):
        t = k * DT_S
        if on_step is not None:
            on_step(t, f)
        if k:  # truth: midpoint integration of M dv/dt = T - drag(v - current), in 2 sub-steps
            h = DT_S / 2
            for j in range(2):
                tj = t - DT_S + j * h
                if slew_radps is None:
                    thrust, thrust_mid = command(tj), command(tj + 0.5 * h)
                else:  # the command of the interval ending at t; the nozzle turns towards it relative to the hull
                    cmd = command(t)
                    hull = heading_at(tj)[0]
                    turn = float(wrap_angle(math.atan2(cmd[1], cmd[0]) - hull - nozzle))
                    nozzle += float(np.clip(turn, -slew_radps * h, slew_radps * h))
                    angle = hull + nozzle
                    thrust = thrust_mid = math.hypot(*cmd) * np.array([math.cos(angle), math.sin(angle)])
                ax, ay = accel_world(vx, vy, thrust, current(tj))
                mx, my = vx + 0.5 * h * ax, vy + 0.5 * h * ay
                ax, ay = accel_world(mx, my, thrust_mid, current(tj + 0.5 * h))
                px, py, vx, vy = px + h * mx, py + h * my, vx + h * ax, vy + h * ay
        p, v = np.array([px, py]), np.array([vx, vy])
        psi, rate = heading_at(t)
        truth_accel = np.array(accel_world(vx, vy, command(t) if slew_radps is None else thrust, current(t)))
        a_body = body(truth_accel, psi) + ACCEL_SIGMA_MPS2 * rng.standard_normal(2) + np.asarray(accel_bias)
        f.predict(t, a_body if accel else None, command(t) if thrust_known else None)
        if k % 5 == 0:
            f.update_compass(t, float(wrap_angle(psi + COMPASS_SIGMA_RAD * rng.standard_normal())))
            f.update_gyro(t, rate + GYRO_SIGMA_RADPS * rng.standard_normal())
        if k % 10 == 0 and not (outage and outage[0] <= t < outage[1]):
            error = GPS_SIGMA_M * rng.standard_normal(2)
            if gps_offset is not None:
                error = error + gps_offset(t)
            vel = v + GPS_VEL_SIGMA_MPS * rng.standard_normal(2) if gps_velocity else None
            outcomes[round(t, 6)] = f.update_gps(t, p + error, vel)
            rec["gps_t"].append(t)
            rec["gps_error"].append(error)
            rec["gps_est_error"].append(f.estimate(t)[0] - p)
        pos, _, head = f.estimate(t)
        if check_covariance:
            cov = f.covariance
            rec["min_eig"].append(np.linalg.eigvalsh(cov).min())
            rec["asymmetry"].append(np.abs(cov - cov.T).max())
        rec["t"].append(t)
        rec["position"].append(p.copy())
        rec["velocity"].append(v.copy())
        rec["heading"].append(psi)
        rec["est_position"].append(pos)
        rec["est_heading"].append(head)
        rec["est_drift"].append(f.drift())
        rec["pos_trace"].append(f.position_covariance_trace())
    arrays = {k: np.array(val) for k, val in rec.items()}
    return f, Run(**arrays, outcomes=outcomes)


def rms(errors: np.ndarray) -> float:
    """Root mean square of the norms of (k, 2) errors (or of (k,) scalars)."""
    e = np.asarray(errors)
    return float(np.sqrt(np.mean(np.sum(e.reshape(len(e), -1) ** 2, axis=1))))


@pytest.fixture(scope="module")
def nominal() -> tuple[BuoyEkf, Run]:
    return simulate(90.0, seed=1, check_covariance=True)


# ---------------------------------------------------------------- buoy accuracy


def test_position_rms_at_most_half_the_raw_gps_error(nominal) -> None:
    _, run = nominal
    settled = run.gps_t >= 10.0
    raw, est = rms(run.gps_error[settled]), rms(run.gps_est_error[settled])
    assert raw == pytest.approx(2.0 * math.sqrt(2.0), rel=0.1)  # the 2 m per axis noise we drew
    assert est <= 0.5 * raw, (est, raw)


def test_heading_rms_under_3_degrees(nominal) -> None:
    _, run = nominal
    settled = run.t >= 5.0
    err = wrap_angle(run.est_heading[settled] - run.heading[settled])
    assert math.degrees(rms(err)) < 3.0


def test_drift_estimate_within_5_cm_per_s_after_60_s(nominal) -> None:
    _, run = nominal
    after = run.t >= 60.0
    err = np.hypot(*(run.est_drift[after] - CURRENT_MPS).T)
    assert err.max() < 0.05, err.max()


def test_covariance_symmetric_positive_definite_after_every_step(nominal) -> None:
    f, run = nominal
    assert run.asymmetry.max() == 0.0  # symmetrised after every prediction and update
    assert run.min_eig.min() > 0.0
    assert np.isfinite(run.est_position).all() and np.isfinite(run.est_heading).all()
    assert f.gated <= 3 and f.failures == 0 and f.rejected == 0  # a clean run: at most chance gating


def test_accelerometer_bias_is_estimated_and_kept_out_of_the_drift() -> None:
    bias = (0.03, -0.02)  # body frame, m/s^2 (1.5 times the simulator's bias std)
    f, run = simulate(90.0, seed=15, accel_bias=bias)
    after = run.t >= 60.0
    assert np.hypot(*(run.est_drift[after] - CURRENT_MPS).T).max() < 0.05
    np.testing.assert_allclose(f.bank.accel_bias()[0], bias, atol=0.005)
    # The same run with the bias states pinned at zero: the drift takes the bias in.
    blind = BuoyEkf(params=BuoyEkfParams(initial_accel_bias_sigma_mps2=1e-6, accel_bias_psd=0.0))
    _, run_blind = simulate(90.0, seed=15, accel_bias=bias, ekf=blind)
    assert np.hypot(*(run_blind.est_drift[after] - CURRENT_MPS).T).max() > 0.05


def reversing_command(t: float) -> np.ndarray:
    """World-frame thrust command, N: 10.8 N reversed every 15 s (the nozzle needs ~1 s to follow)."""
    return (1.0 if int(t // 15.0) % 2 == 0 else -1.0) * np.array([10.0, 4.0])


def test_nozzle_lag_is_modelled_so_thrust_reversals_leave_the_drift_alone() -> None:
    f, run = simulate(90.0, seed=21, command=reversing_command, slew_radps=3.0)
    after = run.t >= 60.0
    assert np.hypot(*(run.est_drift[after] - CURRENT_MPS).T).max() < 0.05
    assert f.model_gated == 0
    # A filter that took each command for the thrust at once would blame the lag on the water.
    naive = BuoyEkf(params=BuoyEkfParams(thrust_slew_radps=1e3))
    _, run_naive = simulate(90.0, seed=21, command=reversing_command, slew_radps=3.0, ekf=naive)
    assert np.hypot(*(run_naive.est_drift[after] - CURRENT_MPS).T).max() > 0.2


def test_drift_locked_out_by_the_gate_is_reopened_after_ten_gated_balances() -> None:
    def corrupt(t: float, f: BuoyEkf) -> None:
        if abs(t - 30.0) < 1e-9:  # a confident, wrong drift: every drag balance now fails the gate
            f.bank.x[0, 6:8] += [1.0, -0.5]

    f, run = simulate(100.0, seed=32, on_step=corrupt)
    assert f.model_gated >= 9 and int(f.bank.outcome_counts("model_reset")[0]) >= 1
    after = run.t >= 90.0
    assert np.hypot(*(run.est_drift[after] - CURRENT_MPS).T).max() < 0.05


def test_drift_follows_a_change_of_current() -> None:
    new = 0.4 * np.array([math.cos(-1.0), math.sin(-1.0)])  # 0.48 m/s away from the old one

    def current(t: float) -> np.ndarray:
        return CURRENT_MPS if t < 60.0 else new

    _, run = simulate(120.0, seed=31, current=current)
    after = run.t >= 110.0
    assert np.hypot(*(run.est_drift[after] - new).T).max() < 0.05


def test_drift_observable_from_thrust_alone_without_accelerometer() -> None:
    # No IMU: the drag model is the process model, v relaxes towards drift + thrust effect.
    _, run = simulate(45.0, seed=2, accel=False)
    after = run.t >= 30.0
    assert np.hypot(*(run.est_drift[after] - CURRENT_MPS).T).max() < 0.05
    assert rms(run.gps_est_error[run.gps_t >= 10.0]) <= 0.5 * rms(run.gps_error[run.gps_t >= 10.0])


def test_without_thrust_command_the_drift_is_not_observable() -> None:
    # Documented: no thrust, no drag model: the drift stays a random walk, its variance only grows.
    f10, _ = simulate(10.0, seed=3, thrust_known=False)
    f20, _ = simulate(20.0, seed=3, thrust_known=False)
    var10, var20 = f10.covariance[6, 6], f20.covariance[6, 6]
    assert var20 > var10 > 0.3**2  # above the 0.3 m/s prior, growing


# ---------------------------------------------------------------- robustness


def test_100_m_gps_jump_is_gated() -> None:
    jump_t = 12.0
    f, run = simulate(16.0, seed=5, gps_offset=lambda t: np.array([100.0, 0.0]) if abs(t - jump_t) < 1e-9 else 0.0)
    assert run.outcomes[jump_t] == "gated"
    assert f.gated == 1
    i = int(np.flatnonzero(np.isclose(run.t, jump_t))[0])
    before = run.est_position[i - 1] + (run.est_position[i - 1] - run.est_position[i - 2])
    assert np.hypot(*(run.est_position[i] - before)) < 1.0  # moved as it was moving, not towards the jump
    assert np.hypot(*(run.est_position[-1] - run.position[-1])) < 3.0


def test_persistent_gps_shift_resets_after_ten_gated_fixes() -> None:
    # A filter that has lost track must not lock itself out: 10 gated fixes in a row re-initialise position.
    f, run = simulate(20.0, seed=6, gps_offset=lambda t: np.array([0.0, 150.0]) if t >= 12.0 else 0.0)
    assert f.gated == 9 and f.resets == 1
    assert run.outcomes[round(12.0 + 9 * 0.2, 6)] == "reset"
    shifted = run.position[-1] + np.array([0.0, 150.0])
    assert np.hypot(*(run.est_position[-1] - shifted)) < 3.0


def test_nan_and_inf_readings_rejected_counted_never_fused() -> None:
    f, _ = simulate(6.0, seed=7)
    state, cov, t = f.state, f.covariance, f.t_s
    outcomes = [
        f.update_gps(6.0, [math.nan, 0.0]),
        f.update_gps(6.0, [1.0, 2.0], [math.inf, 0.0]),
        f.update_gps(math.nan, [1.0, 2.0]),
        f.update_compass(6.0, math.nan),
        f.update_gyro(6.0, -math.inf),
        f.predict(6.02, [math.nan, 0.0]),
        f.predict(6.02, [0.0, 0.0], [math.nan, 1.0]),
        f.predict(math.inf),
    ]
    assert outcomes == ["rejected"] * 8
    assert f.rejected == 8
    np.testing.assert_array_equal(f.state, state)
    np.testing.assert_array_equal(f.covariance, cov)
    assert f.t_s == t
    position, velocity, heading = f.estimate(7.0)
    assert np.isfinite(position).all() and np.isfinite(velocity).all() and math.isfinite(heading)


def test_30_s_gps_outage_dead_reckons_and_recovers() -> None:
    start, end = 15.0, 45.0
    f, run = simulate(55.0, seed=8, outage=(start, end))
    during = (run.t >= start) & (run.t < end)
    trace = run.pos_trace[during]
    assert np.all(np.diff(trace) >= 0.0)  # grows at every step of the outage (dead reckoning)
    assert trace[-1] > 4.0 * trace[0]
    error = np.hypot(*(run.est_position - run.position).T)
    assert error[during].max() < 3.0  # bounded: velocity from the accelerometer, drag model and drift
    after = run.t >= end + 5.0
    assert error[after].max() < 2.5 and run.pos_trace[after].max() < trace[0] * 2.0  # recovered
    assert f.gated <= 2


def test_heading_wraps_across_pi() -> None:
    f = BuoyEkf(position_m=[0.0, 0.0])
    rng = np.random.default_rng(9)
    for k in range(200):  # hull pointing west: readings straddle +pi / -pi
        t = 0.1 * k
        f.predict(t)
        f.update_compass(t, float(wrap_angle(math.pi + COMPASS_SIGMA_RAD * rng.standard_normal())))
        head = f.estimate()[2]
        assert -math.pi < head <= math.pi
        assert abs(wrap_angle(head - math.pi)) < math.radians(8.0)
    assert f.gated == 0
    assert abs(wrap_angle(f.estimate()[2] - math.pi)) < math.radians(1.5)


def test_out_of_order_gps_is_fused_by_replay_exactly_as_in_order() -> None:
    warm, _ = simulate(10.0, seed=10)

    def fresh() -> BuoyEkf:
        return copy.deepcopy(warm)

    in_order, late = fresh(), fresh()
    events = [(10.0 + 0.02 * k, [0.05, -0.02], thrust_at(10.0 + 0.02 * k)) for k in range(1, 11)]
    fix_t, fix = 10.1, (np.array([14.0, -3.0]), np.array([0.3, 0.1]))
    for t, a, thrust in events:  # in order: the fix between the predictions at 10.08 and 10.10
        if abs(t - 10.1) < 1e-9:
            in_order.update_gps(fix_t - 0.01, *fix)
        in_order.predict(t, a, thrust)
        late.predict(t, a, thrust)
    in_order.update_compass(10.2, 0.5)
    late.update_compass(10.2, 0.5)
    assert late.update_gps(fix_t - 0.01, *fix) == "fused"  # delivered 0.11 s after it was measured
    np.testing.assert_allclose(late.state, in_order.state, rtol=0, atol=1e-12)
    np.testing.assert_allclose(late.covariance, in_order.covariance, rtol=0, atol=1e-12)
    assert late.t_s == in_order.t_s == 10.2 and late.late == 0


def test_reading_older_than_the_replay_window_is_rejected_as_late() -> None:
    f, _ = simulate(4.0, seed=11)
    state = f.state
    assert f.update_gps(2.5, [0.0, 0.0]) == "late"  # 1.5 s old, window 1 s
    assert f.update_compass(1.0, 0.0) == "late"
    assert f.late == 2
    np.testing.assert_array_equal(f.state, state)


def test_a_first_fix_older_than_every_logged_reading_sets_the_position_at_the_filters_time() -> None:
    """A vessel's first fix is dated when its autopilot read it, less the GPS's lag: up to a few tenths of a second
    before the first IMU round its filter logged, so no state is there to replay it from. With no position there
    is nothing to keep: the fix sets it, carried to the filter's time at its own velocity. (Counted late and dropped
    before: a vessel whose autopilot then repeats that fix, as one standing still before a fleet's start does, had
    no position at its first step.) Once the filter has a position, such a fix is late as before."""
    f = BuoyEkf()
    f.predict(10.0, [0.0, 0.0])
    f.predict(10.1, [0.0, 0.0])
    assert f.update_gps(9.9, [500.0, 20.0], [2.0, -1.0]) == "init"
    np.testing.assert_allclose(f.estimate()[0], [500.4, 19.8])  # 0.2 s on at (2, -1) m/s
    np.testing.assert_allclose(f.estimate()[1], [2.0, -1.0])
    assert f.t_s == 10.1 and f.late == 0
    assert f.update_gps(9.95, [0.0, 0.0]) == "late"
    np.testing.assert_allclose(f.estimate()[0], [500.4, 19.8])
    g = BuoyEkf()
    g.predict(3.0, [0.0, 0.0])
    assert g.update_gps(2.8, [-7.0, 4.0]) == "init"  # no velocity: taken where it was
    np.testing.assert_allclose(g.estimate()[0], [-7.0, 4.0])
    assert g.update_compass(2.5, 1.0) == "late"  # any other reading older than the log is late


def _still_buoy_with_a_poor_gps(
    seed: int,
    accuracy_m: float | None,
    noise_m: float = 8.0,
    duration_s: float = 45.0,
    speed_noise_mps: float = 0.5,
    speed_accuracy_mps: float | None = None,
) -> tuple[float, BuoyEkfBank]:
    """A buoy holding still at (10, -5) m: IMU and compass at 10 Hz, fixes at 5 Hz with noise_m per axis and
    ground velocities with speed_noise_mps per axis, reported as accuracy_m and speed_accuracy_mps (None: not at
    all). The RMS position error (m) after the first 20 s, and the filter."""
    rng = np.random.default_rng(seed)
    bank, a, truth, errors = BuoyEkfBank(1), np.array([0]), np.array([10.0, -5.0]), []
    for k in range(round(duration_s * 10.0) + 1):
        t = 0.1 * k
        bank.predict(a, t, rng.normal(0.0, 0.02, (1, 2)), np.zeros((1, 2)))
        bank.update_compass(a, np.array([0.3 + rng.normal(0.0, 0.03)]), np.array([t]))
        if k % 2 == 0:
            fix = (truth + rng.normal(0.0, noise_m, 2))[None]
            velocity = rng.normal(0.0, speed_noise_mps, (1, 2))
            bank.update_gps(a, np.array([t]), fix, velocity, accuracy_m, speed_accuracy_mps)
        elif t > 20.0:
            errors.append(np.hypot(*(bank.estimate(t).position[0] - truth)))
    return float(np.sqrt(np.mean(np.square(errors)))), bank


def test_a_fix_is_fused_with_the_accuracies_its_receiver_reports() -> None:
    """A poor GPS (8 m per axis, 0.5 m/s per axis, as near a harbour wall) that says so in GPS_RAW_INT's h_acc and
    vel_acc: fused with the larger of those and the filter's own noise (2 m, 0.1 m/s), as ArduPilot's EKF3 does, the
    estimate averages the fixes. Fused as good fixes, most fail the gate and the filter keeps resetting. Measured at
    seeds 0-4: RMS 0.74-2.04 m told both, 1.7-7.9 m told the position's alone, 7.1-11.2 m told neither (0-1,
    147-163 and 192-198 of 225 fixes gated)."""
    ratios = []
    for seed in range(5):
        told, bank = _still_buoy_with_a_poor_gps(seed, 8.0, speed_accuracy_mps=0.5)
        half, _ = _still_buoy_with_a_poor_gps(seed, 8.0)
        blind, blind_bank = _still_buoy_with_a_poor_gps(seed, None)
        assert told < 2.5 and told < half < blind, (seed, told, half, blind)
        assert bank.outcome_counts("gated")[0] <= 2 and bank.outcome_counts("reset")[0] == 0
        assert blind_bank.outcome_counts("gated")[0] > 150
        ratios.append(told / blind)
    assert np.median(ratios) < 0.3, ratios


def test_a_receiver_claiming_better_than_the_noise_parameter_changes_nothing() -> None:
    """gps_sigma_m is the floor (ArduPilot: max(gpsPosAccuracy, EK3_POSNE_M_NSE)): the same bits as no report."""
    good = {"noise_m": 2.0, "speed_noise_mps": 0.1, "duration_s": 25.0}
    floor, floor_bank = _still_buoy_with_a_poor_gps(3, 0.5, speed_accuracy_mps=0.05, **good)
    plain, plain_bank = _still_buoy_with_a_poor_gps(3, None, **good)
    assert floor == plain
    np.testing.assert_array_equal(floor_bank.x, plain_bank.x)
    np.testing.assert_array_equal(floor_bank.P, plain_bank.P)


def test_estimate_is_finite_before_the_first_fix() -> None:
    f = BuoyEkf()
    f.predict(0.0, [0.1, 0.0])
    f.predict(1.0, [0.1, 0.0])
    pos, vel, head = f.estimate(2.0)
    assert np.isfinite(pos).all() and np.isfinite(vel).all() and math.isfinite(head)
    assert not f.initialized
    assert f.update_gps(1.5, [500.0, 20.0]) == "init"  # the first fix sets position, however far
    assert f.update_compass(None, 1.0) == "init"
    assert f.initialized
    np.testing.assert_allclose(f.estimate()[0], [500.0, 20.0])


@pytest.mark.parametrize("dim_z", [1, 2, 4])
def test_batched_filter_equations_are_filterpys(dim_z: int) -> None:
    rng = np.random.default_rng(40 + dim_z)
    m, n = 5, 10
    a = rng.standard_normal((m, n, n))
    p_cov = a @ a.transpose(0, 2, 1) + n * np.eye(n)
    f_jac = np.eye(n) + 0.1 * rng.standard_normal((m, n, n))
    q_cov = np.array([np.diag(rng.uniform(0.01, 0.1, n)) for _ in range(m)])
    x = rng.standard_normal((m, n))
    h_jac = rng.standard_normal((m, dim_z, n))
    r_cov = np.diag(rng.uniform(0.5, 2.0, dim_z))
    z = rng.standard_normal((m, dim_z))
    p_pred = kalman_predict_rows(p_cov, f_jac, q_cov)
    hx = (h_jac @ x[:, :, None])[:, :, 0]
    x_new, p_new, d2, ok = kalman_update_rows(x, p_pred, z - hx, h_jac, r_cov)
    assert ok.all()
    for i in range(m):
        kf = ExtendedKalmanFilter(dim_x=n, dim_z=dim_z)
        kf.x, kf.P, kf.F, kf.Q = np.zeros((n, 1)), p_cov[i], f_jac[i], q_cov[i]
        kf.predict()
        np.testing.assert_allclose(p_pred[i], 0.5 * (kf.P + kf.P.T), rtol=1e-12, atol=1e-10)
        kf.x, kf.P = x[i][:, None], p_pred[i]
        kf.update(z[i][:, None], lambda _x, i=i: h_jac[i], lambda _x, i=i: hx[i][:, None], R=r_cov)
        np.testing.assert_allclose(x_new[i], kf.x[:, 0], rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(p_new[i], 0.5 * (kf.P + kf.P.T), rtol=1e-10, atol=1e-10)
        assert d2[i] == pytest.approx(float((kf.y.T @ kf.SI @ kf.y).item()), rel=1e-10)


def test_bank_takes_an_agent_twice_in_one_call_in_order() -> None:
    bank, twice = BuoyEkfBank(2), BuoyEkfBank(2)
    for b in (bank, twice):
        b.update_gps(np.arange(2), 0.0, np.zeros((2, 2)))
    bank.update_gps(np.array([1, 0, 1]), np.array([0.2, 0.2, 0.4]), [[1.0, 0.0], [2.0, 0.0], [3.0, 0.0]])
    twice.update_gps(np.array([1, 0]), np.array([0.2, 0.2]), [[1.0, 0.0], [2.0, 0.0]])
    twice.update_gps(np.array([1]), np.array([0.4]), [[3.0, 0.0]])
    np.testing.assert_array_equal(bank.x, twice.x)
    np.testing.assert_array_equal(bank.P, twice.P)


# ---------------------------------------------------------------- eBot


WHEEL_BASE_M, METRES_PER_TICK = 0.1, 2.0 * math.pi * 0.03 / 360


def square_ticks(rate_hz: float = 10.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(times, cumulative ticks (k, 2), true headings) for 1 m sides at 0.2 m/s and in-place 90 deg turns."""
    dt = 1.0 / rate_hz
    wheels, headings = [np.zeros(2)], [0.0]
    travel, heading = np.zeros(2), 0.0
    for _ in range(4):
        for _ in range(round(1.0 / 0.2 / dt)):  # straight: both wheels 0.2 m/s
            travel = travel + 0.2 * dt
            wheels.append(travel.copy())
            headings.append(heading)
        turn = math.pi / 2.0
        steps = 16
        for _ in range(steps):  # in place, counter-clockwise
            d = 0.5 * WHEEL_BASE_M * turn / steps
            travel = travel + np.array([-d, d])
            heading += turn / steps
            wheels.append(travel.copy())
            headings.append(heading)
    times = np.arange(len(wheels)) * dt
    ticks = np.floor(np.array(wheels) / METRES_PER_TICK).astype(np.int64)
    return times, ticks, np.array(headings)


def test_ebot_dead_reckoning_round_a_square_returns_near_the_start() -> None:
    times, ticks, _ = square_ticks()
    f = EbotEkf([1.0, 2.0], 0.0, WHEEL_BASE_M, METRES_PER_TICK)
    traces = []
    for t, k in zip(times, ticks, strict=True):
        f.update_encoders(t, k)
        traces.append(f.position_covariance_trace())
    pos, _, head = f.estimate()
    assert np.hypot(*(pos - [1.0, 2.0])) < 0.03  # 4 m of travel; only tick quantisation
    assert abs(wrap_angle(head - 2.0 * math.pi)) < math.radians(2.0)
    assert traces[-1] > 2.0 * traces[0]  # no correction: the uncertainty grows along the path
    assert np.linalg.eigvalsh(f.covariance).min() > 0.0


def test_ebot_gyro_replaces_the_wheel_heading_change() -> None:
    times, ticks, headings = square_ticks()
    f = EbotEkf([0.0, 0.0], 0.0, WHEEL_BASE_M, METRES_PER_TICK)
    for i, (t, k) in enumerate(zip(times, ticks, strict=True)):
        rate = (headings[i] - headings[i - 1]) / (times[1] - times[0]) if i else 0.0
        f.update_encoders(t, k, rate)
    assert np.hypot(*f.estimate()[0]) < 0.03
    assert abs(wrap_angle(f.estimate()[2])) < 1e-9  # the exact gyro rates give the exact heading


def test_ebot_compass_corrects_an_initial_heading_error() -> None:
    rng = np.random.default_rng(12)
    true_heading = 0.5
    f = EbotEkf([0.0, 0.0], true_heading + math.radians(20.0), WHEEL_BASE_M, METRES_PER_TICK,
                EbotEkfParams(heading_sigma_rad=0.5))  # fmt: skip
    travel = 0.0
    for k in range(101):  # 10 s straight at 0.1 m/s, compass at 10 Hz
        t = 0.1 * k
        travel += 0.01
        f.update_encoders(t, np.floor(np.array([travel, travel]) / METRES_PER_TICK).astype(np.int64))
        f.update_compass(t, true_heading + COMPASS_SIGMA_RAD * rng.standard_normal())
    assert abs(math.degrees(wrap_angle(f.estimate()[2] - true_heading))) < 1.5
    assert f.gated == 0


def test_ebot_position_fix_fused_and_wild_fix_gated() -> None:
    f = EbotEkf([0.0, 0.0], 0.0, WHEEL_BASE_M, METRES_PER_TICK, EbotEkfParams(position_sigma_m=0.5))
    f.update_encoders(0.0, [0, 0])
    assert f.update_position(0.1, [0.3, -0.2], 0.1) == "fused"
    pos = f.estimate()[0]
    assert 0.25 < pos[0] < 0.3 and -0.2 < pos[1] < -0.15  # most of the way to the precise fix
    assert f.position_covariance_trace() < 2 * 0.1**2
    assert f.update_position(0.2, [5.0, 5.0], 0.1) == "gated"
    np.testing.assert_array_equal(f.estimate()[0], pos)
    assert f.update_position(0.3, [math.nan, 0.0], 0.1) == "rejected"
    assert f.update_position(0.3, [0.0, 0.0], -1.0) == "rejected"
    assert f.update_compass(0.3, math.inf) == "rejected"
    assert f.update_encoders(math.nan, [1, 1]) == "rejected"
    assert f.update_encoders(0.4, [1, 1], math.nan) == "rejected"
    assert (f.rejected, f.gated) == (5, 1)
    assert np.isfinite(f.state).all()


def test_ebot_late_compass_replayed_between_encoder_readings() -> None:
    times, ticks, _ = square_ticks()
    a = EbotEkf([0.0, 0.0], 0.0, WHEEL_BASE_M, METRES_PER_TICK)
    b = EbotEkf([0.0, 0.0], 0.0, WHEEL_BASE_M, METRES_PER_TICK)
    for i in range(60):
        if i == 55:
            a.update_compass(times[54] + 0.05, 0.02)
        a.update_encoders(times[i], ticks[i])
        b.update_encoders(times[i], ticks[i])
    assert b.update_compass(times[54] + 0.05, 0.02) == "fused"  # 0.45 s late
    np.testing.assert_allclose(b.state, a.state, rtol=0, atol=1e-12)
    np.testing.assert_allclose(b.covariance, a.covariance, rtol=0, atol=1e-12)
    assert b.update_compass(times[40], 0.02) == "late"


# ---------------------------------------------------------------- banks


def test_buoy_bank_gives_the_single_filters_results() -> None:
    rng = np.random.default_rng(13)
    n = 3
    bank = BuoyEkfBank(n)
    singles = [BuoyEkf() for _ in range(n)]
    agents = np.arange(n)
    for k in range(150):
        t = 0.02 * k
        accel = 0.05 * rng.standard_normal((n, 2))
        thrust = np.tile(thrust_at(t), (n, 1))
        bank.predict(agents, np.full(n, t), accel, thrust)
        for i in range(n):
            singles[i].predict(t, accel[i], thrust[i])
        if k % 5 == 0:
            heading = rng.uniform(-math.pi, math.pi, n)
            gyro = 0.01 * rng.standard_normal(n)
            bank.update_compass(agents, heading, np.full(n, t))
            bank.update_gyro(agents, np.full(n, t), gyro)
            for i in range(n):
                singles[i].update_compass(t, heading[i])
                singles[i].update_gyro(t, gyro[i])
        if k % 10 == 0:
            rows = np.array([2, 0])  # a subset of the agents, in any order
            xy = 3.0 * rng.standard_normal((2, 2)) + [[100.0, 0.0], [0.0, 0.0]]
            vel = 0.1 * rng.standard_normal((2, 2))
            bank.update_gps(rows, np.full(2, t - 0.01), xy, vel)  # 0.01 s late: replayed
            for j, i in enumerate(rows):
                singles[i].update_gps(t - 0.01, xy[j], vel[j])
    est = bank.estimate(3.5)
    for i, f in enumerate(singles):
        pos, vel, head = f.estimate(3.5)
        np.testing.assert_array_equal(est.position[i], pos)
        np.testing.assert_array_equal(est.velocity[i], vel)
        assert est.heading[i] == head
        np.testing.assert_array_equal(bank.drift()[i], f.drift())
        assert bank.covariance_trace()[i] == f.position_covariance_trace()
    assert est.position.shape == (n, 2) and est.heading.shape == (n,) and bank.drift().shape == (n, 2)
    assert np.isfinite(est.position).all()  # agent 1 never had a fix: its prior, not NaN
    np.testing.assert_array_equal(bank.initialized(), [True, False, True])
    bank.update_gps(np.array([0]), np.array([math.nan]), np.array([[0.0, 0.0]]))
    assert bank.rejected == 1
    # The first fixes (t = -0.01) predate the filters' first reading: with no position yet, they set it there.
    assert bank.late == sum(f.late for f in singles) == 0
