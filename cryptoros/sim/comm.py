"""Communication: periodic sharing of the robot's own map, and what peers shared.

A MapUpdate carries the bounding box of the sender's *own* observations (never what
it heard from others, so every cell has one accountable author), its position and
current goal. A receiver keeps the newest map per peer (by sequence number, then
timestamp) in its :class:`~cryptoros.sim.explorer.Belief`, and peers' positions and
goals for the explorer's overlap penalty.

Optional plausibility check (a defence against an *insider* with valid keys): a peer
may only claim cells within lidar range of positions it reported, and its reported
positions may not move faster than a robot can. It bounds what a lying insider can
claim to a swath a real robot could have seen; it does not make it honest.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cryptoros.sim import packets as P
from cryptoros.sim.explorer import Belief
from cryptoros.sim.world import UNKNOWN


@dataclass
class PeerTrail:
    last_pos: tuple[float, float]
    last_t: float
    seen: np.ndarray  # bool grid: cells within lidar range of a reported position


@dataclass
class Comm:
    me: str
    resolution: float
    share_period: float = 5.0
    lidar_cells: float = 17.0
    max_speed: float = 0.22
    plausibility: bool = False
    seq: int = 0
    last: dict[str, tuple[int, float]] = field(default_factory=dict)
    peers_at: dict[str, tuple[float, tuple[float, float], tuple[float, float]]] = field(default_factory=dict)
    trails: dict[str, PeerTrail] = field(default_factory=dict)
    implausible: int = 0

    def share(self, now: float, belief: Belief, pos: tuple[float, float], goal: tuple[float, float], complete: bool) -> Any:
        self.seq += 1
        r0, c0, data = belief.own_patch()
        h, w = data.shape
        return P.make(
            P.MAP, source=self.me, seq=self.seq, timestamp=now, position=P.Point(*pos), goal=P.Point(*goal),
            exploration_complete=complete, origin_x=c0, origin_y=r0, width=w, height=h, data=data.reshape(-1),
        )

    def note_position(self, peer: str, now: float, pos: tuple[float, float], shape: tuple[int, int]) -> bool:
        """Record a reported position; False when it moved implausibly fast."""
        prev = self.peers_at.get(peer)
        goal = prev[2] if prev else pos
        self.peers_at[peer] = (now, pos, goal)
        if not self.plausibility:
            return True
        tr = self.trails.get(peer)
        if tr is None:
            tr = self.trails[peer] = PeerTrail(pos, now, np.zeros(shape, dtype=bool))
        else:
            dt = max(0.0, now - tr.last_t)
            dist = float(np.hypot(pos[0] - tr.last_pos[0], pos[1] - tr.last_pos[1]))
            if dist > self.max_speed * dt * 1.5 + 2 * self.resolution:
                return False
            tr.last_pos, tr.last_t = pos, now
        self._stamp(tr.seen, pos)
        return True

    def _stamp(self, seen: np.ndarray, pos: tuple[float, float]) -> None:
        r, c = pos[1] / self.resolution, pos[0] / self.resolution
        R = self.lidar_cells + 1.5
        H, W = seen.shape
        r0, r1 = max(0, int(r - R)), min(H, int(r + R) + 1)
        c0, c1 = max(0, int(c - R)), min(W, int(c + R) + 1)
        if r0 >= r1 or c0 >= c1:
            return
        rr, cc = np.ogrid[r0:r1, c0:c1]
        seen[r0:r1, c0:c1] |= (rr - r) ** 2 + (cc - c) ** 2 <= R * R

    def on_map(self, msg: Any, now: float, belief: Belief) -> tuple[bool, str, int]:
        """(accepted, reason if not, cells newly known)."""
        src = msg.source
        if src == self.me:
            return False, "own", 0
        key = (int(msg.seq), float(msg.timestamp))
        if src in self.last and key <= self.last[src]:
            return False, "stale", 0
        pos = (float(msg.position.x), float(msg.position.y))
        if not self.note_position(src, now, pos, belief.shape):
            self.implausible += 1
            return False, "implausible_motion", 0
        h, w = int(msg.height), int(msg.width)
        data = np.asarray(msg.data, dtype=np.int8)
        if data.size != h * w:
            return False, "malformed", 0
        data = data.reshape(h, w)
        if self.plausibility and data.size:
            tr = self.trails[src]
            r0, c0 = int(msg.origin_y), int(msg.origin_x)
            H, W = belief.shape
            if r0 < 0 or c0 < 0 or r0 + h > H or c0 + w > W:
                return False, "malformed", 0
            claimed = data != UNKNOWN
            bad = int(np.count_nonzero(claimed & ~tr.seen[r0 : r0 + h, c0 : c0 + w]))
            if bad > 0.02 * max(1, int(np.count_nonzero(claimed))):
                self.implausible += 1
                return False, "implausible_map", 0
        self.last[src] = key
        self.peers_at[src] = (now, pos, (float(msg.goal.x), float(msg.goal.y)))
        gained = belief.merge_peer(src, int(msg.origin_y), int(msg.origin_x), data)
        return True, "", gained

    def others(self, now: float, horizon: float = 15.0) -> list[tuple[float, float]]:
        """Recent positions and goals of peers, in metres."""
        out = []
        for t, pos, goal in self.peers_at.values():
            if now - t <= horizon:
                out.append(pos)
                out.append(goal)
        return out
