"""Scenario files: TOML, validated with clear errors that name the file and the key.

A scenario says what world, which agents (groups with a body and a behaviour),
which network, which scheduled events and which metrics. `load_scenario` reads
a packaged name or a path; `Scenario.model_validate` builds one from a dict
(as the examples do in Python).

What a scenario may hold, so that no file can crash or hang a run:
every number is finite (nan and inf are refused everywhere, also inside the
free-form tables: behaviour parameters, sensors, wind, current); positions are
within +-1e7 m of the origin; `name` is a single safe file name (it names the
default output directory runs/NAME); a room is a simple polygon (at least 3
distinct vertices, no crossing or touching edges, non-zero area); event agent
indices exist; the seed is a non-negative 64-bit integer. Files are read as a
regular file of at most 16 MiB. How large a run may be (agents, agent-steps)
is `sitl.fleets.budget`'s concern.
"""

from __future__ import annotations

import math
import re
import tomllib
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from bob_autonomy.core.behavior_config import BehaviorChoice, build_dataclass
from bob_autonomy.core.geodesy import LocalFrame
from bob_autonomy.core.safe_read import UnreadableFileError, describe_parse_error, read_small_file
from sitl.experiments.metric_params import metric_params_problem
from sitl.radio.channel import RadioChannel
from sitl.radio.mesh_security import MeshSecuritySpec
from sitl.vehicles.sensors import CompassSpec, EncoderSpec, GpsSpec, ImuSpec, LightSpec, RangeSpec
from sitl.world.environment import CurrentSpec, Environment, WindSpec
from sitl.world.waves import WaveSpec

MAX_COORDINATE_M = 1e7  # |x|, |y| of any position: 10,000 km, beyond any local frame (and far from overflow)
MAX_POLYGON_VERTICES = 1000
MAX_SCENARIO_FILE_BYTES = 16 << 20  # room for a gridded current; packaged scenarios are about 2 kB
SAFE_NAME = re.compile(r"[^\W_][\w.+-]{0,99}")  # one path component: no '/', '\\', '..', leading '.' or '-'
# Every model refuses nan and inf (pydantic's allow_inf_nan=False, for every float field).
MODEL_CONFIG = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

PositiveFloat = Annotated[float, Field(gt=0)]
Coordinate = Annotated[float, Field(ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M)]
Point = tuple[Coordinate, Coordinate]


class ScenarioError(ValueError):
    """A scenario that cannot be used; the message names the source and the key."""


class Model(BaseModel):
    model_config = MODEL_CONFIG


def non_finite_numbers(data: Any, limit: int = 20) -> list[tuple[str, float]]:
    """(dotted key, value) of up to `limit` nan or infinite floats anywhere in nested dicts and lists.

    Iterative, so a deeply nested value cannot exhaust the stack. Used for the free-form tables (behaviour
    parameters, sensors, wind, current) that the typed fields' allow_inf_nan=False does not reach.
    """
    found: list[tuple[str, float]] = []
    stack: list[tuple[str, Any]] = [("", data)]
    while stack and len(found) < limit:
        key, value = stack.pop()
        if isinstance(value, float | np.floating) and not math.isfinite(value):
            found.append((key or "(top level)", float(value)))
        elif isinstance(value, dict):
            stack.extend((f"{key}.{k}" if key else str(k), v) for k, v in reversed(list(value.items())))
        elif isinstance(value, list | tuple):
            stack.extend((f"{key}.{i}" if key else str(i), v) for i, v in reversed(list(enumerate(value))))
    return found


