"""Protocol: HELLO neighbour discovery, link-state updates, Dijkstra routes.

Sans-IO: methods take ``now`` and decoded messages and return messages to send; the
robot decides when to call them. HELLOs are one hop and periodic; a neighbour not
heard for ``hold`` seconds is gone. An LSU carries the origin's position, residual
energy, free buffer space, timestamp, sequence number and neighbour list; it is sent
periodically and when the neighbour set changes, and flooded with a TTL (each robot
forwards a given ``(origin, seq)`` once). Routes are Dijkstra on the topology with the
paper's min-hop metric; residual energy and buffer space are feasibility tests: a
robot below ``min_relay_energy`` is never used as a relay, and the recruiter skips
candidates without the energy to reach the target or the buffer space to record it
(the robot's ``_pick_candidate``; paper 5: residual energy, buffer space and distance).
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field
from typing import Any

from cryptoros.sim import packets as P


@dataclass
class NodeInfo:
    position: tuple[float, float]
    energy: float
    state: int
    stamp: float
    seq: int = 0
    neighbours: tuple[str, ...] = ()
    buffer_free: float = 1.0  # free share of the frame buffer


def dijkstra(adj: dict[str, set[str]], source: str, *, allowed_relay=lambda n: True) -> tuple[dict[str, int], dict[str, str]]:
    """Min-hop distances and first hops from ``source``. ``adj`` need not be symmetric;
    a node failing ``allowed_relay`` can be a destination but is never expanded."""
    dist = {source: 0}
    first: dict[str, str] = {}
    heap = [(0, source, "")]
    done: set[str] = set()
    while heap:
        d, node, hop = heapq.heappop(heap)
        if node in done:
            continue
        done.add(node)
        if node != source:
            first[node] = hop
            if not allowed_relay(node):
                continue
        for nb in sorted(adj.get(node, ())):
            nd = d + 1
            if nd < dist.get(nb, 1 << 30):
                dist[nb] = nd
                heapq.heappush(heap, (nd, nb, nb if node == source else hop))
    return dist, first


@dataclass
class Protocol:
    me: str
    hello_period: float = 1.0
    hold: float = 3.5
    lsu_period: float = 10.0
    lsu_ttl: int = 8
    min_relay_energy: float = 0.0
    neighbours: dict[str, NodeInfo] = field(default_factory=dict)
    topology: dict[str, NodeInfo] = field(default_factory=dict)
    hello_seq: int = 0
    lsu_seq: int = 0
    seen_lsu: dict[str, int] = field(default_factory=dict)
    duplicates: dict[tuple[str, int], int] = field(default_factory=dict)  # copies heard, for suppression
    suppress_after: int = 3
    _routes: tuple[dict[str, int], dict[str, str]] | None = None
    _last_set: frozenset[str] = frozenset()

    # -- HELLO -----------------------------------------------------------------------

    def hello(self, now: float, pos: tuple[float, float], energy: float, state: int, buffer_free: float = 1.0) -> Any:
        self.hello_seq += 1
        return P.make(P.HELLO, source=self.me, seq=self.hello_seq, timestamp=now, position=P.Point(*pos), residual_energy=energy,
                      buffer_free=buffer_free, state=state)

    def on_hello(self, msg: Any, now: float) -> bool:
        """Record a neighbour; True when the neighbour set changed."""
        if msg.source == self.me:
            return False
        new = msg.source not in self.neighbours
        self.neighbours[msg.source] = NodeInfo((msg.position.x, msg.position.y), float(msg.residual_energy), int(msg.state), now, int(msg.seq),
                                             buffer_free=float(msg.buffer_free))
        if new:
            self._routes = None
        return new

    def expire(self, now: float) -> bool:
        gone = [n for n, info in self.neighbours.items() if now - info.stamp > self.hold]
        for n in gone:
            del self.neighbours[n]
        stale = [n for n, info in self.topology.items() if now - info.stamp > 3 * self.lsu_period]
        for n in stale:
            del self.topology[n]
        if gone or stale:
            self._routes = None
        return bool(gone)

    def neighbour_set_changed(self) -> bool:
        cur = frozenset(self.neighbours)
        changed = cur != self._last_set
        self._last_set = cur
        return changed

    # -- LSU -------------------------------------------------------------------------

    def lsu(self, now: float, pos: tuple[float, float], energy: float, state: int, buffer_free: float = 1.0) -> Any:
        self.lsu_seq += 1
        self.seen_lsu[self.me] = self.lsu_seq
        return P.make(
            P.LSU, origin=self.me, sender=self.me, seq=self.lsu_seq, timestamp=now, ttl=self.lsu_ttl,
            position=P.Point(*pos), residual_energy=energy, buffer_free=buffer_free, state=state, neighbours=sorted(self.neighbours),
        )

    def still_worth_forwarding(self, fwd: Any) -> bool:
        """Counter-based flooding (Ni et al., the broadcast storm problem): a robot that
        heard ``suppress_after`` copies while waiting to forward adds nothing."""
        n = self.duplicates.pop((fwd.origin, int(fwd.seq)), 0)
        return n < self.suppress_after

    def on_lsu(self, msg: Any, now: float) -> Any | None:
        """Update the topology; return the LSU to forward (or None)."""
        if msg.origin == self.me or self.seen_lsu.get(msg.origin, -1) >= msg.seq:
            key = (msg.origin, int(msg.seq))
            self.duplicates[key] = self.duplicates.get(key, 0) + 1
            return None
        self.seen_lsu[msg.origin] = int(msg.seq)
        self.topology[msg.origin] = NodeInfo((msg.position.x, msg.position.y), float(msg.residual_energy), int(msg.state), now, int(msg.seq), tuple(msg.neighbours),
                                            buffer_free=float(msg.buffer_free))
        self._routes = None
        if msg.ttl > 1:
            return P.replace(msg, ttl=msg.ttl - 1, sender=self.me)
        return None

    # -- routes ----------------------------------------------------------------------

    def adjacency(self) -> dict[str, set[str]]:
        adj: dict[str, set[str]] = {self.me: set(self.neighbours)}
        for origin, info in self.topology.items():
            adj.setdefault(origin, set()).update(info.neighbours)
            for nb in info.neighbours:  # links are radio links: symmetric
                adj.setdefault(nb, set()).add(origin)
        return adj

    def energy_of(self, node: str) -> float:
        if node in self.neighbours:
            return self.neighbours[node].energy
        if node in self.topology:
            return self.topology[node].energy
        return 0.0

    def routes(self) -> tuple[dict[str, int], dict[str, str]]:
        if self._routes is None:
            self._routes = dijkstra(self.adjacency(), self.me, allowed_relay=lambda n: self.energy_of(n) >= self.min_relay_energy)
        return self._routes

    def next_hop(self, dest: str) -> str | None:
        return self.routes()[1].get(dest)

    def hops(self, dest: str) -> int | None:
        return self.routes()[0].get(dest)

    def routing_table(self) -> list[str]:
        dist, first = self.routes()
        return [f"{d}:{first[d]}:{dist[d]}" for d in sorted(first)]

    def known_robots(self) -> dict[str, NodeInfo]:
        out = dict(self.topology)
        out.update(self.neighbours)
        return out
