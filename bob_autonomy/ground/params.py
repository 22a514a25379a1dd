"""The autonomy process's parameters: declared, typed, range-checked, persisted atomically.

A ground station reads and writes these through the MAVLink parameter protocol (`bob_autonomy.ground.gcs`); a
mission script through `bob_autonomy.ground.mission`. Every parameter has a MAVLink id of at most 16 characters,
a MAVLink type (MAV_PARAM_TYPE_INT32 or MAV_PARAM_TYPE_REAL32), a default and an inclusive range.
`ParameterStore.set` refuses unknown names, non-finite, non-integral (for INT32) and out-of-range values
with a `ParamError` whose message says why, and applies nothing then.

Besides the parameters the store keeps the uploaded goal list and geofence polygon (lists of (lat, lon)
in degrees, WGS-84), so that a restart keeps the fence the operator set.

Persistence (`path`): a JSON file, rewritten whole after every change: written to a temporary file in the
same directory, flushed and fsynced, then renamed over the old file with `os.replace` (atomic on POSIX and
Windows), so a crash leaves either the old or the new file, never half of one. On load, a file that cannot
be parsed, has values of the wrong type or out of range is *corrupt*: a warning naming the file and the
problem is logged (and kept in `load_problem` for the ground station), the file is renamed aside to
`<name>.corrupt-<n>` (n = 1, 2, ...: never overwriting an earlier one) and the defaults are used.
The same holds for a file that cannot be read at all: not UTF-8, nested too deeply for the parser
(RecursionError), larger than `MAX_FILE_BYTES` (1 MiB; a full file with 500 goals and 100 fence vertices
is about 40 kB), a directory, FIFO or device in its place, or an OSError such as a permission error. So a
service restart never meets the same bad file twice. Loading never raises. (A directory is moved aside only
when empty, as a container runtime creates for a missing bind-mounted file; one with files in it is a wrong
path, reported at every start and left alone.)
Unknown parameter names in a file (e.g. written by a newer version) only give a warning.

At start (construction with a path), temporary files `.<name>.XXXXXXXX.tmp` that an interrupted atomic
write left in the file's directory are removed (logged), so killed writes do not accumulate.

Goal coupling: BOB_GOAL_LAT / BOB_GOAL_LON are the first goal. Setting the goal list (command or mission
upload) sets both; setting either parameter replaces the goal list by the single goal they make
(both 0 = no goal).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import re
import stat
import tempfile
import threading
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from bob_autonomy.core.safe_read import (
    MAX_SETTINGS_FILE_BYTES,
    UnreadableFileError,
    describe_parse_error,
    read_small_file,
)

__all__ = [
    "BEHAVIOR_NAMES",
    "FAILSAFE_ACTIONS",
    "PARAMS",
    "PARAM_TYPE_INT32",
    "PARAM_TYPE_REAL32",
    "LatLon",
    "ParamError",
    "ParamSpec",
    "ParameterStore",
    "validate_latlon",
]

logger = logging.getLogger(__name__)

PARAM_TYPE_INT32 = 6  # MAV_PARAM_TYPE_INT32
PARAM_TYPE_REAL32 = 9  # MAV_PARAM_TYPE_REAL32
FILE_FORMAT = "bob-autonomy-params"
FILE_VERSION = 1
MAX_GOALS = 500
MAX_FENCE_VERTICES = 100
MAX_FILE_BYTES = MAX_SETTINGS_FILE_BYTES  # a parameter file larger than this is set aside unread

LatLon = tuple[float, float]

# BOB_BEHAVIOR is an index into this tuple. Append only: persisted files and mission scripts hold indices.
BEHAVIOR_NAMES: tuple[str, ...] = (
    "bob-rule",
    "heading-consensus",
    "hold-heading",
    "perimeter-defense",
    "search-rendezvous",
    "marching",
    "area-coverage",
    "waypoints",
    "hold-position",
)

# What BOB_GCS_FS_ACT and BOB_FENCE_ACT ask the process to do.
FAILSAFE_ACTIONS: dict[int, str] = {0: "continue", 1: "hold", 2: "return to rally"}


class ParamError(ValueError):
    """A parameter (or goal / fence) could not be set; the message names it and says why."""


@dataclass(frozen=True)
class ParamSpec:
    """One declared parameter: MAVLink id (<= 16 chars), kind "int" (INT32) or "float" (REAL32), default,
    inclusive range [minimum, maximum], units and a one-line description."""

    name: str
    kind: str
    default: float
    minimum: float
    maximum: float
    units: str
    description: str

    @property
    def mav_type(self) -> int:
        """MAV_PARAM_TYPE_INT32 or MAV_PARAM_TYPE_REAL32."""
        return PARAM_TYPE_INT32 if self.kind == "int" else PARAM_TYPE_REAL32

    def check(self, value: object) -> float | int:
        """The value as it would be stored (int for INT32, float for REAL32); ParamError when it is not a
        finite number, not integral for an INT32, or out of range."""
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ParamError(f"{self.name}: {_short(value)} is not a number")
        bounds = f"[{_fmt(self.minimum)}, {_fmt(self.maximum)}]"
        try:
            v = float(value)
        except OverflowError:  # an int beyond float range (a JSON file can hold one)
            raise ParamError(f"{self.name}: {_short(value)} out of range {bounds}") from None
        if not math.isfinite(v):
            raise ParamError(f"{self.name}: {value!r} is not finite")
        if self.kind == "int":
            if v != round(v):
                raise ParamError(f"{self.name}: {value!r} is not an integer")
            v = round(v)
        if not self.minimum <= v <= self.maximum:
            raise ParamError(f"{self.name}: {_short(value)} out of range {bounds}")
        return int(v) if self.kind == "int" else float(v)


def _fmt(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else repr(float(x))


def _short(value: object, limit: int = 40) -> str:
    """repr(value), cut to `limit` characters (a hostile file's values can be megabytes long)."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 128:
        return f"<integer of about {int(value.bit_length() * 0.30103)} digits>"  # repr() of it may be refused
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _action_doc(what: str) -> str:
    return f"{what}: " + ", ".join(f"{k} {v}" for k, v in FAILSAFE_ACTIONS.items())


PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("BOB_BEHAVIOR", "int", 0, 0, len(BEHAVIOR_NAMES) - 1, "",
              "behaviour to run, index into " + ", ".join(f"{i} {n}" for i, n in enumerate(BEHAVIOR_NAMES))),
    ParamSpec("BOB_P0_M", "float", 10.0, 0.1, 1000.0, "m", "equilibrium distance p0 between neighbours (eq. 5)"),
    ParamSpec("BOB_H", "int", 0, 0, 1, "", "H of eq. 5: 0 aggregate, 1 seek the goal / follow the leader"),
    ParamSpec("BOB_SPD_SCALE", "float", 0.5, 0.0, 10.0, "m/s", "desired speed per unit of the behaviour's v_i"),
    ParamSpec("BOB_MAX_SPD_MPS", "float", 1.0, 0.0, 5.0, "m/s", "cap on the behaviour's desired speed"),
    ParamSpec("BOB_RTL_SPD_MPS", "float", 0.5, 0.0, 5.0, "m/s", "speed when returning to the rally point"),
    ParamSpec("BOB_GOAL_LAT", "float", 0.0, -90.0, 90.0, "deg", "latitude of the (first) goal; 0, 0 = none"),
    ParamSpec("BOB_GOAL_LON", "float", 0.0, -180.0, 180.0, "deg", "longitude of the (first) goal; 0, 0 = none"),
    ParamSpec("BOB_GOAL_R_M", "float", 0.0, 0.0, 1000.0, "m", "the goal pull fades inside this radius (0 never)"),
    ParamSpec("BOB_LEADER_ID", "int", 0, 0, 255, "", "MAVLink system id of the leader to follow, 0 = none"),
    ParamSpec("BOB_FENCE_EN", "int", 0, 0, 1, "", "1 = enforce the uploaded geofence polygon"),
    ParamSpec("BOB_FENCE_ACT", "int", 1, 0, 2, "", _action_doc("on leaving the fence")),
    ParamSpec("BOB_GCS_FS_ACT", "int", 0, 0, 2, "", _action_doc("on losing the ground station")),
    ParamSpec("BOB_GCS_FS_S", "float", 30.0, 0.0, 3600.0, "s", "ground station silent this long = lost (0 off)"),
    ParamSpec("BOB_RALLY_LAT", "float", 0.0, -90.0, 90.0, "deg", "latitude of the rally point"),
    ParamSpec("BOB_RALLY_LON", "float", 0.0, -180.0, 180.0, "deg", "longitude of the rally point"),
    ParamSpec("BOB_POS_HZ", "float", 1.0, 0.0, 10.0, "Hz", "rate of GLOBAL_POSITION_INT reports (0 off)"),
)  # fmt: skip

