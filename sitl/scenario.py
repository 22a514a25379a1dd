"""Scenario files: TOML, validated with clear errors that name the file and the key.

A scenario says what world, which agents (groups with a body and a behaviour),
which network, which scheduled events and which metrics. `load_scenario` reads
a packaged name or a path; `Scenario.model_validate` builds one from a dict
(as the examples do in Python).
"""

from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from bob_autonomy.behavior_config import BehaviorChoice, build_dataclass
from bob_autonomy.geodesy import LocalFrame
from sitl.environment import CurrentSpec, Environment, WindSpec
from sitl.mesh_security import MeshSecuritySpec
from sitl.radio import RadioChannel
from sitl.sensors import CompassSpec, EncoderSpec, GpsSpec, ImuSpec, LightSpec, RangeSpec

PositiveFloat = Annotated[float, Field(gt=0)]
Point = tuple[float, float]


class ScenarioError(ValueError):
    """A scenario that cannot be used; the message names the source and the key."""


class Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


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
    spacing_m: PositiveFloat
    kind: Literal["triangular", "square"] = "triangular"
    angle_deg: float = 0.0


class Start(Model):
    """Where a group starts: uniformly at random in `box`, or on the sites of a `lattice`.

    heading_deg: in degrees, or "random". min_separation_m: least distance
    between random starts in the box, m (a lattice is spaced by its `spacing_m`).
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
    """

    name: str
    count: int = Field(ge=1)
    body: Literal["buoy", "ebot"]
    start: Start
    thrust_fraction: float = Field(default=1.0, gt=0, le=1)


class Event(Model):
    """Something scheduled at `t_s`: agents change behaviour, or are removed.

    The agents are `agents` (indices), or `count` of them (or a `fraction`,
    rounded, at least one) drawn with the seed from `group` (or from everyone
    still active), or every active agent inside `box` (e.g. to open a gap).
    """

    t_s: float = Field(ge=0)
    action: Literal["set-behavior", "remove"]
    agents: list[int] | None = None
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
    polygon: list[Point] = Field(min_length=3)
    walls: bool = True


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


class NetworkSpec(Model):
    """Broadcast radio: range (m), broadcast period (s), neighbour expiry (s).

    `radio`: parameters of the lossy channel model (sitl.radio.RadioChannel);
    absent means perfect delivery within range.
    """

    range_m: PositiveFloat = 300.0
    broadcast_period_s: PositiveFloat = 0.1
    expiry_s: PositiveFloat = 1.0
    radio: dict[str, float] | None = None
    security: MeshSecuritySpec = MeshSecuritySpec()  # fleet key, plausibility, intruders, faults: sitl.mesh_security

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
    """Wind and current (physics fidelity): parameters of sitl.environment.WindSpec and CurrentSpec.

    wind: speed_mps, toward_deg (direction it blows towards, deg from east CCW),
    gust_intensity, gust_time_constant_s. current: speed_mps, toward_deg, grid.
    """

    wind: dict[str, float] = {}
    current: dict[str, Any] = {}

    @model_validator(mode="after")
    def _buildable(self) -> EnvironmentSpec:
        self.specs()
        return self

    def specs(self) -> tuple[WindSpec, CurrentSpec]:
        return (
            build_dataclass(WindSpec, self.wind, "wind parameter(s)"),
            build_dataclass(CurrentSpec, self.current, "current parameter(s)"),
        )

    def build(self, rng: np.random.Generator) -> Environment:
        wind, current = self.specs()
        return Environment(wind, current, rng)


SENSOR_SPECS = {
    "gps": GpsSpec,
    "compass": CompassSpec,
    "imu": ImuSpec,
    "encoders": EncoderSpec,
    "ranges": RangeSpec,
    "light": LightSpec,
}


class SensorsSpec(Model):
    """Sensor models (physics fidelity), overriding the defaults of sitl.sensors' specs."""

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
    seed: int = 0
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
        for k, event in enumerate(self.events):
            if event.group is not None and event.group not in names:
                raise ValueError(f"events[{k}].group {event.group!r} is not a group ({names})")
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
            if agents <= others:
                raise ScenarioError(f"--agents {agents}: the other groups already hold {others} agents")
            for group in data["groups"]:
                if group["name"] == target:
                    group["count"] = agents - others
        return validate_scenario(data, "command-line overrides")


def _describe(error: ValidationError, source: str) -> str:
    lines = [f"{source}: invalid scenario"]
    for item in error.errors():
        key = ".".join(str(p) for p in item["loc"]) or "(top level)"
        got = item.get("input")
        shown = "" if isinstance(got, dict) else f" (got {got!r})"
        lines.append(f"  key '{key}': {item['msg']}{shown}")
    return "\n".join(lines)


def validate_scenario(data: dict[str, Any], source: str) -> Scenario:
    """A Scenario from a dict; ScenarioError names `source` and every bad key."""
    try:
        return Scenario.model_validate(data)
    except ValidationError as error:
        raise ScenarioError(_describe(error, source)) from None


PACKAGED = resources.files("sitl") / "scenarios"


def packaged_scenarios() -> dict[str, str]:
    """Name -> one-line description of the scenarios shipped with the package."""
    out = {}
    for entry in sorted(PACKAGED.iterdir(), key=lambda e: e.name):
        if entry.name.endswith(".toml"):
            data = tomllib.loads(entry.read_text())
            out[entry.name[:-5]] = str(data.get("description", "")).strip().splitlines()[0:1]
    return {k: (v[0] if v else "") for k, v in out.items()}


def load_scenario(name_or_path: str | Path) -> Scenario:
    """A packaged scenario by name, or a TOML file by path."""
    path = Path(name_or_path)
    if path.suffix == ".toml" or path.is_file():
        if not path.is_file():
            raise ScenarioError(f"{path}: no such scenario file")
        text, source = path.read_bytes(), str(path)
    else:
        entry = PACKAGED / f"{name_or_path}.toml"
        if not entry.is_file():
            known = ", ".join(packaged_scenarios())
            raise ScenarioError(f"no scenario named {name_or_path!r}; packaged scenarios: {known}")
        text, source = entry.read_bytes(), f"scenario {name_or_path!r}"
    try:
        data = tomllib.loads(text.decode("utf-8"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as error:
        raise ScenarioError(f"{source}: not valid TOML: {error}") from None
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
