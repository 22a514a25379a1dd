"""The package layering of DESIGN.md: arrows point down only."""

from __future__ import annotations

import ast
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
        ("firmware_bridge", {"firmware_bridge", "numpy", "pymavlink", "serial"}),
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