_SPECS = {spec.name: spec for spec in PARAMS}
assert all(len(name) <= 16 for name in _SPECS), "MAVLink parameter ids have at most 16 characters"

ChangeCallback = Callable[[str, float | int, float | int], None]


def validate_latlon(point: object, what: str = "point") -> LatLon:
    """(lat, lon) in degrees as floats; ParamError unless a finite pair within [-90, 90] x [-180, 180]."""
    if isinstance(point, str | bytes):
        raise ParamError(f"{what}: {_short(point)} is not a (lat, lon) pair")
    try:
        lat, lon = (float(v) for v in point)  # type: ignore[union-attr]
    except (TypeError, ValueError, OverflowError):
        raise ParamError(f"{what}: {_short(point)} is not a (lat, lon) pair of finite numbers") from None
    if not (math.isfinite(lat) and math.isfinite(lon)):
        raise ParamError(f"{what}: ({lat}, {lon}) is not finite")
    if not -90.0 <= lat <= 90.0:
        raise ParamError(f"{what}: latitude {lat} out of range [-90, 90]")
    if not -180.0 <= lon <= 180.0:
        raise ParamError(f"{what}: longitude {lon} out of range [-180, 180]")
    return (lat, lon)


def _check_goals(points: Iterable[object]) -> list[LatLon]:
    goals = [validate_latlon(p, f"goal {i}") for i, p in enumerate(points)]
    if len(goals) > MAX_GOALS:
        raise ParamError(f"{len(goals)} goals: at most {MAX_GOALS}")
    return goals


