"""`BuoyDynamics.step` against its plain form, bit for bit, on random inputs (seeded).

The step batches the nozzle trigonometry and the heading increments over the substeps, shares the flow relative to
the hull between the predictor and the corrector, takes the closed forms of the phi functions when every drag rate
is known to be above their series thresholds, and works on views when every buoy is active. The reference below is
the substep loop as it was written first: one substep after the other, on copies of the active rows. Also
`VehiclePhysics`' row index of a kind (a slice when the rows are contiguous) against the rows themselves.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from sitl.vehicles.dynamics import BuoyDynamics, BuoyParams, _norm, _phi1, _phi2, wrap_angle
from sitl.vehicles.vehicle_physics import _row_index


def _plain_step(b: BuoyDynamics, cmd, dt_s: float, wind, current, limit) -> np.ndarray:
    """`BuoyDynamics.step` as first written: the reference."""
    p = b.params
    n = len(b)
    cmd_mag = _norm(cmd)
    thrust_mag = np.minimum(cmd_mag, np.maximum(limit, 0.0))
    cmd_angle = np.where(cmd_mag > 1e-9, np.arctan2(cmd[:, 1], cmd[:, 0]), b.thrust_angle_body_rad)
    water = current + p.wind_drift_factor * wind
    decay = math.exp(-dt_s / p.yaw_torque_time_constant_s)
    torque_noise = p.yaw_torque_std_nm * math.sqrt(max(0.0, 1.0 - decay * decay))
    b.yaw_torque_nm = b.yaw_torque_nm * decay + torque_noise * b.rng.standard_normal(n)

    act = b.active
    x, v = b.position_m[act], b.velocity_mps[act]
    heading, rate = b.heading_rad[act], b.yaw_rate_radps[act]
    nozzle, target, mag = b.thrust_angle_body_rad[act], cmd_angle[act], thrust_mag[act]
    u, w, torque = water[act], wind[act], b.yaw_torque_nm[act]
    v_start = v.copy()
    mass = p.effective_mass_kg

    def coefficients(v):
        return (
            p.linear_drag_n_per_mps + p.quadratic_drag_n_per_mps2 * _norm(v - u),
            p.air_drag_n_per_mps2 * _norm(w - v),
        )

    def acceleration(v, thrust, h, coef):
        force = thrust + coef[0][:, None] * (u - v) + coef[1][:, None] * (w - v)
        return force / mass, (coef[0] + coef[1]) / mass * h

    substeps = max(1, math.ceil(dt_s / p.max_substep_s - 1e-9))
    h = dt_s / substeps
    yaw_rate_decay = p.yaw_damping_nms_per_rad / p.yaw_inertia_kgm2 * h
    yaw_phi1, yaw_phi2 = _phi1(np.full(1, yaw_rate_decay)), _phi2(np.full(1, yaw_rate_decay))
    slew = p.thrust_slew_radps * h
    thrust = np.zeros_like(v)
    for _ in range(substeps):
        turn = wrap_angle(target - nozzle)
        nozzle = nozzle + np.minimum(np.maximum(turn, -slew), slew)
        world_angle = heading + nozzle
        direction = np.empty_like(v)
        direction[:, 0], direction[:, 1] = np.cos(world_angle), np.sin(world_angle)
        thrust = mag[:, None] * direction
        accel, h_over_tau = acceleration(v, thrust, h, coefficients(v))
        dv_pred = accel * (h * _phi1(h_over_tau))[:, None]
        accel, h_over_tau = acceleration(v, thrust, h, coefficients(v + 0.5 * dv_pred))
        dv = accel * (h * _phi1(h_over_tau))[:, None]
        dx = h * v + accel * (h * h * _phi2(h_over_tau))[:, None]
        x, v = x + dx, v + dv
        yaw_accel = (torque - p.yaw_damping_nms_per_rad * rate) / p.yaw_inertia_kgm2
        heading = heading + h * (rate + yaw_accel * h * yaw_phi2)
        rate = rate + yaw_accel * h * yaw_phi1

    b.position_m[act], b.velocity_mps[act] = x, v
    b.heading_rad[act], b.yaw_rate_radps[act] = wrap_angle(heading), rate
    b.thrust_angle_body_rad[act] = wrap_angle(nozzle)
    b.thrust_n[act] = thrust
    b.acceleration_mps2 = np.zeros((n, 2))
    b.acceleration_mps2[act] = (v - v_start) / dt_s
    idle = ~act
    b.velocity_mps[idle] = 0.0
    b.yaw_rate_radps[idle] = 0.0
    b.thrust_n[idle] = 0.0
    return b.acceleration_mps2.copy()


def _state(b: BuoyDynamics) -> np.ndarray:
    parts = (b.position_m, b.velocity_mps, b.heading_rad, b.yaw_rate_radps, b.thrust_n, b.thrust_angle_body_rad,
             b.yaw_torque_nm, b.acceleration_mps2)  # fmt: skip
    return np.concatenate([a.ravel() for a in parts]).view(np.int64)  # bits: -0.0 and NaN payloads count


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize(
    "params",
    [BuoyParams(), BuoyParams(linear_drag_n_per_mps=0.0), BuoyParams(linear_drag_n_per_mps=1e-6, max_substep_s=0.03)],
    ids=["default", "no-linear-drag", "series-phi"],
)
@pytest.mark.parametrize("dt_s", [0.5, 0.1, 0.0123])
def test_buoy_step_matches_the_plain_substep_loop_bit_for_bit(seed: int, params: BuoyParams, dt_s: float) -> None:
    rng = np.random.default_rng(seed)
    n = 45
    position, heading = rng.uniform(-50.0, 50.0, (n, 2)), rng.uniform(-4.0, 4.0, n)
    fast = BuoyDynamics(params, position, heading, np.random.default_rng(seed + 100))
    plain = BuoyDynamics(params, position, heading, np.random.default_rng(seed + 100))
    for k in range(25):
        cmd = rng.normal(0.0, 20.0, (n, 2))
        cmd[rng.random(n) < 0.1] = 0.0  # no command: the nozzle keeps its angle
        wind, current = rng.normal(0.0, 5.0, (n, 2)), rng.normal(0.0, 0.5, (n, 2))
        if k == 0:  # calm water and air for buoys at rest: drag rates of 0 (the phi series)
            wind[: n // 3], current[: n // 3] = 0.0, 0.0
        elif k % 5 == 0:
            current[: n // 3] = -params.wind_drift_factor * wind[: n // 3]  # still water: only the linear drag
        limit = rng.uniform(0.0, 60.0, n)
        if k % 7 == 3:  # some buoys removed, some back
            fast.active = plain.active = rng.random(n) < 0.7
        elif k % 7 == 5:
            fast.active, plain.active = np.ones(n, dtype=bool), np.ones(n, dtype=bool)
        got = fast.step(cmd, dt_s, wind, current, limit)
        want = _plain_step(plain, cmd, dt_s, wind, current, limit)
        assert np.array_equal(got.view(np.int64), want.view(np.int64))
        assert np.array_equal(_state(fast), _state(plain))


@pytest.mark.parametrize("seed", range(20))
def test_vehicle_physics_row_index_selects_the_rows_of_a_kind(seed: int) -> None:
    rng = np.random.default_rng(seed)
    kinds = rng.integers(0, 3, rng.integers(1, 12))
    if seed % 2:
        kinds = np.sort(kinds)  # the usual layout: each kind in one block
    table = rng.normal(size=(kinds.size, 2))
    for kind in range(3):
        rows = np.flatnonzero(kinds == kind)
        index = _row_index(rows)
        assert np.array_equal(table[index], table[rows])
        assert isinstance(index, slice) == (rows.size > 0 and np.array_equal(rows, np.arange(rows[0], rows[-1] + 1)))
