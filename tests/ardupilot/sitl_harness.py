"""Run ArduPilot's own Rover SITL (a binary built from ArduPilot's source) headless, and watch it.

`ARDUPILOT_SITL` names the built `ardurover`; its default parameter files are taken from the ArduPilot tree
it was built in (`Tools/autotest/default_params/`, or `ARDUPILOT_DEFAULTS_DIR`). Each instance runs in its
own scratch directory with a wiped EEPROM, on instance number I: SERIAL0 (the autonomy's port) on TCP
5760 + 10 I, SERIAL1 (the observer's) on 5762 + 10 I, RC input on a free UDP port (`--rc-in-port`).

The observer is pymavlink on SERIAL1: it asks for RC_CHANNELS, SERVO_OUTPUT_RAW and GLOBAL_POSITION_INT and
keeps what the autopilot itself says of position and inputs, the ground truth of these tests.
"""

from __future__ import annotations

import math
import os
import socket
import subprocess
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil

MODELS = {
    # name: (--model, default parameter files)
    "omni": ("rover-omni3mecanum", ("rover.parm", "rover-omni3mecanum.parm")),
    "motorboat": ("motorboat", ("rover.parm", "motorboat.parm")),
    "skid": ("rover-skid", ("rover.parm", "rover-skid.parm")),
    "rover": ("rover", ("rover.parm",)),
}
HOME = (-35.363261, 149.165230, 584.0, 0.0)


def sitl_binary() -> Path | None:
    path = os.environ.get("ARDUPILOT_SITL")
    return Path(path) if path and Path(path).is_file() and os.access(path, os.X_OK) else None


BINARY = sitl_binary()
# Every real-SITL test module's marks: skipped without a built `ardurover`, run in the real-time worker.
NEEDS_SITL = [
    pytest.mark.skipif(BINARY is None, reason="set ARDUPILOT_SITL to a built ArduPilot ardurover to run these"),
    pytest.mark.xdist_group("realtime"),
]


def defaults_dir(binary: Path) -> Path:
    given = os.environ.get("ARDUPILOT_DEFAULTS_DIR")
    if given:
        return Path(given)
    # build/sitl/bin/ardurover -> the tree's Tools/autotest/default_params
    return binary.resolve().parents[3] / "Tools" / "autotest" / "default_params"


def _port_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_instance(first: int = 20) -> int:
    """An instance number whose SERIAL0-2 TCP ports are all free."""
    for i in range(first, first + 60):
        if all(_port_free(5760 + 10 * i + k) for k in (0, 2, 3)):
            return i
    raise RuntimeError("no free ArduPilot SITL instance ports")


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Observation:
    """What the autopilot reported on the observer's port, with wall times."""

    positions: list[tuple[float, float, float, float]] = field(default_factory=list)  # (t, lat, lon, hdg deg)
    rc: list[tuple[float, list[int]]] = field(default_factory=list)  # (t, chan1..8)
    servos: list[tuple[float, list[int]]] = field(default_factory=list)  # (t, servo1..8 outputs, us)
    modes: list[tuple[float, int, bool]] = field(default_factory=list)  # (t, custom_mode, armed)
    texts: list[str] = field(default_factory=list)
    params: dict[str, float] = field(default_factory=dict)  # each PARAM_VALUE heard (a set goes to every link)
    param_count: int | None = None  # the autopilot's parameter count, from those PARAM_VALUEs


