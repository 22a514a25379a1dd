"""ParameterStore: declared and range-checked parameters, atomic persistence, corrupt files set aside."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import pytest

from behaviors.registry import BEHAVIORS
from bob_autonomy.ground.params import (
    BEHAVIOR_NAMES,
    PARAM_TYPE_INT32,
    PARAM_TYPE_REAL32,
    PARAMS,
    ParamError,
    ParameterStore,
)


def test_declarations_fit_mavlink() -> None:
    names = [spec.name for spec in PARAMS]
    assert len(set(names)) == len(names)
    for spec in PARAMS:
        assert len(spec.name) <= 16 and spec.name.isascii()
        assert spec.mav_type in (PARAM_TYPE_INT32, PARAM_TYPE_REAL32)
        assert spec.minimum <= spec.default <= spec.maximum
    for required in ("BOB_BEHAVIOR", "BOB_P0_M", "BOB_H", "BOB_MAX_SPD_MPS", "BOB_GOAL_LAT", "BOB_GOAL_LON",
                     "BOB_LEADER_ID", "BOB_FENCE_EN", "BOB_GCS_FS_ACT", "BOB_GCS_FS_S", "BOB_RALLY_LAT"):  # fmt: skip
        assert required in names


def test_behavior_indices_name_registered_behaviours() -> None:
    assert set(BEHAVIOR_NAMES) <= set(BEHAVIORS)
    store = ParameterStore()
    store.set("BOB_BEHAVIOR", BEHAVIOR_NAMES.index("perimeter-defense"))
    assert store.behavior_name == "perimeter-defense"


def test_defaults_and_protocol_order() -> None:
    store = ParameterStore()
    assert store.names() == [spec.name for spec in PARAMS]
    assert store.get("BOB_P0_M") == 10.0 and store["BOB_H"] == 0
    assert isinstance(store.get("BOB_BEHAVIOR"), int)
    assert store.name_at(store.index("BOB_FENCE_EN")) == "BOB_FENCE_EN"
    assert store.goals == [] and store.fence == []


@pytest.mark.parametrize(
    ("name", "value", "message"),
    [
        ("BOB_P0_M", 0.0, "out of range"),
        ("BOB_P0_M", 1e6, "out of range"),
        ("BOB_H", 2, "out of range"),
        ("BOB_H", 0.5, "not an integer"),
        ("BOB_MAX_SPD_MPS", math.nan, "not finite"),
        ("BOB_GOAL_LAT", 91.0, "out of range"),
        ("BOB_BEHAVIOR", len(BEHAVIOR_NAMES), "out of range"),
        ("BOB_P0_M", "5", "not a number"),
        ("BOB_NOPE", 1.0, "unknown parameter"),
    ],
)
def test_invalid_set_is_refused_and_not_applied(tmp_path, name, value, message) -> None:
    store = ParameterStore(tmp_path / "params.json")
    before = store.values()
    with pytest.raises(ParamError, match=message) as info:
        store.set(name, value)
    assert name in str(info.value)
    assert store.values() == before
    assert not (tmp_path / "params.json").exists()  # nothing was written either


def test_set_many_is_all_or_nothing() -> None:
    store = ParameterStore()
    with pytest.raises(ParamError, match="BOB_H"):
        store.set_many({"BOB_P0_M": 5.0, "BOB_H": 7})
    assert store.get("BOB_P0_M") == 10.0
    store.set_many({"BOB_P0_M": 5.0, "BOB_H": 1})
    assert (store.get("BOB_P0_M"), store.get("BOB_H")) == (5.0, 1)


def test_values_persist_across_a_new_store(tmp_path) -> None:
    path = tmp_path / "sub" / "params.json"
    store = ParameterStore(path)
    store.set("BOB_P0_M", 5.0)
    store.set("BOB_LEADER_ID", 7.0)  # as it arrives over MAVLink: a float, stored as int
    store.set_fence([(45.0, 7.0), (45.0, 7.01), (45.01, 7.01)])
    store.set_goals([(45.001, 7.002), (45.003, 7.004)])
    again = ParameterStore(path)
    assert again.load_problem is None
    assert again.get("BOB_P0_M") == 5.0
    assert again.get("BOB_LEADER_ID") == 7 and isinstance(again.get("BOB_LEADER_ID"), int)
    assert again.goals == [(45.001, 7.002), (45.003, 7.004)]
    assert again.fence == [(45.0, 7.0), (45.0, 7.01), (45.01, 7.01)]
    assert (again.get("BOB_GOAL_LAT"), again.get("BOB_GOAL_LON")) == (45.001, 7.002)
    assert sorted(p.name for p in path.parent.iterdir()) == ["params.json"]  # no temporary files left
    assert json.loads(path.read_text())["params"]["BOB_P0_M"] == 5.0


def test_goal_parameters_and_goal_list_follow_each_other() -> None:
    store = ParameterStore()
    store.set_goals([(10.0, 20.0), (11.0, 21.0)])
    assert (store.get("BOB_GOAL_LAT"), store.get("BOB_GOAL_LON")) == (10.0, 20.0)
    store.set("BOB_GOAL_LON", 22.0)
    assert store.goals == [(10.0, 22.0)]
    store.set_many({"BOB_GOAL_LAT": 0.0, "BOB_GOAL_LON": 0.0})
    assert store.goals == []
    with pytest.raises(ParamError, match="latitude"):
        store.set_goals([(95.0, 0.0)])
    with pytest.raises(ParamError, match="3 vertices"):
        store.set_fence([(1.0, 1.0), (2.0, 2.0)])


def test_change_callbacks(caplog) -> None:
    store = ParameterStore()
    seen = []
    store.on_change(lambda name, old, new: seen.append((name, old, new)))

    def broken(name, old, new):
        raise RuntimeError("listener bug")

    store.on_change(broken)
    with caplog.at_level(logging.ERROR):
        store.set("BOB_P0_M", 20.0)
    assert seen == [("BOB_P0_M", 10.0, 20.0)]
    assert "callback failed" in caplog.text
    with pytest.raises(ParamError):
        store.set("BOB_P0_M", -1.0)
    store.set("BOB_P0_M", 20.0)  # no change: no call
    assert seen == [("BOB_P0_M", 10.0, 20.0)]


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        ("{not json", "bad JSON"),
        ('["a list"]', "not a JSON object"),
        ('{"params": {"BOB_P0_M": "ten"}}', "not a number"),
        ('{"params": {"BOB_H": 1.5}}', "not an integer"),
        ('{"params": {"BOB_H": true}}', "not an integer"),
        ('{"params": {"BOB_P0_M": -4}}', "out of range"),
        ('{"params": {}, "fence": [[1, 2], [3, 4]]}', "3 vertices"),
        ('{"params": {}, "goals": [[100, 0]]}', "latitude"),
        ('{"params": {}, "goals": 3}', "not a list"),
    ],
)
def test_corrupt_file_is_reported_set_aside_and_defaults_used(tmp_path, caplog, content, problem) -> None:
    path = tmp_path / "params.json"
    path.write_text(content)
    with caplog.at_level(logging.WARNING, logger="bob_autonomy.ground.params"):
        store = ParameterStore(path)
    assert store.values() == ParameterStore().values()
    assert store.goals == [] and store.fence == []
    aside = tmp_path / "params.json.corrupt-1"
    assert aside.read_text() == content
    assert not path.exists()
    assert store.load_problem is not None and problem in store.load_problem and str(path) in store.load_problem
    assert str(path) in caplog.text and problem in caplog.text
    store.set("BOB_P0_M", 3.0)  # the store works, and writes a good file again
    assert ParameterStore(path).get("BOB_P0_M") == 3.0


def test_a_second_corrupt_file_does_not_overwrite_the_first(tmp_path) -> None:
    path = tmp_path / "params.json"
    path.write_text("garbage 1")
    ParameterStore(path)
    path.write_text("garbage 2")
    ParameterStore(path)
    assert (tmp_path / "params.json.corrupt-1").read_text() == "garbage 1"
    assert (tmp_path / "params.json.corrupt-2").read_text() == "garbage 2"


def test_unknown_names_in_the_file_only_warn(tmp_path, caplog) -> None:
    path = tmp_path / "params.json"
    path.write_text(json.dumps({"params": {"BOB_FUTURE": 1, "BOB_P0_M": 7.5}}))
    with caplog.at_level(logging.WARNING):
        store = ParameterStore(path)
    assert store.get("BOB_P0_M") == 7.5 and store.load_problem is None
    assert "BOB_FUTURE" in caplog.text and path.exists()


def test_a_failed_write_keeps_the_value_and_says_why(tmp_path) -> None:
    blocker = tmp_path / "not-a-directory"
    blocker.write_text("")
    store = ParameterStore(blocker / "params.json")
    store.set("BOB_P0_M", 4.0)
    assert store.get("BOB_P0_M") == 4.0
    assert store.persist_error is not None and "params.json" in store.persist_error


def test_the_protocol_document_lists_every_parameter() -> None:
    doc = (Path(__file__).resolve().parents[1] / "docs" / "gcs-protocol.md").read_text()
    for spec in PARAMS:
        row = next((line for line in doc.splitlines() if line.startswith(f"| `{spec.name}` |")), None)
        assert row is not None, f"{spec.name} missing from docs/gcs-protocol.md"
        kind = "INT32" if spec.kind == "int" else "REAL32"
        assert f"| {kind} | {spec.default:g} | {spec.minimum:g} .. {spec.maximum:g} |" in row, row
    assert ", ".join(f"{i} {n}" for i, n in enumerate(BEHAVIOR_NAMES)) in doc
