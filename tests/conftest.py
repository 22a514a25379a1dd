"""Test isolation shared by every test module.

A test that runs a command's main() in process (`bob-autonomy run`, the examples) configures the root logger as the
command does: its handler and level would otherwise outlive the test, and a handler bound to that test's captured
stderr turns every later record, from any thread of any later test, into a "Logging error"."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest


@pytest.fixture(autouse=True)
def _root_logger_restored() -> Iterator[None]:
    """The root logger's handlers and level as they were before the test; handlers the test added are closed."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    for handler in root.handlers:
        if handler not in handlers:
            handler.close()
    root.handlers[:] = handlers
    root.setLevel(level)


# Modules whose tests each run a whole scenario for a minute or more. pytest-xdist hands tests to its workers in
# collection order, so these go first (after the real-time group, the longest unit of all): run last, one of
# them would keep one worker busy for a minute after the other has finished.
LONG_MODULES = ("test_physics_scenarios.py", "test_motorboat_scenarios.py")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The real-time group first, then LONG_MODULES, then the rest, each in its collected order."""

    def rank(item: pytest.Item) -> int:
        if item.get_closest_marker("xdist_group") is not None:
            return 0
        return 1 if item.path.name in LONG_MODULES else 2

    items.sort(key=rank)
