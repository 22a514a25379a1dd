"""Test isolation shared by every test module, and a check that pytest-xdist keeps the real-time tests together.

A test that runs a command's main() in process (`bob-autonomy run`, the examples) configures the root logger as the
command does: its handler and level would otherwise outlive the test, and a handler bound to that test's captured
stderr turns every later record, from any thread of any later test, into a "Logging error"."""

from __future__ import annotations

import logging
import os
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


@pytest.fixture(autouse=True)
def _kept_in_its_xdist_group(request: pytest.FixtureRequest) -> None:
    """Under `--dist loadgroup`, a test marked xdist_group must carry its group in its node id ("...@realtime"),
    or pytest-xdist spreads the group over the workers without a word: the real-time tests (sockets, processes,
    wall-clock rates) then run beside each other and fail at random under load. Fail saying so instead."""
    node = request.node
    grouped = getattr(request.config.option, "loadgroup", False) and node.get_closest_marker("xdist_group")
    if grouped and "@" not in node.nodeid:
        pytest.fail(
            f"pytest-xdist did not put this test in its xdist_group: this pytest ({pytest.__version__}) and "
            "pytest-xdist do not work together; install the versions pyproject.toml pins",
            pytrace=False,
        )
    if grouped and _niced:
        pytest.fail(
            "this real-time test runs in a worker that has already run others niced (pytest_runtest_setup): "
            "pytest-xdist no longer gives the real-time group to a worker of its own first; see pyproject.toml",
            pytrace=False,
        )


# How much nicer (os.nice increment) a worker runs once it takes a test that is not real-time.
BACKGROUND_NICENESS = 10
_niced = False


def pytest_runtest_setup(item: pytest.Item) -> None:
    """Under pytest-xdist, a worker that takes a test outside the real-time group lowers its own priority for good.

    The real-time tests (process fleets at 3x, sockets with timeouts) mostly wait on the wall clock, so their worker
    leaves a core half idle; a third worker uses that share. Niced by BACKGROUND_NICENESS (about a tenth of the
    weight of a normal process under Linux's scheduler), the number-crunching workers take CPU only when the
    real-time tests and their child processes do not want it. The real-time group is the largest xdist scope, so
    it goes first to one worker, which never runs a niced test before it."""
    global _niced
    if _niced or "PYTEST_XDIST_WORKER" not in os.environ or item.get_closest_marker("xdist_group"):
        return
    os.nice(BACKGROUND_NICENESS)
    _niced = True
