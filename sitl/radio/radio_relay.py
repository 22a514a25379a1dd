"""The simulated radio medium of a process fleet: one UDP port that every autonomy process sends its mesh packets to.

Each datagram is one mesh packet (`bob_autonomy.network.mesh`). The relay tells the
sender by the agent id inside the packet (`bob_autonomy.network.mesh.packet_agent_id`,
agent = system id - 1) and binds that agent to the address of its first packet,
for the relay's lifetime; a datagram that is not a valid packet (values in range
included) is counted (`invalid`) and dropped. A later packet carrying an agent's
id from another address, or a packet from a bound address carrying another
agent's id, is a spoof (issue 17): counted (`spoofed`), dropped, and it never
re-binds the agent's address, so nobody can take over another agent's deliveries
or speak in its name. Every packet is
offered to every other agent whose address is known, with the channel model of
`sitl.radio.channel.RadioChannel` applied to the *true* positions of the simulated
vehicles (never to what the agents believe):

* beyond the range (`range_m`, at most the radio's nominal range) nothing is
  heard (`out_of_range`, neither delivered nor dropped, as in the lockstep
  `sitl.radio.medium.BroadcastMedium`);
* a packet over the radio's payload limit is dropped for every listener
  (`oversize` packets, each listener counted in `dropped`);
* otherwise `RadioChannel.deliver(rng, distance, interferers)` decides, where a
  listener's interferers are the other transmitters (neither the sender nor the
  listener) within range of it that sent within the last broadcast period;
* a delivered packet goes, unchanged, to the listener's address after a latency
  drawn by `RadioChannel.latency` (simulated seconds).

Intruders (`sitl.radio.mesh_security.IntruderSpec`, issue 15): radios that are not
members transmit, every broadcast period of simulated time from their
`start_s`, an unsigned packet claiming their agent id and position (memory
fields empty); members within the intruder's `reach_m` hear it through the
channel model at the distance scaled by nominal range over reach (as in the
lockstep medium), after the channel's latency. They never pass the address
checks above: on the air there are no addresses. Counted in `intruder_sent`
and `intruder_delivered`; what the members made of them is in their logs.

Without a channel model (a scenario without `[network] radio`) every agent in
range gets every packet at once. Removed (inactive) vehicles neither send nor
hear. All draws come from the seeded generator given, so a relay fed the same
packets in the same order decides the same way. The latest state each agent
broadcast is kept (`latest`): the process fleet records it as what the agent
believed of its pose.
"""

from __future__ import annotations

import contextlib
import heapq
import itertools
import math
import select
import socket
import time
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from bob_autonomy.core.interfaces import AgentState, Pose
from bob_autonomy.network.mesh import PacketError, decode_state, encode_state, packet_agent_id
from sitl.radio.channel import RadioChannel
from sitl.radio.mesh_security import IntruderSpec

DEFAULT_MESH_PORT = 15000
FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


