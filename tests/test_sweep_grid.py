"""bob-sitl sweep: parameter grids (--param, --x), the fixed order of the rows, the partial file and --resume.

Everything runs through the real `bob-sitl` main() on a tiny heading-consensus (3 eBots, 1.5 s), in
process; the Dask cluster's own test is tests/test_sweep_dask.py.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

import sitl.experiments.sweep
from sitl.cli import main
from sitl.experiments.run_environment import SOURCE_KEY, environment
from sitl.experiments.scenario import ScenarioError, load_scenario
from sitl.experiments.sweep import apply_param, parse_param, partial_path, read_partial, run_sweep

REAL_SIMULATE = sitl.experiments.sweep.simulate
TINY = ["heading-consensus", "--agents", "3", "--duration", "1.5", "--quiet"]


def table(path: Path) -> list[dict[str, str]]:
    with open(path, encoding="utf-8", newline="") as handle:
        return list(csv.DictReader(handle))


def tree(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


@pytest.fixture
def work(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.chdir(tmp_path)
    return tmp_path


# ---------------------------------------------------------------- --param


@pytest.mark.parametrize(
    "text, path, values",
    [
        ("network.range_m=1,50", "network.range_m", [1, 50]),
        ("groups.0.params.p0=5.5, 50", "groups.0.params.p0", [5.5, 50]),
        ("vessel.controller=simple,mpc", "vessel.controller", ["simple", "mpc"]),
        ('groups.0.name="a,b",c', "groups.0.name", ["a,b", "c"]),
        ("world.lights=[1,2],[3,4]", "world.lights", [[1, 2], [3, 4]]),
        ("x=true,false", "x", [True, False]),
        ("x=1979-05-27", "x", ["1979-05-27"]),  # a TOML date is not a scenario's value: kept as text
    ],
)
def test_param_values_are_toml_or_text(text: str, path: str, values: list[Any]) -> None:
    assert parse_param(text) == (path, values)


@pytest.mark.parametrize(
    "text, expected",
    [
        ("network.range_m", "give PATH=V1,V2"),
        ("=1,2", "give PATH=V1,V2"),
        ("a..b=1", "give PATH=V1,V2"),
        ("a/b=1", "give PATH=V1,V2"),
        ("seed=1,2", "the seeds are --runs"),
        ("network.range_m=1,,2", "an empty value"),
        ("network.range_m=", "an empty value"),
        ("network.range_m=5, 5", "given twice"),
        ("name=a,b", "the name names the output"),
    ],
)
def test_bad_param_syntax_is_named(text: str, expected: str) -> None:
    with pytest.raises(ScenarioError, match=expected):
        parse_param(text)


NUMBERS = st.integers(-(10**6), 10**6) | st.floats(allow_nan=False, allow_infinity=False)


@given(st.lists(NUMBERS, min_size=1, max_size=6))
def test_numbers_round_trip_through_the_option(values: list[float]) -> None:
    values = list({json.dumps(v): v for v in values}.values())  # distinct as written
    text = "a.b=" + ",".join(json.dumps(v) for v in values)
    path, parsed = parse_param(text)
    assert path == "a.b"
    assert [json.dumps(v) for v in parsed] == [json.dumps(v) for v in values]


def test_apply_param_walks_tables_and_lists_and_creates_missing_tables() -> None:
    data = {"groups": [{"params": {"p0": 1.0}}], "network": {"radio": None}, "duration_s": 5.0}
    apply_param(data, "groups.0.params.p0", 7.0)
    apply_param(data, "network.radio.ple", 2.0)
    apply_param(data, "environment.wind.speed_mps", 3.0)
    assert data["groups"][0]["params"]["p0"] == 7.0
    assert data["network"]["radio"] == {"ple": 2.0}
    assert data["environment"] == {"wind": {"speed_mps": 3.0}}
    with pytest.raises(ScenarioError, match=r"groups is a list of 1 item\(s\); '1' is not an index"):
        apply_param(data, "groups.1.params.p0", 1.0)
    with pytest.raises(ScenarioError, match=r"groups is a list of 1 item\(s\); 'x' is not an index"):
        apply_param(data, "groups.x", 1.0)
    with pytest.raises(ScenarioError, match=r"duration_s is the float 5\.0, not a table"):
        apply_param(data, "duration_s.x", 1.0)


@pytest.mark.parametrize(
    "param, expected",
    [
        ("network.rang_m=1", ["--param network.rang_m=1", "key 'network.rang_m'", "Extra inputs are not permitted"]),
        ("network.range_m=10,-5", ["--param network.range_m=-5", "key 'network.range_m'", "greater than 0"]),
        ("groups.0.params.p9=1", ["key 'groups.0'", "unknown parameter(s) for 'heading-consensus'", "p9"]),
        ("groups.4.count=2", ["groups is a list of 1 item(s)"]),
        ("network.range_m=inf", ["key 'network.range_m'", "finite"]),
        ("vessel.controller=simple,nope", ["key 'vessel.controller'", "'simple' or 'mpc'"]),
        ("groups.0.count=0", ["key 'groups.0.count'"]),
    ],
)
def test_a_bad_path_or_value_exits_2_before_anything_runs(work: Path, capsys, monkeypatch, param, expected) -> None:
    monkeypatch.setattr(sitl.experiments.sweep, "simulate", lambda *a, **k: pytest.fail("a run started"))
    status = main(["sweep", *TINY, "--runs", "1", "--param", param, "--out", "o"])
    err = capsys.readouterr().err
    assert status == 2, err
    assert err.startswith("bob-sitl: ") and "Traceback" not in err
    for text in expected:
        assert text in err, f"{text!r} not in {err!r}"
    assert tree(work) == []


@pytest.mark.parametrize(
    "options, expected",
    [
        (["--x", "network.range_m"], "--x network.range_m: not swept"),
        (["--param", "network.range_m=1", "--param", "network.range_m=2"], "given twice"),
        (["--workers", "0"], "--workers must be at least 1"),
        (["--scheduler", " "], "--scheduler needs an address"),
    ],
)
def test_bad_sweep_options_exit_2(work: Path, capsys, monkeypatch, options, expected) -> None:
    monkeypatch.setattr(sitl.experiments.sweep, "simulate", lambda *a, **k: pytest.fail("a run started"))
    assert main(["sweep", *TINY, "--runs", "1", "--out", "o", *options]) == 2
    assert expected in capsys.readouterr().err
    assert tree(work) == []


def test_the_grid_is_sizes_by_values_by_seeds_one_column_per_path(work: Path) -> None:
    argv = ["sweep", "heading-consensus", "--agents", "3", "4", "--duration", "1.5", "--quiet", "--runs", "2"]
    argv += ["--param", "network.range_m=1,50", "--param", "groups.0.params.cruise_speed=0,0.05"]
    assert main([*argv, "--x", "network.range_m", "--plot", "initial_spread_deg", "--out", "o"]) == 0
    rows = table(work / "o" / "sweep.csv")
    assert list(rows[0])[:5] == ["agents", "network.range_m", "groups.0.params.cruise_speed", "seed", "passed"]
    expected = [(n, r, c, s) for n in ("3", "4") for r in ("1", "50") for c in ("0", "0.05") for s in ("1", "2")]
    got = [(r["agents"], r["network.range_m"], r["groups.0.params.cruise_speed"], r["seed"]) for r in rows]
    assert got == expected
    # The values reached the runs: out of range (1 m) nobody hears anybody and no consensus forms.
    for r in rows:
        assert (r["criteria.within_5_deg_by_11_s"] == "False") or r["network.range_m"] == "50"
    assert (work / "o" / "sweep.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not partial_path(work / "o").exists()


def test_without_agents_the_scenarios_own_size_is_swept(work: Path) -> None:
    scenario = load_scenario("heading-consensus").with_overrides(duration_s=1.0)
    rows = run_sweep(scenario, None, [5], work / "o", [], progress=False, params=[("vessel.controller", ["simple"])])
    assert [(r["agents"], r["seed"], r["vessel.controller"]) for r in rows] == [(10, 5, "simple")]


# ---------------------------------------------------------------- interrupted sweeps and --resume


class Interrupting:
    """simulate() that lets `allowed` runs finish and then raises KeyboardInterrupt (a Ctrl-C mid-sweep)."""

    def __init__(self, allowed: int) -> None:
        self.allowed, self.calls = allowed, 0

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        self.calls += 1
        if self.calls > self.allowed:
            raise KeyboardInterrupt
        return REAL_SIMULATE(*args, **kwargs)


def test_an_interrupted_sweep_keeps_its_finished_runs_and_resume_skips_them(work: Path, capsys, monkeypatch) -> None:
    argv = ["sweep", *TINY, "--runs", "3", "--param", "network.range_m=1,50"]
    assert main([*argv, "--out", "whole"]) == 0
    whole = (work / "whole" / "sweep.csv").read_bytes()

    interrupting = Interrupting(allowed=4)
    monkeypatch.setattr(sitl.experiments.sweep, "simulate", interrupting)
    assert main([*argv, "--out", "cut"]) == 130
    err = capsys.readouterr().err
    partial = partial_path(work / "cut")
    assert "4 finished run(s) kept in .cut.partial.jsonl" in err and "--resume" in err
    assert len(read_partial(partial)) == 4 and not (work / "cut").exists()

    assert main([*argv, "--out", "cut"]) == 2  # forgetting --resume never throws the finished runs away
    assert "add --resume to continue it" in capsys.readouterr().err
    assert len(read_partial(partial)) == 4

    with open(partial, "a", encoding="utf-8") as handle:
        handle.write('{"run": "torn by a kill')  # a line cut short is ignored
    counting = Interrupting(allowed=10**6)
    monkeypatch.setattr(sitl.experiments.sweep, "simulate", counting)
    assert main([*argv, "--out", "cut", "--resume"]) == 0
    assert counting.calls == 2  # 6 runs, 4 kept
    assert (work / "cut" / "sweep.csv").read_bytes() == whole
    assert not partial.exists()


@pytest.mark.parametrize(
    ("recorded", "said"),
    [
        ({"numpy": "1.0.0"}, "numpy 1.0.0 there, "),
        ({SOURCE_KEY: "0" * 16}, f"{SOURCE_KEY} {'0' * 16} there, "),
        (None, "no record of the code that made them"),  # a partial file from before environments were recorded
    ],
)
def test_resume_refuses_runs_kept_by_other_code_or_libraries(work: Path, capsys, monkeypatch, recorded, said) -> None:
    argv = ["sweep", *TINY, "--runs", "2"]
    monkeypatch.setattr(sitl.experiments.sweep, "simulate", Interrupting(allowed=1))
    assert main([*argv, "--out", "o"]) == 130
    partial = partial_path(work / "o")
    entry = json.loads(partial.read_text())
    assert entry["environment"] == environment()  # each kept run says what made it
    if recorded is None:
        del entry["environment"]
    else:
        entry["environment"] = {**entry["environment"], **recorded}
    partial.write_text(json.dumps(entry) + "\n")
    counting = Interrupting(allowed=10**6)
    monkeypatch.setattr(sitl.experiments.sweep, "simulate", counting)
    capsys.readouterr()
    assert main([*argv, "--out", "o", "--resume"]) == 2
    err = capsys.readouterr().err
    assert said in err and "resuming would mix two versions' results: remove the file" in err
    assert counting.calls == 0 and len(read_partial(partial)) == 1  # nothing run, nothing thrown away


def test_a_sweep_says_what_code_and_libraries_made_it(work: Path) -> None:
    assert main(["sweep", *TINY, "--runs", "1", "--out", "o"]) == 0
    assert json.loads((work / "o" / "environment.json").read_text()) == environment()


def test_an_interrupt_before_any_run_finished_leaves_nothing(work: Path, capsys, monkeypatch) -> None:
    monkeypatch.setattr(sitl.experiments.sweep, "simulate", Interrupting(allowed=0))
    assert main(["sweep", *TINY, "--runs", "2", "--out", "deep/er/o"]) == 130
    assert "nothing written to deep/er/o" in capsys.readouterr().err
    assert tree(work) == []


def test_resume_takes_only_runs_of_the_same_scenario(work: Path, monkeypatch) -> None:
    argv = ["sweep", *TINY, "--runs", "2"]
    monkeypatch.setattr(sitl.experiments.sweep, "simulate", Interrupting(allowed=1))
    assert main([*argv, "--out", "o"]) == 130
    counting = Interrupting(allowed=10**6)
    monkeypatch.setattr(sitl.experiments.sweep, "simulate", counting)
    # Another duration is another scenario: the kept run does not belong to this sweep and is run again.
    assert main([*argv, "--duration", "1.0", "--out", "o", "--resume"]) == 0
    assert counting.calls == 2


def test_a_seed_that_cannot_start_is_a_failed_row_and_the_sweep_goes_on(work: Path, monkeypatch) -> None:
    def no_room_at_seed_1(scenario, **kwargs):
        if scenario.seed == 1:
            raise ScenarioError("cannot place 3 agents 0.4 m apart in box (0, 0)..(3, 3)")
        return REAL_SIMULATE(scenario, **kwargs)

    monkeypatch.setattr(sitl.experiments.sweep, "simulate", no_room_at_seed_1)
    assert main(["sweep", *TINY, "--runs", "2", "--out", "o"]) == 0
    rows = table(work / "o" / "sweep.csv")
    assert [(r["seed"], r["passed"], r["error"]) for r in rows] == [
        ("1", "False", "cannot place 3 agents 0.4 m apart in box (0, 0)..(3, 3)"), ("2", "True", "")
    ]  # fmt: skip