def _check_fence(points: Iterable[object]) -> list[LatLon]:
    fence = [validate_latlon(p, f"fence vertex {i}") for i, p in enumerate(points)]
    if fence and len(fence) < 3:
        raise ParamError(f"a fence polygon needs at least 3 vertices, got {len(fence)}")
    if len(fence) > MAX_FENCE_VERTICES:
        raise ParamError(f"{len(fence)} fence vertices: at most {MAX_FENCE_VERTICES}")
    return fence


class ParameterStore:
    """The declared parameters' values, the goal list and the fence; persisted to `path` (JSON) when given.

    `get(name)` / `store[name]`, `set(name, value)`, `set_many({...})` (all or nothing, one write),
    `names()`, `spec(name)`, `index(name)` / `name_at(index)` (the order of PARAMS, as the parameter
    protocol numbers them), `goals`, `fence`, `set_goals(points)`, `set_fence(points)`.
    `on_change(callback)` registers `callback(name, old, new)`, called after a parameter changed (also for
    the BOB_GOAL_* parameters a goal change implies). `revision` grows by one with every change of anything.
    `load_problem` says why the file was set aside (None when it was fine or absent); `persist_error` why
    the last write failed (the change is kept in memory and the write retried at the next change).
    """

    def __init__(self, path: str | os.PathLike[str] | None = None, *, specs: Sequence[ParamSpec] = PARAMS) -> None:
        self.path = Path(path) if path is not None else None
        if self.path is not None and (self.path.name in ("", ".", "..") or str(path).endswith(("/", os.sep))):
            raise ParamError(f"parameter file {str(path)!r}: give a file name, not a directory")
        self._specs = {s.name: s for s in specs}
        self._order = [s.name for s in specs]
        self._values: dict[str, float | int] = {s.name: s.check(s.default) for s in specs}
        self._goals: list[LatLon] = []
        self._fence: list[LatLon] = []
        self._callbacks: list[ChangeCallback] = []
        self._lock = threading.RLock()
        self.revision = 0
        self.load_problem: str | None = None
        self.persist_error: str | None = None
        if self.path is not None:
            self.remove_stale_temporaries()
            self.load()

    # -- reading -------------------------------------------------------------------------------------------

    def names(self) -> list[str]:
        """Parameter names in protocol order."""
        return list(self._order)

    def __len__(self) -> int:
        return len(self._order)

    def __contains__(self, name: object) -> bool:
        return name in self._specs

    def spec(self, name: str) -> ParamSpec:
        """The declaration of `name`; ParamError for an unknown name."""
        try:
            return self._specs[name]
        except KeyError:
            raise ParamError(f"unknown parameter {name!r}") from None

    def index(self, name: str) -> int:
        """Protocol index (0-based) of `name`."""
        self.spec(name)
        return self._order.index(name)

    def name_at(self, index: int) -> str:
        """Name at a protocol index; ParamError when out of range."""
        if not 0 <= index < len(self._order):
            raise ParamError(f"parameter index {index} out of range [0, {len(self._order) - 1}]")
        return self._order[index]

    def get(self, name: str) -> float | int:
        """Current value of `name` (int for INT32 parameters)."""
        self.spec(name)
        with self._lock:
            return self._values[name]

    __getitem__ = get

    def values(self) -> dict[str, float | int]:
        """A copy of all current values."""
        with self._lock:
            return dict(self._values)

    @property
    def behavior_name(self) -> str:
        """The behaviour BOB_BEHAVIOR selects."""
        return BEHAVIOR_NAMES[int(self.get("BOB_BEHAVIOR"))]

    @property
    def goals(self) -> list[LatLon]:
        """Goal waypoints (lat, lon) in degrees, in order; empty = no goal."""
        with self._lock:
            return list(self._goals)

    @property
    def fence(self) -> list[LatLon]:
        """Geofence inclusion polygon (lat, lon) vertices in degrees; empty = none."""
        with self._lock:
            return list(self._fence)

    def on_change(self, callback: ChangeCallback) -> None:
        """Call `callback(name, old, new)` after every parameter change."""
        self._callbacks.append(callback)

    # -- writing -------------------------------------------------------------------------------------------

    def set(self, name: str, value: float) -> float | int:
        """Validate and apply one value, persist, notify; returns the value now in force. ParamError (nothing
        applied) for an unknown name or a bad value."""
        return self.set_many({name: value})[name]

    def set_many(self, values: Mapping[str, float]) -> dict[str, float | int]:
        """Validate all, then apply all at once (one file write); ParamError and nothing applied if any is
        bad. Setting BOB_GOAL_LAT / BOB_GOAL_LON replaces the goal list by that single goal."""
        checked = {name: self.spec(name).check(value) for name, value in values.items()}
        with self._lock:
            goals = None
            if "BOB_GOAL_LAT" in checked or "BOB_GOAL_LON" in checked:
                lat = checked.get("BOB_GOAL_LAT", self._values["BOB_GOAL_LAT"])
                lon = checked.get("BOB_GOAL_LON", self._values["BOB_GOAL_LON"])
                goals = [] if lat == 0 and lon == 0 else [(float(lat), float(lon))]
            changes = self._apply(checked, goals=goals)
        self._notify(changes)
        return checked

    def set_goals(self, points: Iterable[object]) -> list[LatLon]:
        """Replace the goal list ((lat, lon) deg); BOB_GOAL_LAT / LON follow the first goal (0, 0 if none)."""
        goals = _check_goals(points)
        first = goals[0] if goals else (0.0, 0.0)
        with self._lock:
            changes = self._apply({"BOB_GOAL_LAT": first[0], "BOB_GOAL_LON": first[1]}, goals=goals)
        self._notify(changes)
        return goals

    def set_fence(self, points: Iterable[object]) -> list[LatLon]:
        """Replace the fence polygon ((lat, lon) deg, at least 3 vertices, or none)."""
        fence = _check_fence(points)
        with self._lock:
            self._fence = fence
            self.revision += 1
            self._persist()
        return fence

    def _apply(self, checked: dict[str, float | int], *, goals: list[LatLon] | None) -> list[tuple]:
        changes = []
        for name, value in checked.items():
            old = self._values[name]
            if old != value:
                changes.append((name, old, value))
            self._values[name] = value
        if goals is not None:
            self._goals = goals
        self.revision += 1
        self._persist()
        return changes

    def _notify(self, changes: list[tuple]) -> None:
        for name, old, new in changes:
            for callback in list(self._callbacks):
                try:
                    callback(name, old, new)
                except Exception:  # a bad listener must not break the parameter protocol
                    logger.exception("parameter change callback failed for %s", name)

    # -- persistence ---------------------------------------------------------------------------------------

    def to_document(self) -> dict:
        """What is written to the file."""
        with self._lock:
            return {
                "format": FILE_FORMAT,
                "version": FILE_VERSION,
                "params": dict(self._values),
                "goals": [list(p) for p in self._goals],
                "fence": [list(p) for p in self._fence],
            }

    def _persist(self) -> None:
        if self.path is None:
            return
        try:
            atomic_write_text(self.path, json.dumps(self.to_document(), indent=2) + "\n")
            self.persist_error = None
        except OSError as exc:
            self.persist_error = f"cannot write parameter file {self.path}: {exc}"
            logger.error("%s (the change is kept in memory only)", self.persist_error)

    def load(self) -> None:
        """(Re)load from `path`: a missing file means defaults; a corrupt one is reported, renamed aside and
        replaced by the defaults (see the module docstring)."""
        if self.path is None:
            return
        self.load_problem = None
        try:
            raw = read_small_file(self.path, MAX_FILE_BYTES)
        except FileNotFoundError:
            return
        except UnreadableFileError as exc:
            self._corrupt(str(exc))
            return
        try:
            values, goals, fence = self._parse(raw.decode("utf-8"))
        except ParamError as exc:
            self._corrupt(str(exc))
            return
        except Exception as exc:  # RecursionError, MemoryError, UnicodeDecodeError, ...: any is a bad file
            self._corrupt(describe_parse_error(exc))
            return
        with self._lock:
            self._values.update(values)
            self._goals = goals
            self._fence = fence
            self.revision += 1

    def _parse(self, text: str) -> tuple[dict[str, float | int], list[LatLon], list[LatLon]]:
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ParamError(f"bad JSON: {exc}") from None
        if not isinstance(doc, dict):
            raise ParamError("the top level is not a JSON object")
        if doc.get("format", FILE_FORMAT) != FILE_FORMAT:
            raise ParamError(f"format {doc.get('format')!r} is not {FILE_FORMAT!r}")
        params = doc.get("params", {})
        if not isinstance(params, dict):
            raise ParamError("'params' is not an object")
        values: dict[str, float | int] = {}
        unknown: list[str] = []
        for name, value in params.items():
            spec = self._specs.get(name)
            if spec is None:
                unknown.append(name)
                continue
            if spec.kind == "int" and not (isinstance(value, int) and not isinstance(value, bool)):
                raise ParamError(f"{name}: {_short(value)} is not an integer")
            values[name] = spec.check(value)
        if unknown:  # one line, however many (a newer version's parameters, or junk)
            shown = ", ".join(_short(n) for n in unknown[:10])
            if len(unknown) > 10:
                shown += f" and {len(unknown) - 10} more"
            logger.warning("parameter file %s: unknown parameter(s) %s ignored", self.path, shown)
        for key in ("goals", "fence"):
            if not isinstance(doc.get(key, []), list):
                raise ParamError(f"{key!r} is not a list")
        goals = _check_goals(doc.get("goals", []))
        fence = _check_fence(doc.get("fence", []))
        return values, goals, fence

    def _corrupt(self, problem: str) -> None:
        """Report the file, rename it aside (a file, FIFO or empty directory) and keep the defaults.

        A directory with something in it is left where it is: it is a wrong --params-file (say /etc),
        not a damaged parameter file, and moving it could break more than this process."""
        assert self.path is not None
        aside = _aside_name(self.path)
        try:
            if self.path.is_dir() and not self.path.is_symlink() and any(self.path.iterdir()):
                raise IsADirectoryError(0, "a directory with files in it is not moved; give --params-file a file name")
            os.replace(self.path, aside)
            where = f"; moved to {aside}"
        except OSError as exc:
            where = f"; not moved aside ({exc.strerror or exc})"
        self.load_problem = f"parameter file {self.path} is corrupt ({problem}){where}; using defaults"
        logger.warning("%s", self.load_problem)

    def remove_stale_temporaries(self) -> list[Path]:
        """Delete the temporary files (`.<name>.XXXXXXXX.tmp`, regular files only) that interrupted atomic
        writes of `path` left behind; returns what was removed. Called at start; safe to call again."""
        if self.path is None:
            return []
        pattern = re.compile(rf"\.{re.escape(self.path.name)}\.[A-Za-z0-9_]+\.tmp")
        removed: list[Path] = []
        try:
            entries = list(os.scandir(self.path.parent))
        except OSError:
            return removed  # no directory yet (or not listable): nothing of ours to clean
        for entry in entries:
            if not pattern.fullmatch(entry.name):
                continue
            try:
                if not stat.S_ISREG(entry.stat(follow_symlinks=False).st_mode):
                    continue
                os.unlink(entry.path)
            except OSError as exc:
                logger.warning("parameter file %s: cannot remove leftover %s: %s", self.path, entry.path, exc)
                continue
            removed.append(Path(entry.path))
            logger.warning("parameter file %s: removed %s left by an interrupted write", self.path, entry.path)
        return removed


def _aside_name(path: Path) -> Path:
    n = 1
    while True:
        candidate = path.with_name(f"{path.name}.corrupt-{n}")
        if not candidate.exists():
            return candidate
        n += 1


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    """Write `text` to `path` atomically: temporary file in the same directory, fsync, os.replace, then
    fsync the directory (where the platform allows) so the rename itself survives a power cut."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp_name, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp_name)
        raise
    if hasattr(os, "O_DIRECTORY"):
        with contextlib.suppress(OSError):
            dir_fd = os.open(target.parent, os.O_RDONLY | os.O_DIRECTORY)
            try:
                os.fsync(dir_fd)
            finally:
                os.close(dir_fd)
