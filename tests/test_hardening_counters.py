"""Issue 17, item 6: counters you can see, and a radio relay that cannot be made to re-bind an agent.

The ground-station component's rejected-input counters go to the log (every minute when they changed, and in
the vessel's stop line) and from the vessels' logs into a process fleet's metrics.json; the relay binds each
agent to the address of its first packet, and a packet carrying that agent's id from anywhere else is dropped
and counted as spoofed.
"""

from __future__ import annotations

import hashlib
import json
import logging
import socket
import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bob_autonomy.core.behavior_config import BehaviorChoice
from bob_autonomy.core.clock import ManualClock, ScaledWallClock
from bob_autonomy.core.interfaces import AgentState, Pose
from bob_autonomy.ground.gcs import GcsComponent, MavlinkCodec
from bob_autonomy.ground.params import ParameterStore
from bob_autonomy.network.mesh import encode_state
from bob_autonomy.onboard.vessel import Vessel, VesselConfig
from sitl.fleets.vessel_logs import gcs_counters, stopped_summary
from sitl.radio.radio_relay import RadioRelay

pytestmark = pytest.mark.xdist_group("realtime")

KEY = hashlib.sha256(b"counter test key").digest()
NAMES = ("unsigned_rejected", "bad_signature", "replay_rejected", "malformed", "out_of_range")


def _bad_input(component: GcsComponent) -> None:
    """2 unsigned frames, 1 wrongly signed, 1 replayed, 1 corrupted, 1 out of range (signed, NaN)."""
    unsigned = MavlinkCodec(200, 190)
    wrong = MavlinkCodec(200, 190, signing_key=hashlib.sha256(b"guess").digest())
    good = MavlinkCodec(255, 190, signing_key=KEY)
    beat = unsigned.mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    component.receive(unsigned.pack(beat), datagram=True)
    component.receive(unsigned.pack(beat), datagram=True)
    component.receive(wrong.pack(beat), datagram=True)
    signed = good.pack(beat)
    component.receive(signed, datagram=True)
    component.receive(signed, datagram=True)  # the same frame again: a replay
    corrupt = bytearray(good.pack(beat))
    corrupt[12] ^= 0xFF
    component.receive(bytes(corrupt), datagram=True)
    nan = good.mav.command_long_encode(component.system_id, 191, mavlink.MAV_CMD_DO_PAUSE_CONTINUE, 0,
                                       float("nan"), 0, 0, 0, 0, 0, 0)  # fmt: skip
    component.receive(good.pack(nan), datagram=True)


EXPECTED = {"unsigned_rejected": 2, "bad_signature": 1, "replay_rejected": 1, "malformed": 1, "out_of_range": 1}


def test_the_gcs_component_logs_its_rejection_counters_every_minute_when_they_change(caplog) -> None:
    clock = ManualClock(0.0)
    component = GcsComponent(3, ParameterStore(), signing_key=KEY, clock=clock.now)
    caplog.set_level(logging.INFO, logger="bob_autonomy.ground.gcs")
    component.tick()
    _bad_input(component)
    assert component.counters.security() == EXPECTED
    clock.advance(30.0)
    component.tick()
    assert "input rejected" not in caplog.text  # not yet a minute
    clock.advance(30.0)
    component.tick()
    lines = [r for r in caplog.records if "input rejected" in r.getMessage()]
    assert len(lines) == 1 and lines[0].levelno == logging.WARNING
    text = "unsigned_rejected 2, bad_signature 1, replay_rejected 1, malformed 1, out_of_range 1"
    assert text in lines[0].getMessage()
    clock.advance(120.0)
    component.tick()  # nothing changed: nothing logged again
    assert len([r for r in caplog.records if "input rejected" in r.getMessage()]) == 1


def _log_to(path: Path) -> logging.Handler:
    """A file handler like `bob-autonomy run --log-file` installs."""
    handler = logging.FileHandler(path)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logging.getLogger().addHandler(handler)
    logging.getLogger().setLevel(logging.INFO)
    return handler