def polygon_problem(points: Any) -> str | None:
    """Why `points` ((n, 2), m) is not a simple polygon with non-zero area, or None when it is.

    Simple: no two edges cross or touch except consecutive edges at their shared vertex (which must not
    fold back along each other). Orientation tests in numpy over all pairs of edges (n <= 1000).
    """
    p = np.asarray(points, dtype=float)
    n = len(p)
    if n < 3:
        return f"needs at least 3 vertices, got {n}"
    a, b = p, np.roll(p, -1, axis=0)  # edge k runs from vertex k to vertex k + 1 (the last closes the ring)
    same = np.flatnonzero(np.all(a == b, axis=1))
    if same.size:
        k = int(same[0])
        return f"vertices {k} and {(k + 1) % n} are the same point {tuple(p[k].tolist())}"
    centred = p - p.mean(axis=0)
    if np.linalg.matrix_rank(centred, tol=1e-12 * float(np.abs(centred).max())) < 2:
        return "has zero area (all its vertices are on one line)"

    def orient(o: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
        return np.sign((q[:, 0] - o[:, 0]) * (r[:, 1] - o[:, 1]) - (q[:, 1] - o[:, 1]) * (r[:, 0] - o[:, 0]))

    def on_segment(o: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:  # r on segment o-q, if collinear
        return (np.minimum(o, q) <= r).all(axis=1) & (r <= np.maximum(o, q)).all(axis=1)

    # Consecutive edges k, k + 1 share a vertex; they overlap when the second folds back along the first.
    nxt = np.roll(b, -1, axis=0)
    fold = (orient(a, b, nxt) == 0) & (np.sum((b - a) * (nxt - b), axis=1) < 0)
    if fold.any():
        k = int(np.flatnonzero(fold)[0])
        return f"edges {k} and {(k + 1) % n} fold back on each other at vertex {(k + 1) % n}"
    i, j = np.triu_indices(n, k=2)
    keep = ~((i == 0) & (j == n - 1))  # the first and last edges share vertex 0
    i, j = i[keep], j[keep]
    d1, d2 = orient(a[j], b[j], a[i]), orient(a[j], b[j], b[i])
    d3, d4 = orient(a[i], b[i], a[j]), orient(a[i], b[i], b[j])
    meet = (d1 * d2 < 0) & (d3 * d4 < 0)
    meet |= (d1 == 0) & on_segment(a[j], b[j], a[i])
    meet |= (d2 == 0) & on_segment(a[j], b[j], b[i])
    meet |= (d3 == 0) & on_segment(a[i], b[i], a[j])
    meet |= (d4 == 0) & on_segment(a[i], b[i], b[j])
    if meet.any():
        k = int(np.flatnonzero(meet)[0])
        e, f = int(i[k]), int(j[k])
        return f"crosses itself: edge {e} (vertex {e} to {(e + 1) % n}) meets edge {f} (vertex {f} to {(f + 1) % n})"
    extent = float(np.ptp(p, axis=0).max())
    area = 0.5 * float(np.sum(a[:, 0] * b[:, 1] - b[:, 0] * a[:, 1]))
    if abs(area) <= 1e-12 * extent * extent:  # simple yet no area: only in degenerate floating-point cases
        return "has zero area"
    return None


class Box(Model):
    """An axis-aligned box, m: [[x_min, y_min], [x_max, y_max]]."""

    min: Point
    max: Point

    @model_validator(mode="after")
    def _ordered(self) -> Box:
        if self.max[0] < self.min[0] or self.max[1] < self.min[1]:
            raise ValueError("max must not be below min")
        return self


class Lattice(Model):
    """A regular lattice of start sites: the `count` sites nearest `center`, m.

    kind: "triangular" (equilateral triangles, each inner site with 6
    neighbours at `spacing_m`) or "square". One site is at `center` (m);
    `angle_deg` turns the lattice about it (deg, counter-clockwise from east).
    """

    center: Point
    spacing_m: Annotated[float, Field(gt=0, le=MAX_COORDINATE_M)]
    kind: Literal["triangular", "square"] = "triangular"
    angle_deg: float = 0.0


class Start(Model):
    """Where a group starts: uniformly at random in `box`, or on the sites of a `lattice`.

    heading_deg: in degrees, or "random". min_separation_m: least distance
    between random starts in the box and from every agent of the groups before
    this one, m (a lattice is spaced by its `spacing_m`).
    """

    box: Box | None = None
    lattice: Lattice | None = None
    heading_deg: float | Literal["random"] = "random"
    min_separation_m: float = Field(default=0.0, ge=0)

    @model_validator(mode="after")
    def _one_placement(self) -> Start:
        if (self.box is None) == (self.lattice is None):
            raise ValueError("give exactly one of 'box' or 'lattice'")
        if self.lattice is not None and self.min_separation_m:
            raise ValueError("'min_separation_m' is for a 'box'; a lattice is spaced by its 'spacing_m'")
        return self


class Group(BehaviorChoice):
    """`count` agents with the same body, start region and behaviour.

    thrust_fraction: the buoys' maximum thrust as a fraction of nominal (a weak
    battery is below 1); physics fidelity only.
    top_speed_mps, turning_radius_m, steering: motorboats only (sitl.vehicles.motorboat):
    speed at full throttle (m/s, default 2), turning radius at full steering
    (m, default 3) and "outboard" (default) or "rudder".
    """

    model_config = MODEL_CONFIG

    name: str
    count: int = Field(ge=1)
    body: Literal["buoy", "ebot", "motorboat"]
    start: Start
    thrust_fraction: float = Field(default=1.0, gt=0, le=1)
    top_speed_mps: float | None = Field(default=None, gt=0, le=30)
    turning_radius_m: float | None = Field(default=None, gt=0, le=500)
    steering: Literal["outboard", "rudder"] | None = None

    @model_validator(mode="after")
    def _motorboat_keys(self) -> Group:
        given = [k for k in ("top_speed_mps", "turning_radius_m", "steering") if getattr(self, k) is not None]
        if given and self.body != "motorboat":
            raise ValueError(f'{", ".join(given)}: only for body = "motorboat" (this group is {self.body!r})')
        if self.body == "motorboat":
            self.motorboat_params()  # a boat that cannot be built (e.g. a turn harder than a hull can pull) is refused
        return self

    def motorboat_params(self):  # -> sitl.vehicles.motorboat.MotorboatParams
        """The group's motorboat parameters (defaults where not given)."""
        from sitl.vehicles.motorboat import MotorboatParams, params_for

        d = MotorboatParams()
        speed, radius = self.top_speed_mps or d.top_speed_mps, self.turning_radius_m or d.turning_radius_m
        return params_for(speed, radius, self.steering or d.steering)


class Event(Model):
    """Something scheduled at `t_s`: agents change behaviour, or are removed.

    The agents are `agents` (indices), or `count` of them (or a `fraction`,
    rounded, at least one) drawn with the seed from `group` (or from everyone
    still active), or every active agent inside `box` (e.g. to open a gap).
    """

    t_s: float = Field(ge=0)
    action: Literal["set-behavior", "remove"]
    agents: list[Annotated[int, Field(ge=0)]] | None = None
    count: int | None = Field(default=None, ge=1)
    fraction: float | None = Field(default=None, gt=0, le=1)
    box: Box | None = None
    group: str | None = None
    choice: BehaviorChoice | None = None

    @model_validator(mode="after")
    def _consistent(self) -> Event:
        if sum(x is not None for x in (self.agents, self.count, self.fraction, self.box)) != 1:
            raise ValueError("give exactly one of 'agents', 'count', 'fraction' or 'box'")
        if self.action == "set-behavior" and self.choice is None:
            raise ValueError("'set-behavior' needs a 'choice' table with a 'behavior'")
        return self


class Room(Model):
    """A polygon (m); its edges are walls unless `walls` is false."""

    name: str = ""
    polygon: list[Point] = Field(min_length=3, max_length=MAX_POLYGON_VERTICES)
    walls: bool = True

    @field_validator("polygon")
    @classmethod
    def _simple(cls, polygon: list[Point]) -> list[Point]:
        problem = polygon_problem(polygon)
        if problem is not None:
            raise ValueError(f"the polygon {problem}; a room must be a simple polygon with non-zero area")
        return polygon


class Light(Model):
    """A light source at `position`, or placed at random in `box`; power in W."""

    position: Point | None = None
    box: Box | None = None
    power_w: PositiveFloat = 20.0

    @model_validator(mode="after")
    def _placed(self) -> Light:
        if (self.position is None) == (self.box is None):
            raise ValueError("give exactly one of 'position' or 'box'")
        return self


class WorldSpec(Model):
    rooms: list[Room] = []
    walls: list[tuple[Point, Point]] = []
    lights: list[Light] = []
    light_height_m: float = Field(default=0.3, ge=0)

    @field_validator("walls")
    @classmethod
    def _walls_have_length(cls, walls: list[tuple[Point, Point]]) -> list[tuple[Point, Point]]:
        for k, (start, end) in enumerate(walls):
            if start == end:
                raise ValueError(f"wall {k} starts and ends at the same point {start}")
        return walls


class NetworkSpec(Model):
    """Broadcast radio: range (m), broadcast period (s), neighbour expiry (s).

    `radio`: parameters of the lossy channel model (sitl.radio.channel.RadioChannel);
    absent means perfect delivery within range.
    """

    range_m: PositiveFloat = 300.0
    broadcast_period_s: PositiveFloat = 0.1
    expiry_s: PositiveFloat = 1.0
    radio: dict[str, float] | None = None
    security: MeshSecuritySpec = (
        MeshSecuritySpec()
    )  # fleet key, plausibility, intruders, faults: sitl.radio.mesh_security

    @model_validator(mode="after")
    def _radio(self) -> NetworkSpec:
        self.channel()
        return self

    def channel(self) -> RadioChannel | None:
        """The radio channel model, or None for perfect delivery."""
        if self.radio is None:
            return None
        return build_dataclass(RadioChannel, self.radio, "radio parameter(s)")


class EnvironmentSpec(Model):
    """Wind and current (physics fidelity): parameters of sitl.world.environment.WindSpec and CurrentSpec.

    wind: speed_mps, toward_deg (direction it blows towards, deg from east CCW),
    gust_intensity, gust_time_constant_s. current: speed_mps, toward_deg, grid. waves (sitl.world.waves.WaveSpec):
    tilt_deg (0: flat water), period_s, length_m, toward_deg; they roll and pitch buoys and motorboats, whose IMU
    and ATTITUDE then carry the tilt.
    """

    wind: dict[str, float] = {}
    current: dict[str, Any] = {}
    waves: dict[str, float] = {}

    @model_validator(mode="after")
    def _buildable(self) -> EnvironmentSpec:
        self.specs()
        return self

    def specs(self) -> tuple[WindSpec, CurrentSpec, WaveSpec]:
        return (
            build_dataclass(WindSpec, self.wind, "wind parameter(s)"),
            build_dataclass(CurrentSpec, self.current, "current parameter(s)"),
            build_dataclass(WaveSpec, self.waves, "waves parameter(s)"),
        )

    def build(self, rng: np.random.Generator) -> Environment:
        wind, current, waves = self.specs()
        return Environment(wind, current, rng, waves)


SENSOR_SPECS = {
    "gps": GpsSpec,
    "compass": CompassSpec,
    "imu": ImuSpec,
    "encoders": EncoderSpec,
    "ranges": RangeSpec,
    "light": LightSpec,
}


class SensorsSpec(Model):
    """Sensor models (physics fidelity), overriding the defaults of sitl.vehicles.sensors' specs."""

    gps: dict[str, Any] = {}
    compass: dict[str, Any] = {}
    imu: dict[str, Any] = {}
    encoders: dict[str, Any] = {}
    ranges: dict[str, Any] = {}
    light: dict[str, Any] = {}

    @model_validator(mode="after")
    def _buildable(self) -> SensorsSpec:
        self.specs()
        return self

    def specs(self) -> dict[str, Any]:
        return {
            name: build_dataclass(cls, getattr(self, name), f"{name} parameter(s)")
            for name, cls in SENSOR_SPECS.items()
        }


class VesselSpec(Model):
    """The autonomy on each vessel (physics fidelity): which pose estimator and which controller.

    estimator: "ekf" (the default: EKFs with filterpy's equations, a water-drift
    state for buoys) or "simple" (alpha-beta GPS tracker / odometry). controller: "mpc" (casadi
    QP, the default) or "simple" (proportional with drag feed-forward). The
    MPC's horizon step is the scenario's dt_s. link: "mavlink" (the full stack:
    each vehicle sends MAVLink telemetry bytes that the vessel decodes with
    firmware_bridge and gets RC_CHANNELS_OVERRIDE bytes back, in memory) or
    "direct" (readings and commands handed over as objects; faster).
    """

    estimator: Literal["simple", "ekf"] = "ekf"
    controller: Literal["simple", "mpc"] = "mpc"
    link: Literal["direct", "mavlink"] = "mavlink"


class Origin(Model):
    """The swarm's shared origin (WGS-84 degrees); default: Bedok Reservoir, Singapore."""

    lat_deg: float = Field(default=1.3406, ge=-90, le=90)
    lon_deg: float = Field(default=103.9266, ge=-180, le=180)

    def frame(self) -> LocalFrame:
        return LocalFrame(self.lat_deg, self.lon_deg)


class MetricsSpec(Model):
    """Which metrics and figures (`kind`) and their thresholds."""

    kind: Literal[
        "heading-consensus",
        "perimeter-defense",
        "search-exploration",
        "aggregation",
        "leader-follower",
        "avoidance",
        "exploration",
        "radio-table",
        "generic",
    ] = "generic"
    params: dict[str, float | str | list[float]] = {}


class Scenario(Model):
    name: str
    description: str = ""
    duration_s: PositiveFloat
    dt_s: PositiveFloat = 0.1
    seed: int = Field(default=0, ge=0, lt=2**64)
    log_period_s: PositiveFloat = 0.5
    fidelity: Literal["kinematic", "physics"] = "kinematic"
    origin: Origin = Origin()
    environment: EnvironmentSpec = EnvironmentSpec()
    sensors: SensorsSpec = SensorsSpec()
    vessel: VesselSpec = VesselSpec()
    resize_group: str | None = Field(default=None, description="group that --agents resizes (default: the first)")
    world: WorldSpec = WorldSpec()
    network: NetworkSpec = NetworkSpec()
    groups: list[Group] = Field(min_length=1)
    events: list[Event] = []
    metrics: MetricsSpec = MetricsSpec()

    @model_validator(mode="before")
    @classmethod
    def _finite(cls, data: Any) -> Any:
        bad = non_finite_numbers(data, limit=1)
        if bad:
            raise ValueError(f"key {bad[0][0]!r} must be a finite number, got {bad[0][1]}")
        return data

    @field_validator("name")
    @classmethod
    def _safe_name(cls, name: str) -> str:
        if not SAFE_NAME.fullmatch(name):
            raise ValueError(
                "must be a single file name (it names the output directory runs/NAME): 1 to 100 letters, digits, "
                "'.', '_', '+' or '-', starting with a letter or digit"
            )
        return name

    @model_validator(mode="after")
    def _references(self) -> Scenario:
        names = [g.name for g in self.groups]
        if len(set(names)) != len(names):
            raise ValueError(f"group names must be unique, got {names}")
        if self.resize_group is not None and self.resize_group not in names:
            raise ValueError(f"resize_group {self.resize_group!r} is not a group ({names})")
        problem = self.network.security.reference_problem(names, sum(g.count for g in self.groups))
        if problem:
            raise ValueError(problem)
        n = sum(g.count for g in self.groups)
        for k, event in enumerate(self.events):
            if event.group is not None and event.group not in names:
                raise ValueError(f"events[{k}].group {event.group!r} is not a group ({names})")
            if event.agents and max(event.agents) >= n:
                raise ValueError(f"events.{k}.agents: agent {max(event.agents)} does not exist (agents 0..{n - 1})")
        problem = metric_params_problem(self.metrics.kind, dict(self.metrics.params), n)
        if problem:
            raise ValueError(f"metrics.params: {problem}")
        return self

    @property
    def n_agents(self) -> int:
        return sum(g.count for g in self.groups)

    def with_overrides(
        self,
        agents: int | None = None,
        seed: int | None = None,
        duration_s: float | None = None,
        fidelity: str | None = None,
        estimator: str | None = None,
        controller: str | None = None,
        link: str | None = None,
    ) -> Scenario:
        """A copy with the command-line overrides applied (and validated)."""
        data = self.model_dump()
        if fidelity is not None:
            data["fidelity"] = fidelity
        if estimator is not None:
            data["vessel"]["estimator"] = estimator
        if controller is not None:
            data["vessel"]["controller"] = controller
        if link is not None:
            data["vessel"]["link"] = link
        if seed is not None:
            data["seed"] = seed
        if duration_s is not None:
            data["duration_s"] = duration_s
        if agents is not None:
            target = self.resize_group or self.groups[0].name
            others = sum(g.count for g in self.groups if g.name != target)
            if agents < 1:
                raise ScenarioError(f"--agents must be at least 1, got {agents}")
            if agents <= others:
                raise ScenarioError(
                    f"--agents {agents}: the other groups already hold {others} agents and group {target!r}, "
                    f"which --agents resizes, needs at least 1: give --agents {others + 1} or more"
                )
            for group in data["groups"]:
                if group["name"] == target:
                    group["count"] = agents - others
        return validate_scenario(data, "command-line overrides")


MAX_REPORTED_ERRORS = 20


def _shown(value: Any, limit: int = 80) -> str:
    text = repr(value) if not isinstance(value, list | tuple) or len(value) < 50 else f"<{len(value)} items>"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _describe(error: ValidationError, source: str) -> str:
    lines = [f"{source}: invalid scenario"]
    items = error.errors()
    for item in items[:MAX_REPORTED_ERRORS]:
        key = ".".join(str(p) for p in item["loc"]) or "(top level)"
        got = item.get("input")
        shown = "" if isinstance(got, dict) else f" (got {_shown(got)})"
        message = item["msg"].removeprefix("Value error, ")
        lines.append(f"  key '{key}': {message}{shown}")
    if len(items) > MAX_REPORTED_ERRORS:
        lines.append(f"  ... and {len(items) - MAX_REPORTED_ERRORS} more")
    return "\n".join(lines)


def validate_scenario(data: dict[str, Any], source: str) -> Scenario:
    """A Scenario from a dict; ScenarioError names `source` and every bad key (every nan or inf too)."""
    bad = non_finite_numbers(data, limit=MAX_REPORTED_ERRORS)
    if bad:
        keys = "\n".join(f"  key '{key}': must be a finite number (got {value})" for key, value in bad)
        raise ScenarioError(f"{source}: invalid scenario\n{keys}")
    try:
        return Scenario.model_validate(data)
    except ValidationError as error:
        raise ScenarioError(_describe(error, source)) from None
    except RecursionError:
        raise ScenarioError(f"{source}: invalid scenario: nested too deeply") from None


PACKAGED = resources.files("sitl.experiments") / "scenarios"


def packaged_scenarios() -> dict[str, str]:
    """Name -> one-line description of the scenarios shipped with the package."""
    out = {}
    for entry in sorted(PACKAGED.iterdir(), key=lambda e: e.name):
        if entry.name.endswith(".toml"):
            data = tomllib.loads(entry.read_text())
            out[entry.name[:-5]] = str(data.get("description", "")).strip().splitlines()[0:1]
    return {k: (v[0] if v else "") for k, v in sorted(out.items())}  # by name: "a" before "a-b"


def load_scenario(name_or_path: str | Path) -> Scenario:
    """A packaged scenario by name, or a TOML file by path (a regular file of at most 16 MiB)."""
    path = Path(name_or_path)
    try:
        is_file = path.is_file()
    except (OSError, ValueError) as error:  # a name too long for the file system, a NUL byte
        raise ScenarioError(f"{str(name_or_path)[:100]!r}: cannot be a scenario file ({error})") from None
    if path.suffix == ".toml" or is_file:
        source = str(path)
        try:
            text = read_small_file(path, MAX_SCENARIO_FILE_BYTES)
        except FileNotFoundError:
            raise ScenarioError(f"{path}: no such scenario file") from None
        except UnreadableFileError as error:
            raise ScenarioError(f"{path}: {error}") from None
    else:
        known = packaged_scenarios()
        if str(name_or_path) not in known:
            raise ScenarioError(f"no scenario named {name_or_path!r}; packaged scenarios: {', '.join(known)}")
        text, source = (PACKAGED / f"{name_or_path}.toml").read_bytes(), f"scenario {name_or_path!r}"
    try:
        data = tomllib.loads(text.decode("utf-8"))
    except tomllib.TOMLDecodeError as error:
        raise ScenarioError(f"{source}: not valid TOML: {error}") from None
    except Exception as error:  # UnicodeDecodeError, RecursionError (deep nesting), huge integers, MemoryError
        raise ScenarioError(f"{source}: not valid TOML: {describe_parse_error(error)}") from None
    return validate_scenario(data, source)


def scenario_to_toml(scenario: Scenario) -> str:
    """The resolved scenario as TOML text (written beside every run's outputs)."""
    return _toml_table(scenario.model_dump(exclude_none=True), [])


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float | np.floating):
        return repr(float(value)) if isinstance(value, float) else str(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def _toml_key(key: str) -> str:
    return key if key.replace("_", "").replace("-", "").isalnum() else _toml_value(key)


def _toml_table(data: dict[str, Any], path: list[str]) -> str:
    scalars = {k: v for k, v in data.items() if not isinstance(v, dict) and not _is_table_list(v)}
    lines = [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in scalars.items()]
    for key, value in data.items():
        if isinstance(value, dict):
            lines += ["", f"[{'.'.join([*path, key])}]", _toml_table(value, [*path, key])]
        elif _is_table_list(value):
            for item in value:
                lines += ["", f"[[{'.'.join([*path, key])}]]", _toml_table(item, [*path, key])]
    return "\n".join(line for line in lines if line is not None).strip() + "\n"


def _is_table_list(value: Any) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(v, dict) for v in value)
