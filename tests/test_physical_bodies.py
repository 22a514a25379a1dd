"""sitl/vehicles/physical_bodies.py: the physics fidelity with the autonomy's estimator and controller in the loop.

Truth is `position`, `heading`, `velocity`; what the vessels believe is `believed()`. Buoy defaults
(sitl/vehicles/dynamics.py BuoyParams): effective mass 35 kg, water drag 5 v + 40 v^2 N, air drag
0.5 * 1.225 * 1.0 * 0.15 = 0.091875 N/(m/s)^2, so full thrust = 5 + 40 + 0.091875 = 45.091875 N
(top speed 1 m/s). GPS defaults: 5 Hz, 2 m per axis, 0.1 m/s receiver velocity.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from bob_autonomy.core.geodesy import LocalFrame
from sitl.experiments.recorder import TRAJECTORY_COLUMNS
from sitl.experiments.runner import simulate
from sitl.experiments.scenario import Scenario, validate_scenario
from sitl.fleets.fleet import LockstepFleet, make_bodies
from sitl.vehicles.bodies import BUOY, EBOT
from sitl.vehicles.dynamics import BuoyParams
from sitl.vehicles.physical_bodies import PhysicalBodies
from sitl.vehicles.sensors import GpsSpec
from sitl.world.environment import CurrentSpec, Environment, WindSpec
from sitl.world.world import World

DT_S = 0.1
AIR_DRAG = 0.5 * 1.225 * 1.0 * 0.15  # 0.091875 N/(m/s)^2


def buoys(
    n: int = 10,
    seed: int = 0,
    thrust_fraction: float = 1.0,
    wind: WindSpec | None = None,
    sensors: dict[str, object] | None = None,
) -> PhysicalBodies:
    """n buoys 50 m apart along x, heading east, in still water unless `wind` is given."""
    environment = Environment(wind or WindSpec(), CurrentSpec(), np.random.default_rng([seed, 3]))
    position = np.column_stack((50.0 * np.arange(n), np.zeros(n)))
    return PhysicalBodies(
        np.full(n, BUOY),
        position,
        np.zeros(n),
        environment,
        LocalFrame(1.3406, 103.9266),
        np.random.default_rng([seed, 2]),
        np.full(n, thrust_fraction),
        sensors or {},
    )


def run(bodies: PhysicalBodies, wish: tuple[float, float], steps: int) -> dict[str, np.ndarray]:
    """Apply the same wished velocity for `steps` steps of DT_S; truth and belief after each step."""
    n, world = len(bodies), World()
    out: dict[str, list[np.ndarray]] = {"position": [], "velocity": [], "heading": [], "believed": [], "b_heading": []}
    for _ in range(steps):
        bodies.apply(np.tile(wish, (n, 1)), np.full(n, np.nan), DT_S, world)
        believed, believed_heading, _ = bodies.believed()
        out["position"].append(bodies.position.copy())
        out["velocity"].append(bodies.velocity.copy())
        out["heading"].append(bodies.heading.copy())
        out["believed"].append(believed.copy())
        out["b_heading"].append(believed_heading.copy())
    return {k: np.array(v) for k, v in out.items()}


def wrapped(angle: np.ndarray) -> np.ndarray:
    return np.mod(angle + np.pi, 2.0 * np.pi) - np.pi


# ---------------------------------------------------------------- buoys


@pytest.fixture(scope="module")
def cruise() -> dict[str, np.ndarray]:
    """10 buoys asked for 0.5 m/s east for 30 s with default sensors, in still water."""
    return run(buoys(), (0.5, 0.0), 300)


def test_params_full_thrust_by_hand() -> None:
    # 5 * 1 + (40 + 0.091875) * 1^2 = 45.091875 N
    assert BuoyParams().max_thrust_n == pytest.approx(5.0 + 40.0 + AIR_DRAG)


def test_buoy_belief_differs_from_truth_but_tracks_it(cruise) -> None:
    error = cruise["believed"] - cruise["position"]
    assert np.isfinite(cruise["believed"]).all() and np.isfinite(cruise["b_heading"]).all()
    assert np.abs(error).max() > 0.1  # sensor noise: the belief is not the truth
    rms = math.sqrt(float((error**2).sum(axis=-1).mean()))
    assert rms < 3.0  # 2 m per axis fixes, smoothed: ~1.4 m
    # compass: bias 1 deg std + 2 deg noise, smoothed -> within a few degrees
    heading_error = wrapped(cruise["b_heading"] - cruise["heading"])
    assert np.abs(heading_error).max() > 1e-6
    assert math.degrees(math.sqrt(float((heading_error**2).mean()))) < 5.0


def test_buoy_reaches_wished_speed_default_sensors(cruise) -> None:
    last = cruise["velocity"][-50:]  # the last 5 s
    # the fleet as a whole moves at the wished 0.5 m/s east
    assert last[..., 0].mean() == pytest.approx(0.5, abs=0.05)
    assert abs(last[..., 1].mean()) < 0.05
    # and went that way: ~0.5 m/s * 30 s = 15 m east on average (a little less for the start)
    travelled = cruise["position"][-1] - buoys().position
    assert 11.0 < travelled[:, 0].mean() < 16.0


def test_buoy_reaches_wished_speed_precise_gps() -> None:
    truth = run(buoys(sensors={"gps": GpsSpec(noise_m=0.05, velocity_noise_mps=0.01)}), (0.5, 0.0), 300)
    speed_x = truth["velocity"][-50:, :, 0]
    np.testing.assert_allclose(speed_x.mean(axis=0), 0.5, atol=0.03)  # every buoy
    assert np.abs(truth["velocity"][-50:, :, 1]).mean() < 0.03
    assert speed_x.std() < 0.05


def test_each_buoy_holds_wished_speed_default_sensors(cruise) -> None:
    speed_x = cruise["velocity"][-50:, :, 0]
    np.testing.assert_allclose(speed_x.mean(axis=0), 0.5, atol=0.1)
    assert np.hypot(*cruise["velocity"][-50:].transpose(2, 0, 1)).std() < 0.08


def test_weak_buoy_stays_below_its_terminal_speed() -> None:
    fraction = 0.4
    thrust = fraction * (5.0 + 40.0 + AIR_DRAG)  # 0.4 * 45.091875 = 18.03675 N
    # 5 v + (40 + 0.091875) v^2 = thrust: v = (-5 + sqrt(25 + 4 c2 T)) / (2 c2)
    c2 = 40.0 + AIR_DRAG
    terminal = (-5.0 + math.sqrt(25.0 + 4.0 * c2 * thrust)) / (2.0 * c2)
    assert terminal == pytest.approx(0.6113, abs=1e-3)
    truth = run(buoys(thrust_fraction=fraction), (1.0, 0.0), 300)  # asked for 1 m/s
    speed = np.hypot(truth["velocity"][..., 0], truth["velocity"][..., 1])
    # With |thrust| <= 18.04 N the speed through still water can never pass the force balance.
    assert speed.max() <= terminal + 1e-6
    # but the buoy does try: near it after 25 s (and far below the 1 m/s asked)
    assert speed[-50:].mean() > 0.9 * terminal


@pytest.mark.parametrize("toward_deg", [0.0, 135.0])
def test_wind_drifts_idle_buoys_downwind(toward_deg: float) -> None:
    bodies = buoys(wind=WindSpec(speed_mps=5.0, toward_deg=toward_deg))
    start = bodies.position.copy()
    truth = run(bodies, (0.0, 0.0), 300)
    wind = np.array([math.cos(math.radians(toward_deg)), math.sin(math.radians(toward_deg))])
    moved = (truth["position"][-1] - start).mean(axis=0)
    along, across = moved @ wind, moved @ np.array([-wind[1], wind[0]])
    # windage 0.091875 * 25 = 2.3 N plus 3 % surface drift against the controller's 52.5 N/(m/s):
    # a slow but steady drift downwind (~0.06 m/s, ~2 m in 30 s)
    assert along > 0.5
    assert abs(across) < 0.5 * along
    # in still air the same buoys hardly move
    calm = buoys()
    calm_start = calm.position.copy()
    still = run(calm, (0.0, 0.0), 300)
    assert np.linalg.norm((still["position"][-1] - calm_start).mean(axis=0)) < 0.5 * along


# ---------------------------------------------------------------- eBots


def ebots(n: int = 4, seed: int = 0) -> PhysicalBodies:
    """n eBots 1 m apart along x, heading east, no walls."""
    return PhysicalBodies(
        np.full(n, EBOT),
        np.column_stack((np.arange(n, dtype=float), np.zeros(n))),
        np.zeros(n),
        Environment(WindSpec(), CurrentSpec(), np.random.default_rng([seed, 3])),
        LocalFrame(1.3406, 103.9266),
        np.random.default_rng([seed, 2]),
        np.ones(n),
        {},
    )


@pytest.mark.parametrize("turn_deg", [-90.0, 90.0])
def test_ebot_turns_in_place_to_wished_heading(turn_deg: float) -> None:
    # Turning left in place runs the left wheel backwards: negative cumulative encoder ticks, which the
    # odometry once took for "no reading yet" (believed heading ~65 deg, truth overshooting to ~200 deg).
    bodies = ebots()
    start = bodies.position.copy()
    n, world = len(bodies), World()
    for _ in range(10):  # 1 s; at 4 rad/s per rad, wheels +-0.2 m/s -> 4 rad/s: a quarter turn takes ~0.5 s
        bodies.apply(np.zeros((n, 2)), np.full(n, math.radians(turn_deg)), DT_S, world)
    believed, believed_heading, _ = bodies.believed()
    assert np.all(np.abs(np.degrees(wrapped(bodies.heading - math.radians(turn_deg)))) < 10.0)
    assert np.all(np.abs(np.degrees(wrapped(believed_heading - bodies.heading))) < 10.0)
    # in place: the centre stays (slip only changes the turn rate), and the belief agrees
    assert np.abs(bodies.position - start).max() < 0.02
    assert np.abs(believed - bodies.position).max() < 0.02


def test_ebot_drives_straight_and_dead_reckons() -> None:
    bodies = ebots()
    start = bodies.position.copy()
    truth = run(bodies, (0.2, 0.0), 50)  # 5 s east at the 0.2 m/s wheel limit: ~1 m
    moved = truth["position"][-1] - start
    np.testing.assert_allclose(moved[:, 0], 1.0, atol=0.1)  # slip is 5 % per wheel per step, zero mean
    assert np.abs(moved[:, 1]).max() < 0.1
    # no walls, no contacts: dead reckoning (encoders count wheel turns, slip is unseen) stays within ~slip
    error = np.hypot(*(truth["believed"][-1] - truth["position"][-1]).T)
    assert error.max() < 0.1


# ---------------------------------------------------------------- through a scenario


def scenario(**changes: object) -> Scenario:
    """Physics: 6 eBots cruising in a walled 3 m x 3 m room; 4 half-thrust buoys going east at 0.5 m/s on a pond."""
    data: dict[str, object] = {
        "name": "physics-test",
        "duration_s": 5.0,
        "dt_s": 0.1,
        "seed": 3,
        "log_period_s": 0.5,
        "fidelity": "physics",
        "environment": {"wind": {"speed_mps": 3.0, "toward_deg": 30.0}, "current": {"speed_mps": 0.1}},
        "world": {
            "rooms": [
                {"name": "lab", "polygon": [[0, 0], [3, 0], [3, 3], [0, 3]]},
                {"name": "pond", "polygon": [[90, 90], [310, 90], [310, 310], [90, 310]], "walls": False},
            ]
        },
        "groups": [
            {
                "name": "bots",
                "count": 6,
                "body": "ebot",
                "behavior": "hold-heading",
                "params": {"cruise_speed": 0.2},
                "start": {"box": {"min": [0.3, 0.3], "max": [2.7, 2.7]}, "min_separation_m": 0.3},
            },
            {
                "name": "buoys",
                "count": 4,
                "body": "buoy",
                "behavior": "hold-heading",
                "params": {"heading_deg": 0.0, "cruise_speed": 0.5},
                "thrust_fraction": 0.5,
                "start": {"box": {"min": [100.0, 100.0], "max": [300.0, 300.0]}, "heading_deg": 0.0},
            },
        ],
    }
    data.update(changes)
    return validate_scenario(data, "physics test")


def test_make_bodies_physics_fidelity() -> None:
    fleet = LockstepFleet(scenario())
    bodies = fleet.bodies
    assert isinstance(bodies, PhysicalBodies)
    np.testing.assert_array_equal(bodies.kind, [EBOT] * 6 + [BUOY] * 4)
    np.testing.assert_allclose(bodies.max_thrust_n, 0.5 * (45.0 + AIR_DRAG))  # the buoys' thrust_fraction
    kinematic = make_bodies(scenario(fidelity="kinematic"), bodies.kind, bodies.position, bodies.heading)
    assert not isinstance(kinematic, PhysicalBodies)


def test_ebot_estimate_starts_at_true_pose_and_ebots_stay_in_the_room() -> None:
    fleet = LockstepFleet(scenario())
    e = fleet.bodies.ebots
    believed, believed_heading, _ = fleet.bodies.believed()
    # eBots are told their start pose; with zero wheel commands in the pre-roll they have not moved
    np.testing.assert_allclose(believed[e], fleet.bodies.position[e], atol=1e-12)
    # the heading was only pulled a little towards the biased, noisy compass
    assert np.all(np.abs(np.degrees(wrapped(believed_heading[e] - fleet.bodies.heading[e]))) < 5.0)
    for _ in range(300):  # 30 s at 0.2 m/s: 6 m, i.e. into the walls several times
        fleet.step()
        assert fleet.inside_rooms()[e].all()
        assert np.all(np.isfinite(fleet.bodies.believed()[0]))
    assert fleet.bodies.wall_contacts > 0


def test_physics_run_is_deterministic() -> None:
    runs = []
    for seed in (3, 3, 4):
        fleet = LockstepFleet(scenario(seed=seed))
        for _ in range(50):
            fleet.step()
        b = fleet.bodies
        runs.append((b.position.copy(), b.heading.copy(), b.velocity.copy(), b.believed()[0].copy()))
    for first, second in zip(runs[0], runs[1], strict=True):
        np.testing.assert_array_equal(first, second)
    assert not np.array_equal(runs[0][0], runs[2][0])  # another seed, another run


def test_physics_trajectory_columns_present_and_finite(tmp_path: Path) -> None:
    result = simulate(scenario(duration_s=3.0))
    path = tmp_path / "trajectory.csv"
    result.recorder.write_csv(path)
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        assert tuple(reader.fieldnames or ()) == TRAJECTORY_COLUMNS
        rows = list(reader)
    assert len(rows) == 7 * 10  # frames at 0, 0.5, ..., 3.0 s, 10 agents each
    extra = TRAJECTORY_COLUMNS[TRAJECTORY_COLUMNS.index("wind_x") :]
    assert extra == ("wind_x", "wind_y", "current_x", "current_y", "est_x", "est_y", "est_heading")
    values = np.array([[float(row[c]) for c in extra] for row in rows])
    assert np.isfinite(values).all()
    # steady wind 3 m/s towards 30 deg: (2.598, 1.500); current 0.1 m/s towards 0 deg: (0.1, 0)
    np.testing.assert_allclose(values[:, 0:2], np.tile([3.0 * math.cos(math.radians(30.0)), 1.5], (70, 1)), atol=1e-3)
    np.testing.assert_allclose(values[:, 2:4], np.tile([0.1, 0.0], (70, 1)), atol=1e-3)
    # the estimate is not the truth, but close: within 10 m (GPS) for buoys, 0.5 m for eBots after 3 s
    truth = np.array([[float(row["x"]), float(row["y"])] for row in rows])
    error = np.hypot(*(values[:, 4:6] - truth).T)
    ebot = np.array([row["body"] == "ebot" for row in rows])
    assert error[ebot].max() < 0.5
    assert error[~ebot].max() < 10.0
    assert error[~ebot].max() > 0.0


def test_ekf_and_mpc_vessel_options_drive_a_buoy() -> None:
    # The EKF and the MPC in the loop (a short run): the buoy reaches the wished 0.5 m/s east and its
    # believed position stays within a few metres of the truth.
    import numpy as np

    from sitl.experiments.scenario import validate_scenario
    from sitl.fleets.fleet import LockstepFleet

    scenario = validate_scenario(
        {
            "name": "ekf-mpc",
            "duration_s": 40.0,
            "dt_s": 0.5,
            "seed": 3,
            "fidelity": "physics",
            "vessel": {"estimator": "ekf", "controller": "mpc"},
            "groups": [
                {
                    "name": "b",
                    "count": 2,
                    "body": "buoy",
                    "behavior": "waypoints",
                    "params": {"waypoints": [[500.0, 0.0]], "speed": 0.5},
                    "start": {"box": {"min": [0.0, 0.0], "max": [10.0, 10.0]}},
                }
            ],
        },
        "test",
    )
    fleet = LockstepFleet(scenario)
    for _ in range(60):
        fleet.step()
    bodies = fleet.bodies
    assert bodies.buoy_vessels.use_ekf and bodies.buoy_vessels.use_mpc
    np.testing.assert_allclose(bodies.velocity[:, 0], 0.5, atol=0.08)
    believed, _, _ = bodies.believed()
    assert np.hypot(*(believed - bodies.position).T).max() < 6.0
    assert bodies.mpc_fallbacks == 0
