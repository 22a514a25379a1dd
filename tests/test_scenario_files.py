"""Scenario files (sitl/experiments/scenario.py): packaged scenarios, clear errors naming file and key, overrides,
round trip."""

from __future__ import annotations

import copy
import importlib.resources
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sitl.experiments.scenario import (
    PACKAGED,
    Scenario,
    ScenarioError,
    load_scenario,
    packaged_scenarios,
    scenario_to_toml,
    validate_scenario,
)

KNOWN = {"heading-consensus", "perimeter-defense", "search-exploration"}

VALID_TOML = """\
name = "tiny"
description = "two buoys"
duration_s = 2.0

[[groups]]
name = "boats"
count = 2
body = "buoy"
behavior = "heading-consensus"
start = { box = { min = [0.0, 0.0], max = [1.0, 1.0] } }
"""

MINIMAL: dict[str, Any] = tomllib.loads(VALID_TOML)


def write(tmp_path: Path, text: str, name: str = "scenario.toml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def error_of(data: dict[str, Any]) -> str:
    with pytest.raises(ScenarioError) as info:
        validate_scenario(data, "my-file.toml")
    message = str(info.value)
    assert message.startswith("my-file.toml: ")
    return message


def changed(**top: Any) -> dict[str, Any]:
    data = copy.deepcopy(MINIMAL)
    data.update(top)
    return data


def with_group(**fields: Any) -> dict[str, Any]:
    data = copy.deepcopy(MINIMAL)
    data["groups"][0].update(fields)
    return data


# ---------------------------------------------------------------- packaged scenarios


def test_packaged_scenarios_listed_with_descriptions() -> None:
    listed = packaged_scenarios()
    assert set(listed) >= KNOWN
    assert list(listed) == sorted(listed)
    for name, description in listed.items():
        assert description, name
        assert "\n" not in description


@pytest.mark.parametrize("name", sorted(KNOWN))
def test_every_packaged_scenario_loads_by_name_and_path(name: str) -> None:
    scenario = load_scenario(name)
    assert isinstance(scenario, Scenario)
    assert scenario.name == name
    assert scenario.n_agents >= 1
    assert scenario.description.startswith(packaged_scenarios()[name][:40])
    with importlib.resources.as_file(PACKAGED / f"{name}.toml") as path:
        assert load_scenario(path) == scenario
        assert load_scenario(str(path)) == scenario


def test_all_packaged_files_load() -> None:
    for name in packaged_scenarios():
        assert load_scenario(name).name == name


def test_unknown_name_lists_packaged_scenarios() -> None:
    with pytest.raises(ScenarioError) as info:
        load_scenario("no-such-scenario")
    message = str(info.value)
    assert "'no-such-scenario'" in message
    for name in packaged_scenarios():
        assert name in message


def test_missing_file_named(tmp_path: Path) -> None:
    path = tmp_path / "absent.toml"
    with pytest.raises(ScenarioError, match=r"absent\.toml"):
        load_scenario(path)


# ---------------------------------------------------------------- file errors


def test_valid_file_loads(tmp_path: Path) -> None:
    scenario = load_scenario(write(tmp_path, VALID_TOML))
    assert (scenario.name, scenario.duration_s, scenario.n_agents) == ("tiny", 2.0, 2)
    # Defaults filled in.
    assert (scenario.dt_s, scenario.seed, scenario.network.range_m) == (0.1, 0, 300.0)


def test_toml_syntax_error_names_the_file(tmp_path: Path) -> None:
    path = write(tmp_path, VALID_TOML + "oops = [1, 2\n", name="broken.toml")
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    assert str(path) in str(info.value)
    assert "not valid TOML" in str(info.value)


def test_non_utf8_file_is_a_scenario_error(tmp_path: Path) -> None:
    path = tmp_path / "latin1.toml"
    path.write_bytes(b'name = "caf\xe9"\n')
    with pytest.raises(ScenarioError, match=r"latin1\.toml"):
        load_scenario(path)


def test_wrong_type_names_file_and_key(tmp_path: Path) -> None:
    path = write(tmp_path, VALID_TOML.replace("duration_s = 2.0", 'duration_s = "long"'), name="typo.toml")
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    message = str(info.value)
    assert str(path) in message
    assert "key 'duration_s'" in message
    assert "'long'" in message


def test_missing_required_key_is_named() -> None:
    data = copy.deepcopy(MINIMAL)
    del data["duration_s"]
    message = error_of(data)
    assert "key 'duration_s'" in message and "required" in message
    data = copy.deepcopy(MINIMAL)
    del data["groups"][0]["body"]
    assert "key 'groups.0.body'" in error_of(data)


def test_unknown_key_is_named() -> None:
    assert "key 'colour'" in error_of(changed(colour="red"))
    assert "key 'groups.0.colour'" in error_of(with_group(colour="red"))


def test_nested_bad_values_are_named() -> None:
    assert "key 'groups.0.count'" in error_of(with_group(count=0))
    assert "key 'groups.0.body'" in error_of(with_group(body="submarine"))
    assert "key 'duration_s'" in error_of(changed(duration_s=-1.0))
    data = with_group(start={"box": {"min": [1.0, 1.0], "max": [0.0, 2.0]}})
    assert "groups.0.start.box" in error_of(data)


def test_several_errors_all_reported() -> None:
    message = error_of(changed(duration_s="long", dt_s=0.0, colour="red"))
    for key in ("duration_s", "dt_s", "colour"):
        assert f"key '{key}'" in message


def test_duplicate_group_names() -> None:
    data = copy.deepcopy(MINIMAL)
    data["groups"].append(copy.deepcopy(data["groups"][0]))
    assert "unique" in error_of(data)


def test_unknown_behaviour_parameter_is_named() -> None:
    message = error_of(with_group(params={"cruise_speed": 0.1, "speedy": 1.0}))
    assert "'speedy'" in message
    assert "cruise_speed" in message  # the known ones are listed


def test_behaviour_parameter_of_wrong_type() -> None:
    message = error_of(with_group(params={"cruise_speed": "fast"}))
    assert "cruise_speed" in message and "'fast'" in message


def test_unknown_behaviour_name_is_a_scenario_error() -> None:
    message = error_of(with_group(behavior="no-such-behaviour"))
    assert "no-such-behaviour" in message


def test_unknown_behaviour_in_event_choice_is_a_scenario_error() -> None:
    data = changed(events=[{"t_s": 1.0, "action": "set-behavior", "agents": [0], "choice": {"behavior": "nope"}}])
    assert "nope" in error_of(data)


def test_unknown_avoidance_parameter_is_a_scenario_error() -> None:
    assert "bogus" in error_of(with_group(avoid_obstacles=True, avoid_params={"bogus": 1.0}))


def test_event_needs_exactly_one_selection() -> None:
    both = changed(events=[{"t_s": 1.0, "action": "remove", "agents": [0], "count": 1}])
    message = error_of(both)
    assert "key 'events.0'" in message and "exactly one" in message
    neither = changed(events=[{"t_s": 1.0, "action": "remove"}])
    assert "exactly one" in error_of(neither)


def test_set_behavior_event_needs_a_choice() -> None:
    assert "choice" in error_of(changed(events=[{"t_s": 1.0, "action": "set-behavior", "agents": [0]}]))


def test_event_group_must_exist() -> None:
    message = error_of(changed(events=[{"t_s": 1.0, "action": "remove", "count": 1, "group": "ghosts"}]))
    assert "'ghosts'" in message


def test_light_needs_position_or_box() -> None:
    both = changed(world={"lights": [{"position": [1.0, 1.0], "box": {"min": [0, 0], "max": [1, 1]}}]})
    assert "world.lights.0" in error_of(both)


def test_start_needs_exactly_one_of_box_or_lattice() -> None:
    lattice = {"center": [0.0, 0.0], "spacing_m": 10.0}
    both = with_group(start={"box": {"min": [0.0, 0.0], "max": [1.0, 1.0]}, "lattice": lattice})
    assert "groups.0.start" in error_of(both) and "exactly one of 'box' or 'lattice'" in error_of(both)
    assert "exactly one of 'box' or 'lattice'" in error_of(with_group(start={"heading_deg": 0.0}))


@pytest.mark.parametrize(
    ("lattice", "key"),
    [
        ({"center": [0.0, 0.0], "spacing_m": 0.0}, "spacing_m"),
        ({"center": [0.0, 0.0], "spacing_m": 10.0, "kind": "hexagonal"}, "kind"),
        ({"center": [0.0, 0.0]}, "spacing_m"),
        ({"center": [0.0, 0.0], "spacing_m": 10.0, "rows": 3}, "rows"),
    ],
)
def test_bad_lattice_is_named(lattice: dict[str, Any], key: str) -> None:
    assert f"groups.0.start.lattice.{key}" in error_of(with_group(start={"lattice": lattice}))


def test_lattice_start_rejects_min_separation() -> None:
    start = {"lattice": {"center": [0.0, 0.0], "spacing_m": 10.0}, "min_separation_m": 5.0}
    assert "min_separation_m" in error_of(with_group(start=start))


@pytest.mark.parametrize("kind", ["triangular", "square"])
def test_lattice_start_places_the_sites_nearest_the_center(kind: str) -> None:
    from scipy.spatial import cKDTree

    from sitl.fleets.fleet import initial_poses, lattice_sites
    from sitl.world.world import World

    spacing, count = 80.0, 16
    lattice = {"center": [5.0, -7.0], "spacing_m": spacing, "kind": kind, "angle_deg": 30.0}
    scenario = validate_scenario(with_group(count=count, start={"lattice": lattice, "heading_deg": 0.0}), "lattice")
    empty = World()  # open water: no rooms, every site allowed
    position, heading = initial_poses(scenario, empty, np.random.default_rng(0))
    assert position.shape == (count, 2) and np.array_equal(heading, np.zeros(count))
    # No random draw: the same sites with any seed, one of them at the centre.
    assert np.array_equal(position, initial_poses(scenario, empty, np.random.default_rng(1))[0])
    assert np.array_equal(position, lattice_sites(count, (5.0, -7.0), spacing, kind, 30.0))
    assert np.hypot(*(position - [5.0, -7.0]).T).min() < 1e-9
    # Every site's nearest neighbour is exactly one spacing away, and the sites are distinct.
    distance, _ = cKDTree(position).query(position, k=2)
    np.testing.assert_allclose(distance[:, 1], spacing)
    # A triangular site has 6 neighbours at one spacing, a square one 4 (the centre site is inner).
    neighbours = (np.hypot(*(position - position[0]).T) < 1.01 * spacing).sum() - 1
    assert neighbours == (6 if kind == "triangular" else 4)
    # The nearest sites to the centre: a compact patch (for 16 sites, none beyond sqrt(5) spacings).
    assert np.hypot(*(position - [5.0, -7.0]).T).max() < 2.25 * spacing


def test_lattice_sites_outside_the_rooms_are_a_scenario_error() -> None:
    from sitl.fleets.fleet import initial_poses
    from sitl.world.world import World

    start = {"lattice": {"center": [5.0, 5.0], "spacing_m": 8.0}}
    scenario = validate_scenario(with_group(count=7, start=start), "lattice")
    room = World(rooms=[np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])])
    with pytest.raises(ScenarioError, match=r"'boats'.*outside the rooms"):
        initial_poses(scenario, room, np.random.default_rng(0))


