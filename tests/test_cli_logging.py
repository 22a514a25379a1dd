"""`bob-autonomy run` logs to stderr through a handler that follows sys.stderr, so that a record from one of the
vessel's threads after the stream it started with was swapped and closed is written, not a logging error."""

from __future__ import annotations

import io
import logging
import sys

import pytest

from bob_autonomy.cli import _setup_logging


def test_the_run_commands_stderr_handler_follows_sys_stderr(monkeypatch: pytest.MonkeyPatch) -> None:
    first, second = io.StringIO(), io.StringIO()
    monkeypatch.setattr(sys, "stderr", first)
    _setup_logging(None, verbose=False)
    log = logging.getLogger("bob_autonomy.test_cli_logging")
    log.info("to the first stream")
    assert "INFO bob_autonomy.test_cli_logging: to the first stream" in first.getvalue()
    first.close()  # a test's capture, closed when the test ends
    monkeypatch.setattr(sys, "stderr", second)
    errors = []
    monkeypatch.setattr(logging.Handler, "handleError", lambda _self, record: errors.append(record))
    log.info("to the second stream")
    assert errors == []
    assert "to the second stream" in second.getvalue()
