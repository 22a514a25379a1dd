"""MAVProxy (from PyPI, in the dev extras) as a ground station the tests drive through its console."""

from __future__ import annotations

import json
import os
import queue
import re
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

HERE = Path(__file__).resolve().parent  # where mavproxy_probe.py is
MAVPROXY = shutil.which("mavproxy.py", path=str(Path(sys.executable).parent)) or shutil.which("mavproxy.py")


class MavproxySession:
    """mavproxy.py with its console on pipes: send a command line, wait for a line matching a pattern."""

    def __init__(
        self, master: str, cwd: Path, component: int | None = 191, target_system: int = 1, extra: tuple[str, ...] = ()
    ) -> None:
        target = [f"--target-system={target_system}", f"--target-component={component}"] if component else []
        self.cwd = cwd
        self.process = subprocess.Popen(
            [MAVPROXY, f"--master={master}", *target, *extra, "--nowait", "--no-state", "--state-basedir", str(cwd)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=cwd,
            env={**os.environ, "PYTHONPATH": os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")])},
        )  # fmt: skip
        self.lines: queue.Queue[str] = queue.Queue()
        self.transcript: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.process.stdout:
            self.lines.put(line.rstrip())

    def send(self, command: str) -> None:
        self.process.stdin.write(command + "\n")
        self.process.stdin.flush()

    def expect(self, pattern: str, timeout_s: float) -> re.Match:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.1)
            except queue.Empty:
                continue
            self.transcript.append(line)
            match = re.search(pattern, line)
            if match:
                return match
        raise AssertionError(f"MAVProxy never printed /{pattern}/; it printed:\n" + "\n".join(self.transcript[-40:]))

    def command(self, command: str, pattern: str, timeout_s: float = 10.0) -> re.Match:
        """Send a command line and wait for a line matching `pattern`."""
        self.send(command)
        return self.expect(pattern, timeout_s)

    def retry(self, command: str, pattern: str, timeout_s: float = 10.0) -> re.Match:
        """Send a command every second until a line matches (`status X` prints nothing before X has arrived)."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                return self.command(command, pattern, 1.0)
            except AssertionError:
                if time.monotonic() > deadline:
                    raise

    def probe(self) -> dict:
        """What MAVProxy received from each system and component (tests/mavproxy_probe.py)."""
        return json.loads(self.command("probe", r"PROBE (\{.*\})").group(1))  # a prompt may follow on the line

    def close(self) -> None:
        try:
            self.send("exit")
            self.process.wait(timeout=5)
        except (OSError, subprocess.TimeoutExpired):
            self.process.kill()
            self.process.wait()


def signed_session(port: int, cwd: Path, passphrase: str, component: int = 191) -> MavproxySession:
    """MAVProxy on udpout to `port`, its target (1, component), signing with `passphrase`'s key and taking signed
    frames only."""
    session = MavproxySession(f"udpout:127.0.0.1:{port}", cwd, component=component)
    session.send("set param_ftp 0")  # the parameter protocol at once: component 191 serves no MAVFTP
    session.send("set allow_unsigned 0")  # signed frames only (RADIO_STATUS aside)
    session.command(f'signing key "{passphrase}"', r"Setup signing key")
    return session


def heard(
    session: MavproxySession, timeout_s: float, done: Callable[[set[str], list[int]], bool] | None = None
) -> tuple[set[str], list[int]]:
    """The components ("1:191") MAVProxy detected and the parameter counts it received, in whatever order it
    prints them, once `done(detected, counts)` holds (by default: two components and two parameter sets)."""
    detected: set[str] = set()
    counts: list[int] = []
    finished = done or (lambda found, sets: len(found) >= 2 and len(sets) >= 2)
    deadline = time.monotonic() + timeout_s
    while not finished(detected, counts):
        found = session.expect(r"Detected vehicle (1:\d+)|Received (\d+) parameters", deadline - time.monotonic())
        if found.group(1):
            detected.add(found.group(1))
        else:
            counts.append(int(found.group(2)))
    return detected, counts
