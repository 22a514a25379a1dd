"""Mesh security in scenarios (issue 15): the fleet key, plausibility limits, intruders and faulty broadcasts.

A scenario's `[network.security]` table (all optional):

    key = true                 # the fleet shares a key: every member signs its packets, every receiver
                               # checks them (bob_autonomy.network.mesh_auth); lockstep runs draw the key from the seed
    window_s = 5.0             # freshness window of the timestamps, s of the mesh clock (here simulated time)
    plausibility = { max_speed_mps = 2.0, slack_m = 20.0, range_factor = 1.5 }   # or { enabled = false }

    [[network.security.intruders]]   # a radio that is not a member (it has no key)
    claims_agent = 0           # the agent id its packets carry
    position = [x, y]          # where it is, m (packets reach the members within reach_m of here)
    claimed_position = [x, y]  # the position its packets claim, m (default: where it is)
    reach_m = 600.0            # how far its radio carries, m (default: the network's range); see below
    start_s = 0.0              # when it starts (and stop_s, when it stops; default never)

    [[network.security.faults]]      # members that broadcast a wrong value while taking part
    group = "faulty"           # or agents = [9]
    heading_offset_deg = 120.0 # what they broadcast: their own heading turned by this much
    start_s = 0.0

In the lockstep fleet (`sitl.radio.medium.BroadcastMedium`) an intruder transmits in every broadcast round; a
member hears it if it is within `reach_m` of the intruder, through the radio channel model (when the
scenario has one) evaluated at the distance scaled by the channel's nominal range over `reach_m` (a
stronger transmitter looks nearer); intruders are not counted as interferers. With a key, every packet of
a round is really encoded and signed (`bob_autonomy.network.mesh.encode_state`) and its tag checked once
(`bob_autonomy.network.mesh_auth.verify_tag`: the check is the same for every listener); replays and staleness are
judged per listener from the timestamps, and plausibility per listener with
`bob_autonomy.core.plausibility.implausible`, exactly the checks a vessel makes. Listeners use the sender's
float64 state, not the packet's float32 copy, so a keyed run differs from a keyless one only by what the
checks refuse.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator

from behaviors.base import SwarmTable
from bob_autonomy.core.interfaces import AgentState, Pose
from bob_autonomy.core.plausibility import REASONS as PLAUSIBILITY_REASONS
from bob_autonomy.core.plausibility import PlausibilityLimits
from bob_autonomy.network.mesh import MAX_PACKET_BYTES, PacketError, encode_state, signed_part
from bob_autonomy.network.mesh_auth import DEFAULT_WINDOW_S, REASONS, AuthError, MeshSigner, verify_tag

__all__ = [
    "REJECT_REASONS",
    "FaultSpec",
    "IntruderSpec",
    "MediumSecurity",
    "MeshSecuritySpec",
    "PlausibilitySpec",
    "add_mesh_criteria",
    "medium_security",
    "mesh_log_counters",
    "write_fleet_key",
]

MAX_COORDINATE_M = 1e7
Coordinate = Annotated[float, Field(ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M)]
Point = tuple[Coordinate, Coordinate]
PositiveFloat = Annotated[float, Field(gt=0)]
# Why a delivery was refused, in the order the checks run; code k + 1 in the medium's arrays.
REJECT_REASONS = (*REASONS, *(PLAUSIBILITY_REASONS[k] for k in sorted(PLAUSIBILITY_REASONS)))
_AUTH_CODE = {reason: k + 1 for k, reason in enumerate(REJECT_REASONS)}


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class PlausibilitySpec(_Model):
    """Limits of `bob_autonomy.core.plausibility.PlausibilityLimits` (the radio range is the network's)."""

    enabled: bool = True
    max_speed_mps: PositiveFloat = 2.0
    slack_m: PositiveFloat = 20.0
    range_factor: PositiveFloat = 1.5

    def limits(self, range_m: float) -> PlausibilityLimits | None:
        if not self.enabled:
            return None
        return PlausibilityLimits(self.max_speed_mps, self.slack_m, range_m, self.range_factor)


class IntruderSpec(_Model):
    """A keyless radio broadcasting as `claims_agent` (see the module docstring)."""

    claims_agent: int = Field(ge=0, le=0xFFFF)
    position: Point
    claimed_position: Point | None = None
    heading_deg: float = Field(default=0.0, ge=-360.0, le=360.0)
    reach_m: PositiveFloat | None = None
    start_s: float = Field(default=0.0, ge=0.0)
    stop_s: float | None = Field(default=None, gt=0.0)


class FaultSpec(_Model):
    """Members (a `group` or `agents` by index) broadcasting their heading turned by `heading_offset_deg`."""

    group: str | None = None
    agents: list[Annotated[int, Field(ge=0)]] | None = None
    heading_offset_deg: float = Field(ge=-360.0, le=360.0)
    start_s: float = Field(default=0.0, ge=0.0)

    @model_validator(mode="after")
    def _one_selection(self) -> FaultSpec:
        if (self.group is None) == (self.agents is None):
            raise ValueError("a fault names either a group or agents (not both)")
        return self


class MeshSecuritySpec(_Model):
    """`[network.security]` of a scenario (see the module docstring)."""

    key: bool = False
    window_s: PositiveFloat = DEFAULT_WINDOW_S
    plausibility: PlausibilitySpec = PlausibilitySpec()
    intruders: list[IntruderSpec] = []
    faults: list[FaultSpec] = []

    def reference_problem(self, group_names: list[str], n_agents: int) -> str | None:
        """What is wrong with the groups and agents the faults name, or None."""
        for k, fault in enumerate(self.faults):
            if fault.group is not None and fault.group not in group_names:
                return f"network.security.faults.{k}.group {fault.group!r} is not a group ({group_names})"
            if fault.agents and max(fault.agents) >= n_agents:
                return (
                    f"network.security.faults.{k}.agents: agent {max(fault.agents)} does not exist "
                    f"(agents 0..{n_agents - 1})"
                )
        return None


class MediumSecurity:
    """The lockstep medium's key, checks, intruders and faults, for `n` members (see the module docstring).

    key: the fleet key or None. group_of: (n,) group index of each member; group_names: their names.
    range_m: the network's range, m (plausibility's radio range and the intruders' default reach).
    """

    def __init__(
        self,
        spec: MeshSecuritySpec,
        key: bytes | None,
        group_of: NDArray[np.intp],
        group_names: list[str],
        range_m: float,
    ) -> None:
        n = int(group_of.size)
        problem = spec.reference_problem(group_names, n)
        if problem:
            raise ValueError(problem)
        self.n, self.key, self.window_s = n, key, float(spec.window_s)
        self.limits = spec.plausibility.limits(range_m)
        self.now = 0.0
        self.signers = [MeshSigner(key, lambda: self.now) for _ in range(n)] if key is not None else []
        intruders = spec.intruders
        self.m = len(intruders)
        self.intruder_position = np.array([i.position for i in intruders], dtype=float).reshape(-1, 2)
        self.intruder_claimed = np.array([i.claimed_position or i.position for i in intruders], dtype=float).reshape(
            -1, 2
        )
        self.intruder_claims = np.array([i.claims_agent for i in intruders], dtype=np.intp)
        self.intruder_heading = np.radians([i.heading_deg for i in intruders])
        self.intruder_reach_m = np.array([i.reach_m or range_m for i in intruders], dtype=float)
        self.intruder_start_s = np.array([i.start_s for i in intruders], dtype=float)
        self.intruder_stop_s = np.array([i.stop_s if i.stop_s is not None else math.inf for i in intruders])
        self.heading_offset = np.zeros(n)
        self.fault_start_s = np.full(n, math.inf)
        for fault in spec.faults:
            agents = (
                np.flatnonzero(group_of == group_names.index(fault.group))
                if fault.group is not None
                else np.array(fault.agents, dtype=np.intp)
            )
            self.heading_offset[agents] = math.radians(fault.heading_offset_deg)
            self.fault_start_s[agents] = fault.start_s
        self.n_ids = max(n, int(self.intruder_claims.max()) + 1 if self.m else n)
        self.rejected = np.zeros((len(REJECT_REASONS), self.n_ids), dtype=np.int64)
        self.intruder_sent = 0
        self.intruder_delivered = 0
        self.intruder_refused = 0
        self.packet_bytes = 0  # largest packet really encoded (keyed runs)

    @property
    def checks(self) -> bool:
        """Whether deliveries are vetted at all (a key or plausibility limits)."""
        return self.key is not None or self.limits is not None

    def intruders_on(self, t: float) -> NDArray[np.bool_]:
        """(m,) which intruders transmit at time t (s)."""
        return (self.intruder_start_s <= t + 1e-9) & (t < self.intruder_stop_s)

    def faulty(self, agents: NDArray[np.intp], t: float) -> NDArray[np.bool_]:
        """Which of `agents` broadcast a faulty heading at time t (s)."""
        return self.fault_start_s[agents] <= t + 1e-9

    def authenticate(self, t: float, table: SwarmTable, rows: NDArray[np.intp], senders: NDArray[np.intp]):
        """(code, stamp) per message row: the packets of one round encoded, members' signed with the key and
        every tag checked (code 0, or that of ``unsigned`` / ``bad_mac``); stamp in 10 us units (-1 none).
        `senders`: the transmitter of each row (< n: a member; >= n: an intruder, which has no key)."""
        self.now = float(t)
        code = np.zeros(rows.size, dtype=np.int8)
        stamp = np.full(rows.size, -1, dtype=np.int64)
        fields = list(table.memory)
        for k, (row, sender) in enumerate(zip(rows.tolist(), senders.tolist(), strict=True)):
            state = AgentState(
                int(table.ids[row]),
                float(t),
                Pose(
                    float(table.position[row, 0]),
                    float(table.position[row, 1]),
                    float(table.heading[row]),
                    float(table.velocity[row, 0]),
                    float(table.velocity[row, 1]),
                ),
                {name: table.memory[name][row] for name in fields},
            )
            try:
                packet = encode_state(state, fields, self.signers[sender] if sender < self.n else None)
            except PacketError as error:
                raise ValueError(f"{error} (packet limit {MAX_PACKET_BYTES} bytes with the key's 14)") from None
            self.packet_bytes = max(self.packet_bytes, len(packet))
            try:
                stamp[k] = verify_tag(self.key, state.agent_id, signed_part(packet))
            except AuthError as error:
                code[k] = _AUTH_CODE[error.reason]
        return code, stamp

    def count(self, code: NDArray[np.int8], claimed: NDArray[np.intp]) -> None:
        """Add refused deliveries (code > 0) to `rejected`, by reason and claimed sender id."""
        bad = code > 0
        np.add.at(self.rejected, (code[bad].astype(np.intp) - 1, claimed[bad]), 1)

    def counters(self) -> dict:
        """For metrics.json: `rejected` reason -> {claimed agent id -> deliveries refused} (every reason of
        REJECT_REASONS listed), `rejected_total`, the intruders' transmissions and deliveries, and the
        largest packet on the air (keyed runs)."""
        rejected = {
            reason: {str(k): int(v) for k, v in enumerate(self.rejected[r]) if v}
            for r, reason in enumerate(REJECT_REASONS)
        }
        out = {
            "key": self.key is not None,
            "plausibility": self.limits is not None,
            "rejected": rejected,
            "rejected_total": int(self.rejected.sum()),
        }
        if self.m:
            out.update(
                intruder_sent=self.intruder_sent,
                intruder_delivered=self.intruder_delivered,
                intruder_refused=self.intruder_refused,
            )
        if self.packet_bytes:
            out["packet_bytes"] = self.packet_bytes
        return out


def add_mesh_criteria(metrics: dict) -> dict:
    """With intruders on the air (`metrics["network"]["mesh"]` has their counters): the criterion
    `intruder_packets_refused` (members heard at least one intruder packet, and refused every one they
    heard), and `passed` updated. Returns `metrics`."""
    mesh = metrics.get("network", {}).get("mesh", {})
    if "intruder_delivered" in mesh and "criteria" in metrics:
        heard = mesh["intruder_delivered"]
        metrics["criteria"]["intruder_packets_refused"] = heard > 0 and mesh["intruder_refused"] == heard
        metrics["passed"] = bool(all(metrics["criteria"].values()))
    return metrics


def code_of(reason: str) -> int:
    """The medium's code of a rejection reason (REJECT_REASONS)."""
    return _AUTH_CODE[reason]


def medium_security(scenario, group_of: NDArray[np.intp]) -> MediumSecurity:
    """The lockstep medium's security for a `sitl.experiments.scenario.Scenario` (its agents' groups `group_of`): the
    fleet key, when the scenario has one, is drawn from the scenario's seed (its own stream)."""
    net = scenario.network
    spec: MeshSecuritySpec = net.security
    channel = net.channel()
    range_m = net.range_m if channel is None else min(net.range_m, channel.nominal_range_m)
    key = np.random.default_rng([scenario.seed, 5]).bytes(32) if spec.key else None
    return MediumSecurity(spec, key, group_of, [g.name for g in scenario.groups], range_m)


def write_fleet_key(scenario, directory: Path) -> Path | None:
    """For a process fleet: the scenario's fleet key (the same bytes a lockstep run of it uses) written to
    `directory`/mesh.key (32 raw bytes, owner-only), to hand to every `bob-autonomy run --mesh-key`; None when
    the scenario has no key."""
    if not scenario.network.security.key:
        return None
    path = Path(directory) / "mesh.key"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as out:
        out.write(np.random.default_rng([scenario.seed, 5]).bytes(32))
    return path


_MESH_LINE = re.compile(r"vessel (\d+) mesh: (\{.*\})\s*$")


def mesh_log_counters(logs: Mapping[int, Path]) -> dict:
    """What the vessels of a process fleet said their mesh refused (the `vessel N mesh: {...}` line each
    `bob-autonomy run` logs when it stops): `by_vessel` (system id as text -> that line's counters),
    `rejected_total` (every refusal, key and plausibility, over the vessels that reported) and `unreported`
    (system ids whose log has no such line: killed, or no mesh)."""
    by_vessel: dict[str, dict] = {}
    unreported: list[int] = []
    total = 0
    for system_id, log in sorted(logs.items()):
        found = None
        with contextlib.suppress(OSError):
            for line in Path(log).read_text(errors="replace").splitlines():
                match = _MESH_LINE.search(line)
                if match and int(match.group(1)) == system_id:
                    with contextlib.suppress(json.JSONDecodeError):
                        found = json.loads(match.group(2))
        if not isinstance(found, dict):
            unreported.append(system_id)
            continue
        by_vessel[str(system_id)] = found
        for table in (found.get("rejected", {}), found.get("implausible", {})):
            total += sum(int(v) for by_id in table.values() if isinstance(by_id, dict) for v in by_id.values())
    return {"rejected_total": total, "by_vessel": by_vessel, "unreported": unreported}