def test_a_vessel_reports_its_gcs_counters_when_it_stops_and_the_fleet_reads_them(tmp_path: Path) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    key_file = tmp_path / "bob.key"
    key_file.write_bytes(KEY)
    config = VesselConfig(
        vehicle=f"udpout:127.0.0.1:{port}",
        system_id=4,
        behavior=BehaviorChoice(behavior="bob-rule", params={"p0": 10.0}),
        origin=(1.3405, 103.9560),
        estimator="simple",
        controller="simple",
        signing_key_file=str(key_file),
        autostart=False,
    )
    log = tmp_path / "vessel-04.log"
    handler = _log_to(log)
    try:
        vessel = Vessel(config, clock=ScaledWallClock(1.0))
        _bad_input(vessel.gcs)
        vessel.shutdown()
    finally:
        logging.getLogger().removeHandler(handler)
        handler.close()
    summary = stopped_summary(log)
    assert summary is not None and {k: summary[f"gcs_{k}"] for k in NAMES} == EXPECTED
    report = gcs_counters({4: log, 5: tmp_path / "vessel-05.log"})  # vessel 5 was killed: no stop line
    assert report == {"total": EXPECTED, "by_vessel": {"4": EXPECTED}, "unreported": [5]}
    json.dumps(report)  # as it goes into metrics.json


# -- the radio relay ----------------------------------------------------------------------------------------


def _packet(agent: int, x: float = 1.0) -> bytes:
    return encode_state(AgentState(agent, 1.0, Pose(x, 2.0, 0.5, 0.1, 0.0), {}), [])


def _socket() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.setblocking(False)
    return s


def _received(s: socket.socket) -> list[bytes]:
    out = []
    while True:
        try:
            out.append(s.recv(65535))
        except BlockingIOError:
            return out


def test_the_relay_never_lets_a_packet_re_bind_another_agents_address() -> None:
    positions = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]])
    relay = RadioRelay(
        3, lambda: positions, lambda: np.ones(3, dtype=bool), channel=None, range_m=300.0,
        broadcast_period_s=1.0, rng=np.random.default_rng(1), port=0,
    )  # fmt: skip
    agents = [_socket() for _ in range(3)]
    attacker = _socket()
    try:
        for k, s in enumerate(agents):  # each agent makes itself known
            s.sendto(_packet(k), relay.address)
            relay.serve(0.05)
        for s in agents:
            _received(s)
        bound = dict(relay.addresses)
        attacker.sendto(_packet(1, x=999.0), relay.address)  # "I am agent 1": to steal its deliveries
        agents[0].sendto(_packet(2, x=999.0), relay.address)  # agent 0 speaking in agent 2's name
        relay.serve(0.05)
        agents[0].sendto(_packet(0), relay.address)  # agent 1 must still hear agent 0, at its own address
        relay.serve(0.05)
        time.sleep(0.02)
        assert relay.addresses == bound
        assert relay.counters()["spoofed"] == 2
        assert _received(attacker) == []
        heard_by_1 = _received(agents[1])
        assert heard_by_1 == [_packet(0)]  # no forged packet relayed to anyone
        assert _received(agents[2]) == [_packet(0)]
        assert relay.latest[1][0].pose.x == 1.0 and relay.latest[2][0].pose.x == 1.0
    finally:
        relay.close()
        for s in [*agents, attacker]:
            s.close()


# -- a process fleet ----------------------------------------------------------------------------------------


def test_a_process_fleet_puts_the_gcs_and_spoof_counters_in_metrics_json(tmp_path: Path) -> None:
    from test_process_fleet import SPEED, aggregation_scenario, free_ports

    from sitl.fleets.process_fleet import ProcessOptions, run_processes_to_directory

    base, (mesh, gcs) = free_ports(2, extra=2)
    options = ProcessOptions(speed=SPEED, base_port=base, mesh_port=mesh, gcs_port=gcs)
    out = tmp_path / "run"
    result = run_processes_to_directory(aggregation_scenario(count=2, duration_s=10.0, switch=False), out, options)
    metrics = json.loads((out / "metrics.json").read_text())
    zeros = dict.fromkeys(NAMES, 0)
    assert metrics["processes"]["exit_codes"] == [0, 0]
    assert metrics["gcs"] == {"total": zeros, "by_vessel": {"1": zeros, "2": zeros}, "unreported": []}
    assert metrics["network"]["spoofed"] == 0 and metrics["network"]["sent"] > 0
    assert result.metrics["gcs"] == metrics["gcs"]