class RoverSitl:
    """One ArduPilot Rover SITL process and an observer on its SERIAL1. Use as a context manager. home: where the
    vehicle starts (lat, lon deg, alt m, heading deg); params: parameters over the model's defaults (its system id
    is MAV_SYSID there, 1 by default; SYSID_THISMAV before ArduPilot 4.7); serial2: SERIAL2's (TELEM2's) device,
    e.g. "uart:/dev/pts/4" (SITL's own default otherwise)."""

    def __init__(
        self,
        binary: Path,
        model: str,
        workdir: Path,
        *,
        params: dict[str, float] | None = None,
        home: tuple[float, float, float, float] = HOME,
        serial2: str | None = None,
    ) -> None:
        self.binary, self.workdir, self.home, self.serial2 = binary, workdir, home, serial2
        self.system_id = int((params or {}).get("MAV_SYSID", 1))
        self.model, parm_files = MODELS[model]
        self.instance = free_instance()
        self.serial0 = 5760 + 10 * self.instance
        self.serial1 = self.serial0 + 2
        self.rc_port = free_udp_port()
        folder = defaults_dir(binary)
        extra = workdir / "extra.parm"
        extra.write_text("".join(f"{k} {v}\n" for k, v in (params or {}).items()))
        self.defaults = ",".join([str(folder / f) for f in parm_files] + [str(extra)])
        self.process: subprocess.Popen | None = None
        self.observer = None
        self.seen = Observation()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> RoverSitl:
        home = ",".join(str(v) for v in self.home)
        command = [
            str(self.binary),
            "-w",
            "-I",
            str(self.instance),
            "--model",
            self.model,
            "--speedup",
            "1",
            "--defaults",
            self.defaults,
            "--serial0",
            "tcp:0",
            "--rc-in-port",
            str(self.rc_port),
            "--home",
            home,
        ]
        if self.serial2:
            command += ["--serial2", self.serial2]
        self.log = open(self.workdir / "ardurover.log", "w")  # closed in __exit__
        self.process = subprocess.Popen(command, cwd=self.workdir, stdout=self.log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 30
        while _port_free(self.serial1):
            if self.process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"ArduPilot SITL did not start: see {self.workdir / 'ardurover.log'}")
            time.sleep(0.1)
        self.observer = mavutil.mavlink_connection(f"tcp:127.0.0.1:{self.serial1}", source_system=254)
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()
        return self

    def _watch(self) -> None:
        obs = self.observer
        asked = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now - asked > 2.0:
                asked = now
                for msg_id, hz in ((65, 10), (36, 5), (33, 10)):  # RC_CHANNELS, SERVO_OUTPUT_RAW, GLOBAL_POSITION_INT
                    obs.mav.command_long_send(self.system_id, 1, 511, 0, msg_id, 1e6 / hz, 0, 0, 0, 0, 0)
            try:
                msg = obs.recv_match(blocking=True, timeout=0.2)
            except (OSError, ConnectionError):
                return
            if msg is None:
                continue
            t, name = time.monotonic(), msg.get_type()
            if name == "GLOBAL_POSITION_INT" and msg.get_srcComponent() == 1:
                self.seen.positions.append((t, msg.lat * 1e-7, msg.lon * 1e-7, msg.hdg / 100.0))
            elif name == "RC_CHANNELS":
                self.seen.rc.append((t, [getattr(msg, f"chan{c}_raw") for c in range(1, 9)]))
            elif name == "SERVO_OUTPUT_RAW":
                self.seen.servos.append((t, [getattr(msg, f"servo{c}_raw") for c in range(1, 9)]))
            elif name == "HEARTBEAT" and msg.get_srcComponent() == 1:
                armed = bool(msg.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                self.seen.modes.append((t, msg.custom_mode, armed))
            elif name == "STATUSTEXT":
                self.seen.texts.append(msg.text)
            elif name == "PARAM_VALUE" and msg.get_srcComponent() == 1:
                self.seen.params[msg.param_id] = msg.param_value
                self.seen.param_count = msg.param_count

    def wait_initialised(self, timeout_s: float = 60.0) -> None:
        """Until the autopilot leaves INITIALISING (custom mode 16) and has a GPS position."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.seen.modes and self.seen.modes[-1][1] != 16 and self.seen.positions:
                return
            time.sleep(0.2)
        raise RuntimeError("ArduPilot SITL did not initialise")

    def stop_watching(self) -> None:
        """Stop the observer (before the autopilot restarts: its connection closes with the process)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
            self._thread = None
        if self.observer is not None:
            self.observer.close()
            self.observer = None

    def __exit__(self, *exc) -> None:
        self.stop_watching()
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.log.close()


def vessel_config(sitl: RoverSitl, goal: tuple[float, float] = (0.0, 0.0), **overrides):
    """A `VesselConfig` for a buoy vessel on the SITL's SERIAL0 that seeks `goal` (east, north m from HOME) with the
    BoB rule, allowed 60 s to arm; `overrides` replace any of its fields."""
    from bob_autonomy.core.behavior_config import BehaviorChoice
    from bob_autonomy.onboard.vessel import VesselConfig

    params = {"H": 1, "goal": list(goal), "max_speed": 1.5, "speed_scale": 1.0}
    values = dict(
        vehicle=f"tcp:127.0.0.1:{sitl.serial0}",
        system_id=1,
        origin=(HOME[0], HOME[1]),
        behavior=BehaviorChoice(behavior="bob-rule", params=params),
        arm_timeout_s=60.0,
    )
    values.update(overrides)
    return VesselConfig(**values)


def asking_link(sitl: RoverSitl, messages: tuple[int, ...], rate_hz: float) -> socket.socket:
    """A TCP connection to the SITL's SERIAL0 that has asked for each of `messages` at rate_hz (Hz), as a vessel
    does (MAV_CMD_SET_MESSAGE_INTERVAL); the caller closes it (`with`)."""
    from firmware_bridge.autopilot_requests import set_message_interval
    from firmware_bridge.commands import Encoder

    link = socket.create_connection(("127.0.0.1", sitl.serial0), timeout=5.0)
    for message in messages:
        link.sendall(set_message_interval(Encoder(), 1, message, rate_hz))
    return link


def sent_s(msg) -> float:
    """ArduPilot's time of sending (s since boot) of a message stamped when it was sent: `time_usec` (RAW_IMU) or
    `time_boot_ms` (SCALED_IMU, ATTITUDE)."""
    return msg.time_usec * 1e-6 if hasattr(msg, "time_usec") else msg.time_boot_ms * 1e-3


def drive(sitl: RoverSitl, config, seconds: float):
    """Run a `bob_autonomy.onboard.vessel.Vessel` with `config` for `seconds` after its start-up; every 0.5 s record
    (wall s since start, the autopilot's own position as east/north m, its heading deg) and the distance of
    the vessel's estimate from it (m). Returns (track, estimate errors, the vessel)."""
    from bob_autonomy.onboard.vessel import Vessel

    vessel = Vessel(config)
    thread = threading.Thread(target=vessel.run, kwargs={"duration_s": seconds}, daemon=True)
    thread.start()
    track, errors = [], []
    t0 = time.monotonic()
    while thread.is_alive():
        time.sleep(0.5)
        if vessel.stats.commands and sitl.seen.positions:
            _t, lat, lon, hdg = sitl.seen.positions[-1]
            truth = np.array(local_xy(lat, lon))
            estimate = vessel.pipeline.estimate(vessel.clock.now()).position[0]
            track.append((time.monotonic() - t0, truth, hdg))
            errors.append(float(np.hypot(*(estimate - truth))))
    thread.join()
    return track, errors, vessel


def home_at(east_m: float, north_m: float) -> tuple[float, float, float, float]:
    """A SITL home east_m, north_m from HOME (the inverse of `local_xy`), same altitude and heading."""
    r = 6378137.0
    lat = HOME[0] + math.degrees(north_m / r)
    lon = HOME[1] + math.degrees(east_m / (r * math.cos(math.radians(HOME[0]))))
    return (lat, lon, HOME[2], HOME[3])


def local_xy(lat: float, lon: float) -> tuple[float, float]:
    """East, north metres from HOME (equirectangular: ample within a few hundred metres)."""
    r = 6378137.0
    return (
        math.radians(lon - HOME[1]) * r * math.cos(math.radians(HOME[0])),
        math.radians(lat - HOME[0]) * r,
    )


class LaggingTcpProxy:
    """A TCP relay to 127.0.0.1:`target` that holds every chunk for a fixed time in each direction: a slow
    telemetry radio or an overloaded autopilot, between a vessel and the SITL. Use as a context manager; connect
    to `port`. to_target_s, from_target_s: how long bytes towards and from the target are held, s."""

    def __init__(self, target: int, *, to_target_s: float, from_target_s: float) -> None:
        self.target, self.delays = target, (to_target_s, from_target_s)
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port = self._listener.getsockname()[1]
        self._stop = threading.Event()
        self._sockets: list[socket.socket] = []

    def __enter__(self) -> LaggingTcpProxy:
        threading.Thread(target=self._accept, daemon=True).start()
        return self

    def _accept(self) -> None:
        self._listener.settimeout(0.2)
        while not self._stop.is_set():
            try:
                client, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            server = socket.create_connection(("127.0.0.1", self.target))
            self._sockets += [client, server]
            for source, sink, delay in ((client, server, self.delays[0]), (server, client, self.delays[1])):
                threading.Thread(target=self._relay, args=(source, sink, delay), daemon=True).start()

    def _relay(self, source: socket.socket, sink: socket.socket, delay_s: float) -> None:
        held: list[tuple[float, bytes]] = []
        lock = threading.Lock()

        def release() -> None:
            while not self._stop.is_set():
                with lock:
                    due = [chunk for t, chunk in held if t <= time.monotonic()]
                    del held[: len(due)]
                for chunk in due:
                    try:
                        sink.sendall(chunk)
                    except OSError:
                        return
                time.sleep(0.01)

        threading.Thread(target=release, daemon=True).start()
        while not self._stop.is_set():
            try:
                chunk = source.recv(65536)
            except OSError:
                return
            if not chunk:
                return
            with lock:
                held.append((time.monotonic() + delay_s, chunk))

    def __exit__(self, *exc) -> None:
        self._stop.set()
        for s in [self._listener, *self._sockets]:
            s.close()
