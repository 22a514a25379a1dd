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