class RadioRelay:
    """The mesh of n agents over UDP (see the module docstring).

    positions: returns the agents' true positions (n, 2), m. active: returns (n,) bool, False for removed
    vehicles. channel: the radio model, or None for perfect delivery within range_m. broadcast_period_s: the
    window (s) in which a transmitter counts as an interferer. rng: draws deliveries and latencies. clock:
    simulated time, s (default: wall time). memory_fields: the swarm's memory field names, in packet order
    (to decode `latest`). intruders: keyless radios on the channel (see the module docstring).
    """

    def __init__(
        self,
        n_agents: int,
        positions: Callable[[], FloatArray],
        active: Callable[[], BoolArray],
        *,
        channel: RadioChannel | None,
        range_m: float,
        broadcast_period_s: float,
        rng: np.random.Generator,
        clock: Callable[[], float] = time.monotonic,
        host: str = "127.0.0.1",
        port: int = DEFAULT_MESH_PORT,
        memory_fields: Sequence[str] = (),
        intruders: Sequence[IntruderSpec] = (),
    ) -> None:
        if range_m <= 0 or broadcast_period_s <= 0:
            raise ValueError("range_m and broadcast_period_s must be positive")
        self.n = int(n_agents)
        self.positions, self.active, self.clock = positions, active, clock
        self.channel, self.rng = channel, rng
        self.range_m = min(range_m, channel.nominal_range_m) if channel is not None else float(range_m)
        self.period_s = float(broadcast_period_s)
        self.memory_fields = list(memory_fields)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind((host, port))
        except OSError as error:
            self.sock.close()
            raise OSError(
                f"cannot bind the radio relay to UDP {host}:{port} ({error}); choose another --mesh-port"
            ) from error
        self.sock.setblocking(False)
        self.address = self.sock.getsockname()
        self.addresses: dict[int, tuple[str, int]] = {}  # agent -> the address of its first packet
        self._agent_at: dict[tuple[str, int], int] = {}  # the inverse: one agent per address
        self.last_sent_s = np.full(self.n, -np.inf)
        self.latest: dict[int, tuple[AgentState, float]] = {}  # agent -> (state, simulated time received)
        self._queue: list[tuple[float, int, bytes, tuple[str, int]]] = []
        self._seq = itertools.count()
        self.sent = self.delivered = self.dropped = self.invalid = 0
        self.out_of_range = self.oversize = self.from_inactive = self.spoofed = 0
        self.intruders = list(intruders)
        self._intruder_next_s = [float(spec.start_s) for spec in self.intruders]
        self.intruder_sent = self.intruder_delivered = 0

    def fileno(self) -> int:
        return self.sock.fileno()

    def counters(self) -> dict[str, int]:
        """sent (valid packets from active agents), delivered and dropped (per listener in range), invalid
        datagrams, out_of_range (listener-packet pairs beyond range), oversize packets, from_inactive packets,
        spoofed packets (an agent's id from another address than its own); with intruders, intruder_sent and
        intruder_delivered (listener-packet pairs)."""
        names = ("sent", "delivered", "dropped", "invalid", "out_of_range", "oversize", "from_inactive", "spoofed")
        if self.intruders:
            names += ("intruder_sent", "intruder_delivered")
        return {name: int(getattr(self, name)) for name in names}

    # -- in ------------------------------------------------------------------------------------------------

    def read(self) -> int:
        """Take every datagram waiting and offer each to the listeners; returns how many were read."""
        count = 0
        while True:
            try:
                data, sender = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return count
            except ConnectionRefusedError:  # ICMP for an earlier send to an agent that has gone
                continue
            count += 1
            self.offer(data, sender)

    def offer(self, packet: bytes, sender: tuple[str, int]) -> None:
        """One datagram from `sender`: identify its agent, then deliver or drop it for each other agent."""
        agent = packet_agent_id(packet)
        if agent is None or not 0 <= agent < self.n:
            self.invalid += 1
            return
        if not self._bind(agent, sender):
            self.spoofed += 1
            return
        now = float(self.clock())
        active = np.asarray(self.active(), dtype=bool)
        if not active[agent]:
            self.from_inactive += 1  # a removed vessel's radio is off
            return
        self.sent += 1
        self.last_sent_s[agent] = now
        with contextlib.suppress(PacketError):  # packet_agent_id has already decoded it
            self.latest[agent] = (decode_state(packet, self.memory_fields), now)
        listeners = np.array([j for j in self.addresses if j != agent and active[j]], dtype=np.intp)
        if listeners.size == 0:
            return
        position = np.asarray(self.positions(), dtype=float)
        distance = np.hypot(*(position[listeners] - position[agent]).T)
        near = distance <= self.range_m
        self.out_of_range += int(np.count_nonzero(~near))
        listeners, distance = listeners[near], distance[near]
        if listeners.size == 0:
            return
        if self.channel is None:
            ok, latency = np.ones(listeners.size, dtype=bool), np.zeros(listeners.size)
        elif len(packet) > self.channel.payload_limit_bytes:
            self.oversize += 1
            self.dropped += int(listeners.size)
            return
        else:
            ok = self.channel.deliver(self.rng, distance, self._interferers(agent, listeners, position, active, now))
            latency = self.channel.latency(self.rng, int(np.count_nonzero(ok)))
        self.dropped += int(np.count_nonzero(~ok))
        self.delivered += int(np.count_nonzero(ok))
        for listener, delay in zip(listeners[ok].tolist(), latency.tolist(), strict=True):
            heapq.heappush(self._queue, (now + delay, next(self._seq), packet, self.addresses[listener]))
        self.flush()

    def _bind(self, agent: int, sender: tuple[str, int]) -> bool:
        """Whether `sender` may speak for `agent`: its first address binds it, and an address speaks for one
        agent only."""
        bound = self.addresses.get(agent)
        if bound is not None:
            return bound == sender
        if sender in self._agent_at:
            return False  # this address already speaks for another agent
        self.addresses[agent] = sender
        self._agent_at[sender] = agent
        return True

    def _interferers(
        self, sender: int, listeners: NDArray[np.intp], position: FloatArray, active: BoolArray, now: float
    ) -> FloatArray:
        """Per listener: transmitters of the last broadcast period within range of it, sender and listener
        excluded."""
        transmitting = np.flatnonzero(active & (now - self.last_sent_s <= self.period_s + 1e-9))
        transmitting = transmitting[transmitting != sender]
        if transmitting.size == 0:
            return np.zeros(listeners.size)
        gap = np.hypot(*(position[listeners][:, None, :] - position[transmitting][None, :, :]).transpose(2, 0, 1))
        heard = (gap <= self.range_m) & (listeners[:, None] != transmitting[None, :])
        return heard.sum(axis=1).astype(float)

    # -- out -----------------------------------------------------------------------------------------------

    def next_due_s(self) -> float | None:
        """Simulated time (s) of the next delivery waiting or intruder transmission, or None."""
        due = [self._queue[0][0]] if self._queue else []
        for t, spec in zip(self._intruder_next_s, self.intruders, strict=True):
            if spec.stop_s is None or t < spec.stop_s:
                due.append(t)
        return min(due) if due else None

    def _intrude(self, now: float) -> None:
        """The intruders whose transmission is due send one unsigned packet each (see the module docstring)."""
        for k, spec in enumerate(self.intruders):
            due = self._intruder_next_s[k]
            if now + 1e-9 < due or (spec.stop_s is not None and now >= spec.stop_s):
                continue
            self._intruder_next_s[k] = due + self.period_s * (math.floor((now - due) / self.period_s) + 1)
            claimed = spec.claimed_position or spec.position
            pose = Pose(float(claimed[0]), float(claimed[1]), math.radians(spec.heading_deg))
            packet = encode_state(AgentState(spec.claims_agent, now, pose, {}), self.memory_fields)
            self.intruder_sent += 1
            active = np.asarray(self.active(), dtype=bool)
            listeners = np.array([j for j in self.addresses if active[j] and j != spec.claims_agent], dtype=np.intp)
            if listeners.size == 0:
                continue
            reach = spec.reach_m or self.range_m
            distance = np.hypot(*(np.asarray(self.positions(), dtype=float)[listeners] - spec.position).T)
            listeners, distance = listeners[distance <= reach], distance[distance <= reach]
            if self.channel is None:
                ok, latency = np.ones(listeners.size, dtype=bool), np.zeros(listeners.size)
            else:
                position = np.asarray(self.positions(), dtype=float)
                interferers = self._interferers(-1, listeners, position, active, now)
                scaled = distance * self.channel.nominal_range_m / reach
                ok = self.channel.deliver(self.rng, scaled, interferers)
                latency = self.channel.latency(self.rng, int(np.count_nonzero(ok)))
            self.intruder_delivered += int(np.count_nonzero(ok))
            for listener, delay in zip(listeners[ok].tolist(), latency.tolist(), strict=True):
                heapq.heappush(self._queue, (now + delay, next(self._seq), packet, self.addresses[listener]))

    def flush(self) -> int:
        """Send the deliveries that are due now (intruders transmit first when due); returns how many were sent."""
        now, sent = float(self.clock()), 0
        if self.intruders:
            self._intrude(now)
        while self._queue and self._queue[0][0] <= now + 1e-9:
            _, _, packet, address = heapq.heappop(self._queue)
            try:
                self.sock.sendto(packet, address)
                sent += 1
            except (BlockingIOError, ConnectionRefusedError):
                pass  # a full buffer or a vanished agent: the radio is lossy anyway
        return sent

    def serve(self, wall_s: float) -> None:
        """Relay for `wall_s` wall seconds (standalone use, when `clock` is wall time)."""
        end = time.monotonic() + wall_s
        while (left := end - time.monotonic()) > 0:
            due = self.next_due_s()
            wait = left if due is None else max(0.0, min(left, due - float(self.clock())))
            ready, _, _ = select.select([self.sock], [], [], wait)
            if ready:
                self.read()
            self.flush()

    def close(self) -> None:
        """Close the socket (undelivered packets are lost)."""
        self.sock.close()
