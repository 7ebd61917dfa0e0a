"""Recruit: the expanding-ring recruit request (paper section 5.2).

An originator sends a REQUEST with TTL 1; robots forward it while the TTL allows
(each ``(originator, request, ttl)`` once, remembering who it came from). When no
OFFER came back before the ring's timeout, the request is sent again with TTL 2,
and so on up to ``max_ttl``. Two kinds:

* **specific**: ``dest_recruit_originator`` names the robot wanted (chosen from the
  topology table: robots idle at a base first, then the nearest to the target);
* **general**: any robot idle at a base may offer.

A robot only offers if its battery can take it to the target and back to a base
(the robot decides; this module only carries the answer). The originator picks among
offers (idle at a base first, then the nearest) and sends a CONFIRM to that robot.
OFFER and CONFIRM travel back hop by hop: the robot gives each one a next hop from
its routes, or from the pointers this module recorded while the request spread.

Sans-IO: every method takes ``now`` and returns messages; timers are the robot's.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from cryptoros.sim import packets as P

REQUEST, OFFER, CONFIRM = 1, 2, 3
STATE_IDLE_AT_BASE = 4  # must match robot.IDLE


@dataclass
class Pending:
    request_id: int
    dest: str
    target: tuple[float, float]
    ttl: int
    deadline: float
    offers: list[Any] = field(default_factory=list)
    attempts: list[int] = field(default_factory=list)


@dataclass
class Recruit:
    me: str
    timeout: float = 1.5  # per hop of the ring
    max_ttl: int = 6
    next_id: int = 0
    pending: dict[int, Pending] = field(default_factory=dict)
    seen: set[tuple[str, int, int]] = field(default_factory=set)
    offered: set[tuple[str, int]] = field(default_factory=set)
    reverse: dict[tuple[str, int], str] = field(default_factory=dict)  # towards originator
    forward: dict[tuple[str, int], str] = field(default_factory=dict)  # towards candidate
    log: list[tuple[float, str, int, int]] = field(default_factory=list)  # (t, event, req, ttl)

    def _request(self, p: Pending, now: float, pos: tuple[float, float], energy: float) -> Any:
        return P.make(
            P.RECRUIT, kind=REQUEST, request_id=p.request_id, ttl=p.ttl, recruit_originator=self.me, src_hop=self.me,
            dst_hop="", dest_recruit_originator=p.dest, timestamp=now, src_position=P.Point(*pos),
            originator_position=P.Point(*pos), target=P.Point(*p.target), residual_energy=energy, state=0, distance=0.0,
        )

    def start(self, now: float, target: tuple[float, float], pos: tuple[float, float], energy: float, dest: str = "") -> tuple[Any, Pending]:
        self.next_id += 1
        p = Pending(self.next_id, dest, target, 1, now + self.timeout)
        p.attempts.append(1)
        self.pending[p.request_id] = p
        self.seen.add((self.me, p.request_id, 1))
        self.log.append((now, "request", p.request_id, 1))
        return self._request(p, now, pos, energy), p

    def on_timeout(self, request_id: int, now: float, pos: tuple[float, float], energy: float) -> tuple[str, Any]:
        """('confirm', offer) | ('resend', request msg) | ('give_up', None) | ('none', None)."""
        p = self.pending.get(request_id)
        if p is None or now + 1e-9 < p.deadline:
            return "none", None
        if p.offers:
            best = min(p.offers, key=lambda o: (o.state != STATE_IDLE_AT_BASE, o.distance, o.src_hop if False else o.dest_recruit_originator))
            del self.pending[request_id]
            self.log.append((now, "confirm", request_id, p.ttl))
            return "confirm", best
        if p.ttl >= self.max_ttl:
            del self.pending[request_id]
            self.log.append((now, "give_up", request_id, p.ttl))
            return "give_up", None
        p.ttl += 1
        p.attempts.append(p.ttl)
        p.deadline = now + self.timeout * p.ttl
        self.seen.add((self.me, p.request_id, p.ttl))
        self.log.append((now, "request", request_id, p.ttl))
        return "resend", self._request(p, now, pos, energy)

    def on_request(self, msg: Any, now: float, pos: tuple[float, float]) -> tuple[bool, Any | None]:
        """(should this robot consider offering, request to forward or None)."""
        key = (msg.recruit_originator, int(msg.request_id), int(msg.ttl))
        if msg.recruit_originator == self.me or key in self.seen:
            return False, None
        self.seen.add(key)
        self.reverse.setdefault((msg.recruit_originator, int(msg.request_id)), msg.src_hop)
        fwd = None
        if msg.ttl > 1:
            fwd = P.replace(msg, ttl=msg.ttl - 1, src_hop=self.me, src_position=P.Point(*pos))
            # a forwarded copy keeps its ring identity: the originator's ttl is in seen
        consider = (msg.recruit_originator, int(msg.request_id)) not in self.offered and (not msg.dest_recruit_originator or msg.dest_recruit_originator == self.me)
        return consider, fwd

    def promise(self, req: Any) -> None:
        """This robot will offer (after its back-off): later rings of the same request
        must not schedule a second offer."""
        self.offered.add((req.recruit_originator, int(req.request_id)))

    def offer(self, req: Any, now: float, pos: tuple[float, float], energy: float, state: int, distance: float) -> Any:
        self.offered.add((req.recruit_originator, int(req.request_id)))
        return P.make(
            P.RECRUIT, kind=OFFER, request_id=req.request_id, ttl=req.ttl, recruit_originator=req.recruit_originator,
            src_hop=self.me, dst_hop="", dest_recruit_originator=self.me, timestamp=now, src_position=P.Point(*pos),
            originator_position=req.originator_position, target=req.target, residual_energy=energy, state=state, distance=distance,
        )

    def on_offer(self, msg: Any, now: float) -> bool:
        p = self.pending.get(int(msg.request_id))
        if msg.recruit_originator != self.me or p is None:
            return False
        p.offers.append(msg)
        self.log.append((now, "offer", p.request_id, p.ttl))
        return True

    def confirm(self, offer: Any, now: float, pos: tuple[float, float]) -> Any:
        return P.replace(offer, kind=CONFIRM, src_hop=self.me, timestamp=now, originator_position=P.Point(*pos))

    def seen_request_ttls(self, originator: str, request_id: int) -> list[int]:
        return sorted(t for o, r, t in self.seen if o == originator and r == request_id)