def test_lattice_round_trips() -> None:
    start = {"lattice": {"center": [1.0, 2.0], "spacing_m": 10.0, "kind": "square"}, "heading_deg": 0.0}
    scenario = validate_scenario(with_group(start=start), "lattice")
    assert validate_scenario(tomllib.loads(scenario_to_toml(scenario)), "again") == scenario


# ---------------------------------------------------------------- overrides


def test_with_overrides_resizes_first_group_and_validates() -> None:
    base = load_scenario("heading-consensus")
    resized = base.with_overrides(agents=4, seed=99, duration_s=3.0)
    assert resized.groups[0].count == 4 and resized.n_agents == 4
    assert (resized.seed, resized.duration_s) == (99, 3.0)
    # The original is untouched, and no override means an equal copy.
    assert base.groups[0].count == 10
    assert base.with_overrides() == base
    with pytest.raises(ScenarioError) as info:
        base.with_overrides(duration_s=-1.0)
    assert "command-line overrides" in str(info.value) and "duration_s" in str(info.value)
    with pytest.raises(ScenarioError):
        base.with_overrides(agents=0)


def test_with_overrides_resizes_named_group() -> None:
    data = copy.deepcopy(MINIMAL)
    second = copy.deepcopy(data["groups"][0])
    second.update(name="ebots", body="ebot", count=3)
    data["groups"].append(second)
    data["resize_group"] = "ebots"
    scenario = validate_scenario(data, "two groups")
    # 10 agents in all: the 2 boats stay, the ebots become 10 - 2 = 8.
    resized = scenario.with_overrides(agents=10)
    assert [g.count for g in resized.groups] == [2, 8]
    # Not even one ebot would be left with 2 agents in all.
    with pytest.raises(ScenarioError, match="already hold 2 agents"):
        scenario.with_overrides(agents=2)
    assert "resize_group" in error_of(changed(resize_group="nobody"))


