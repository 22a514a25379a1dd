"""State estimation: extended Kalman filters for the BoB buoy and the eBot.

The buoy filter runs as a bank: `BuoyEkfBank` holds N independent buoy EKFs in
numpy arrays (rows = agents) and handles each call for all its rows at once;
`BuoyEkf` is a bank of one, so a vessel's own filter runs the same code as a
simulated fleet's. Its filter equations are those of filterpy's
`ExtendedKalmanFilter` (predict P = F P F^T + Q; update in Joseph form) written
over a stack of filters (`kalman_predict_rows`, `kalman_update_rows`;
tests/test_ekf.py checks them against filterpy row by row). The eBot filter
runs as a bank too: `EbotEkfBank` (rows = robots, the same row equations); its
reference is `EbotEkf`, one filterpy `ExtendedKalmanFilter` per robot, which
tests/test_ebot_ekf_bank.py holds the bank to reading by reading.
Both banks have the batch API of
`bob_autonomy.estimation.simple_estimator` (update_gps, update_compass, update_encoders,
estimate -> PoseEstimate), which they replace. Frames: x east, y north (m);
headings in rad from east, counter-clockwise, wrapped to (-pi, pi]; the body
frame is x forward along the heading, y to the left.

Buoy (`BuoyEkfBank`, `BuoyEkf`)
-------------------------------
State s = [x, y, vx, vy, heading, yaw_rate, drift_x, drift_y, bias_x, bias_y]:
position (m), velocity over ground v (m/s), heading (rad), yaw rate r (rad/s),
the equivalent drift d (m/s, below) and the accelerometer bias b (body frame,
m/s^2).

What the drift is. The filter models the hull as the autonomy's nominal buoy
(velocity_control.BuoyModel, the MPC's model too): M dv/dt = T - f(v - d),
f(w) = (c1 + c2 |w|) w, with the thrust T known and d the velocity of "the
water" (M = 35 kg with added mass, c1 = 5 N s/m, c2 = 40 N s^2/m^2). On real
water a hull moving at v is pushed by E(v): drag from the surface water
(current plus wind-driven drift) and windage on the hull. The EQUIVALENT DRIFT
at v is the d for which the nominal law gives that same push, f(d - v) = E(v)
(`sitl.vehicles.dynamics.equivalent_drift_mps` computes it from the simulator's force
balance). For an unpowered buoy it is the velocity over ground the buoy settles
to (there E = 0, so d = v); for a buoy holding station it is the water velocity
whose drag alone on a hull at rest equals water and wind together. The two
differ (by 0.02 to 0.09 m/s in a 5 m/s wind with a 0.1 m/s current): drag grows
with the square of the speed through the water, and a hull at one operating
velocity only ever feels E at that velocity, so where it would settle if
unpowered (which depends on how E splits into water and wind) is not observable
from it without a wind sensor. The filter therefore estimates d at the operating
velocity, which is what makes the nominal model, and the MPC that takes d as its
water, right where the buoy is. d is a slow random walk (PSD `drift_psd`,
0.003^2 m^2/s^3): it follows a change of operating point within tens of seconds.

Process model, integrated in sub-steps of at most `max_step_s` (0.25 s) with
p += v h + a h^2 / 2, v += a h, heading += r h; r, d and b are random walks. The
acceleration a over ground comes from, in order of preference:
  1. the accelerometer: a = R(heading) (a_body - b), the body-frame reading less
     the bias rotated by the ESTIMATED heading (the Jacobian carries how heading
     and bias errors feed velocity errors). The reading given to
     `predict(t, accel_body)` is the mean acceleration over the interval that
     ends at t (a sample describes the motion just past); it is then held for
     `accel_hold_s` (0.1 s) of predictions to later measurement times. Its white
     noise `accel_noise_mps2` (0.05 m/s^2) spreads over the interval H it covers:
     velocity PSD accel_noise^2 H + `accel_psd` (0.01^2 m^2/s^3, unmodelled
     motion). The bias (prior 0.05 m/s^2, random walk PSD `accel_bias_psd`
     1e-4^2 m^2/s^5) is observable through GPS: it is the gap between the
     integrated readings and the ground velocity;
  2. else, with a known thrust command, the nominal model M a = T - f(v - d),
     PSD `model_psd` (0.1^2 m^2/s^3, model error);
  3. else constant velocity, PSD `free_psd` (0.3^2 m^2/s^3: any manoeuvre).
Yaw rate: random walk, PSD `yaw_accel_psd` (0.05^2 rad^2/s^3). Position/velocity
and heading/yaw-rate noise use the exact piecewise-white blocks
q [[h^3/3, h^2/2], [h^2/2, h]].

The thrust and the nozzle. `predict(t, accel_body, thrust_world_n)` takes the
world-frame command (N) in force over the interval ending at t, the one that
produced the acceleration read at t; it stays in force for `thrust_hold_s` (1 s)
after t. The thrust on the hull lags the command: the vectored nozzle turns
relative to the hull at most `thrust_slew_radps` (3 rad/s; a reversal takes
~1 s, time enough for the real thrust to point 20 N away from a swinging
command). The filter turns a believed nozzle angle (forward at power-up) towards
each command's body-frame direction (its direction less the estimated heading)
at that rate, the magnitude following at once, and takes the mean body-frame
thrust T_b over the interval.

How the drift is observed: the drag balance. Each accelerometer reading that
comes with a command in force (once position and heading are known) is fused as
a pseudo-measurement a_body = T_b / M - R(heading)^T f(v_mid - d) / M + b at the
interval's midpoint velocity v_mid = v - R (a_body - b) H / 2 (the reading is a
mean over H), sigma `drag_balance_sigma_mps2` (0.1 m/s^2: sensor noise and
drag-model error), gated like a sensor (counted in `model_gated`);
`gate_reset_count` consecutive gated balances re-open the drift to its prior
(outcome 'model_reset'). GPS pins v (positions, Doppler velocity) and with it b;
the balance then gives d, to within M db / (c1 + 2 c2 |v - d|) for a bias error
db (7 db for an unpowered buoy, whose drag is softest). Without an
accelerometer, model (2) is what ties d to the velocity GPS sees: v relaxes
towards d + w_T, w_T the velocity through the water at which drag balances T.
With no thrust command the drift is not observable: it stays a random walk and
its variance grows (a caller that knows the buoy is idle passes zero thrust).

Measurement models (z = h(s) + noise):
  * GPS (`update_gps`): [x, y] (sigma `gps_sigma_m` 2 m per axis), plus
    [vx, vy] when the receiver's ground velocity is given (sigma
    `gps_velocity_sigma_mps` 0.1 m/s). The first fix initialises position (and
    velocity).
  * compass (`update_compass`): heading, sigma `compass_sigma_rad` (2 deg; the
    compass bias is not modelled), innovation wrapped to (-pi, pi]. The first
    reading initialises the heading; until then the accelerometer is ignored
    (it cannot be rotated into the world).
  * gyro (`update_gyro`): yaw rate, sigma `gyro_sigma_radps` (0.006 rad/s).

eBot (`EbotEkfBank`, `EbotEkf`)
-------------------------------
State [x, y, heading]. Prediction from wheel-encoder odometry: the cumulative
ticks give wheel travels dl, dr since the last reading; ds = (dl + dr) / 2,
dheading = (dr - dl) / wheel_base (or gyro_z * dt when a gyro reading comes
with the encoders); midpoint integration x += ds cos(heading + dheading / 2),
etc. Wheel-travel noise has a standard deviation proportional to the distance,
`wheel_noise_fraction` (0.05, as the simulator's per-step wheel slip) times |d|,
plus the tick quantisation (metres_per_tick^2 / 6 for the two readings), mapped
through the motion Jacobian; a gyro heading change has sigma
`gyro_sigma_radps` * dt. Corrections: compass (2 deg) and, when one exists, a
position fix `update_position(t, xy, sigma_m)`. Between encoder readings the
pose is held (an eBot's encoders are read every control step).

Robustness (both filters)
-------------------------
* Non-finite readings (NaN/inf in the time or any value) are never fused; they
  are counted in `rejected` and leave the filter untouched.
* Innovation gate: a reading whose squared Mahalanobis distance y^T S^-1 y
  exceeds the chi-square 99.9 % quantile for its dimension (10.83, 13.82,
  16.27, 18.47 for 1-4) is not fused and is counted in `gated` (a 100 m GPS
  jump is rejected). So that a filter that has lost track cannot lock itself
  out for ever, `gate_reset_count` (10) consecutive gated readings of one
  sensor re-initialise what it measures from the reading (counted in `resets`).
* Updates use the Joseph-form covariance update; P is symmetrised after every
  prediction and update; a step that would leave a non-finite state or a
  non-positive variance is undone (counted in `failures`). Estimates are never
  NaN: before its first fix a buoy reports its prior (the origin unless given;
  see `initialized`).
* Time. Each reading is fused at its own measurement time t_s: the filter
  first predicts to t_s. A reading older than the filter's time (out of order,
  e.g. a GPS fix delivered 0.1 s late after IMU predictions) is fused by
  stored-state replay: every call is logged with the filter state after it,
  for `replay_window_s` (1 s); the filter goes back to the state just before
  t_s, fuses the late reading there and re-runs the later calls, which gives
  exactly the result of an in-order arrival (the buoy bank re-runs the agents
  of one logged call together). Readings older than the window are rejected and
  counted in `late`.

Modules
-------
* `kalman_rows`: filterpy's EKF predict and Joseph update over a stack of filters, the gate quantiles, wrap_angle.
* `timed_ekf`: the filterpy-based filter machinery (gate, updates, replay log) under `EbotEkf`; filterpy is
  imported on first use, so importing this package does not import it.
* `row_replay`: the banks' time, log, replay and outcome counters, and `OUTCOMES`. `row_fusion`: the banks' gated
  Joseph-form fusion and reset.
* `buoy_params`: `BuoyEkfParams`, the buoy state layout and kinds of reading.
* `buoy_ekf_bank`: `BuoyEkfBank`, its code spread over bases: `buoy_updates` (GPS, compass, gyro), `buoy_process`
  (nozzle slew, prediction, drag balance), `row_fusion` and `row_replay`.
* `buoy_ekf`: `BuoyEkf`, a bank of one. `ebot_ekf`: `EbotEkfParams`, `EbotEkf` (filterpy, the reference).
  `ebot_ekf_bank`: `EbotEkfBank`.
The package exports the public names.
"""

from bob_autonomy.estimation.buoy_ekf import BuoyEkf
from bob_autonomy.estimation.buoy_ekf_bank import BuoyEkfBank
from bob_autonomy.estimation.buoy_params import BuoyEkfParams
from bob_autonomy.estimation.ebot_ekf import EbotEkf, EbotEkfParams
from bob_autonomy.estimation.ebot_ekf_bank import EbotEkfBank
from bob_autonomy.estimation.kalman_rows import CHI2_999, kalman_predict_rows, kalman_update_rows, wrap_angle
from bob_autonomy.estimation.row_replay import OUTCOMES

__all__ = [
    "CHI2_999",
    "OUTCOMES",
    "BuoyEkf",
    "BuoyEkfBank",
    "BuoyEkfParams",
    "EbotEkf",
    "EbotEkfBank",
    "EbotEkfParams",
    "kalman_predict_rows",
    "kalman_update_rows",
    "wrap_angle",
]
