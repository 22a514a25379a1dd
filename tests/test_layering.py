"""The package layering of DESIGN.md: arrows point down only."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PROJECT = {"behaviors", "bob_autonomy", "firmware_bridge", "sitl"}
STDLIB = set(sys.stdlib_module_names)


def imported_top_levels(package: str) -> dict[str, set[str]]:
    """Top-level module names imported by each file of a package (absolute imports)."""
    found: dict[str, set[str]] = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        names: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                names |= {alias.name.split(".")[0] for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
        found[str(path.relative_to(ROOT))] = names
    return found


@pytest.mark.parametrize(
    ("package", "allowed"),
    [
        ("behaviors", {"behaviors", "numpy"}),
        ("firmware_bridge", {"firmware_bridge", "numpy", "pymavlink", "fastcrc", "serial"}),  # fastcrc: pymavlink's CRC
    ],
)
def test_package_imports_only_what_it_may(package: str, allowed: set[str]) -> None:
    for path, names in imported_top_levels(package).items():
        outside = names - allowed - STDLIB
        assert not outside, f"{path} imports {sorted(outside)}"


def test_bob_autonomy_never_imports_the_simulator() -> None:
    for path, names in imported_top_levels("bob_autonomy").items():
        assert "sitl" not in names, f"{path} imports sitl"


def test_the_checker_sees_imports() -> None:
    # Guard against a checker that finds nothing: sitl does import the other packages.
    names = set().union(*imported_top_levels("sitl").values())
    assert {"behaviors", "bob_autonomy", "numpy", "scipy"} <= names


def _lint_imports(cwd: Path, extra_path: Path | None = None) -> subprocess.CompletedProcess:
    """`lint-imports` with the contracts of pyproject.toml, the packages found first on `extra_path` if given."""
    env = dict(os.environ)
    if extra_path is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(extra_path), env.get("PYTHONPATH", "")])
    config = ROOT / "pyproject.toml"
    command = [sys.executable, "-c", "from importlinter.cli import lint_imports_command; lint_imports_command()"]
    return subprocess.run(
        [*command, "--config", str(config), "--no-cache"], cwd=cwd, env=env, capture_output=True, text=True
    )


def test_the_import_linter_contracts_hold() -> None:
    done = _lint_imports(ROOT)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "5 kept, 0 broken" in done.stdout


def test_the_import_linter_contracts_catch_a_layer_crossed(tmp_path: Path) -> None:
    # Stand-in packages of the same names, each crossing one rule: the contracts must all break.
    sources = {
        "behaviors": "import scipy\n",  # behaviours: numpy only
        "firmware_bridge": "import behaviors\nimport casadi\n",  # a sibling layer, a solver
        "bob_autonomy": "import sitl\n",  # upwards
        "sitl": "",
    }
    for name, text in sources.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "__init__.py").write_text(text)
    # The simulator's parts, the world reaching up into the vehicles.
    (tmp_path / "sitl" / "cli.py").write_text("")
    parts = {"experiments": "", "fleets": "", "vehicles": "", "radio": "", "world": "import sitl.vehicles\n"}
    for part, text in parts.items():
        (tmp_path / "sitl" / part).mkdir()
        (tmp_path / "sitl" / part / "__init__.py").write_text(text)
    # The autonomy's parts, the core reaching up into the vessel process.
    (tmp_path / "bob_autonomy" / "cli.py").write_text("")
    for part in ("onboard", "network", "ground", "estimation", "control", "core"):
        (tmp_path / "bob_autonomy" / part).mkdir()
        text = "import bob_autonomy.onboard\n" if part == "core" else ""
        (tmp_path / "bob_autonomy" / part / "__init__.py").write_text(text)
    done = _lint_imports(tmp_path, tmp_path)
    assert done.returncode != 0
    assert "0 kept, 5 broken" in done.stdout, done.stdout + done.stderr