# ---------------------------------------------------------------- TOML round trip


@pytest.mark.parametrize("name", sorted(KNOWN))
def test_round_trip_packaged(name: str) -> None:
    scenario = load_scenario(name)
    text = scenario_to_toml(scenario)
    again = validate_scenario(tomllib.loads(text), "round trip")
    assert again == scenario
    assert scenario_to_toml(again) == text


def test_round_trip_all_packaged() -> None:
    for name in packaged_scenarios():
        scenario = load_scenario(name)
        assert validate_scenario(tomllib.loads(scenario_to_toml(scenario)), name) == scenario


def test_round_trip_awkward_values(tmp_path: Path) -> None:
    data = copy.deepcopy(MINIMAL)
    data["description"] = 'quotes " and \\ backslash\nsecond line, tab\there, unicode \u00e9\u00b0'
    data["groups"][0]["name"] = "boats with spaces"
    data["groups"][0]["start"]["heading_deg"] = -37.5
    data["metrics"] = {"kind": "generic", "params": {"odd key.with dot": 1e-7, "big": 1e20}}
    data["world"] = {"walls": [[[0.0, 0.0], [1.0, 0.0]]], "rooms": []}
    data["events"] = [
        {
            "t_s": 0.5,
            "action": "set-behavior",
            "agents": [1],
            "choice": {"behavior": "hold-heading", "params": {"turn_deg": 90.0}},
        }
    ]
    scenario = validate_scenario(data, "awkward")
    path = write(tmp_path, scenario_to_toml(scenario), name="awkward.toml")
    assert load_scenario(path) == scenario


def test_directory_named_like_packaged_scenario_does_not_shadow_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "heading-consensus").mkdir()
    assert load_scenario("heading-consensus").name == "heading-consensus"
