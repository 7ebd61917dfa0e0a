"""Attackers: each a radio node driven by the same :class:`~cryptoros.sim.robot.Host`.

The paper's three first, then more:

* ``impersonate``: a robot outside the team claims the whole map is explored (a
  MapUpdate with every cell free). ``impersonate-insider``: the same from a robot
  holding a valid team key (authentication cannot tell; the plausibility check in
  :mod:`cryptoros.sim.comm` bounds what it can claim).
* ``mitm``: hears every map update and re-sends it at once with the map data and goal
  erased and the sequence number pushed ahead (so the author's next genuine updates
  look stale), recomputing a bare SHA-256 digest when there is one; it cannot
  recompute a MAC or a signature.
* ``eavesdrop``: records everything and reconstructs what it can parse: the map and
  robots' positions.
* ``replay``: re-sends recorded frames byte for byte ``replay_delay`` seconds later.
* ``flood``: puts junk frames on the air at a high rate.
* ``false-recruit``: sends recruit requests for far targets to every robot it hears and
  confirms every offer, so robots drive away and drain their batteries.
* ``blackhole``: an insider that advertises links to everyone (so routes go through
  it) and forwards nothing.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cryptoros.sim import packets as P
from cryptoros.sim.explorer import Belief
from cryptoros.sim.protocol import Protocol
from cryptoros.sim.recruit import OFFER, REQUEST, CONFIRM
from cryptoros.sim.security import F_DIGEST, F_ENC, SecurityManager, header_bytes, _u8

import hashlib

ATTACKS = ("impersonate", "impersonate-insider", "mitm", "eavesdrop", "replay", "flood", "false-recruit", "blackhole")
INSIDER = {"impersonate-insider", "blackhole"}


class Attacker:
    kind = "attacker"

    def __init__(self, name: str, host: Any, rng: np.random.Generator, security: SecurityManager, cell: tuple[int, int], shape: tuple[int, int], resolution: float) -> None:
        self.name = name
        self.host = host
        self.rng = rng
        self.security = security
        self.cell = cell
        self.shape = shape
        self.resolution = resolution
        self.stats: dict[str, Any] = {"frames_sent": 0}
        self.hello_seq = 0

    @property
    def pos(self) -> tuple[float, float]:
        return (self.cell[1] * self.resolution, self.cell[0] * self.resolution)

    def alive(self) -> bool:
        return True

    def start(self) -> None:
        for m, t in self.security.start(self.host.now()):
            self.send(m, t)

    def send(self, msg: Any, typename: str) -> None:
        t, data = self.security.seal(msg, typename, self.host.now())
        self.security.take_cpu()
        self.raw(t, data)

    def raw(self, typename: str, data: bytes) -> None:
        self.stats["frames_sent"] += 1
        self.host.broadcast(typename, data)

    def hello(self) -> None:
        self.hello_seq += 1
        self.send(P.make(P.HELLO, source=self.name, seq=self.hello_seq, timestamp=self.host.now(), position=P.Point(*self.pos), residual_energy=50000.0, buffer_free=1.0, state=1), P.HELLO)

    def open(self, frame: P.Frame) -> tuple[Any, str]:
        msg, typename, _, replies = self.security.open(frame, self.host.now())
        self.security.take_cpu()
        for m, t in replies:
            self.send(m, t)
        return msg, typename

    def on_frame(self, frame: P.Frame) -> None:
        self.open(frame)

    def every(self, period: float, fn) -> None:
        def tick() -> None:
            fn()
            self.host.call_later(period, tick)

        self.host.call_later(period * float(self.rng.random()), tick)

    def report(self) -> dict[str, Any]:
        return {"kind": self.kind, "name": self.name, **self.stats}


class Impersonator(Attacker):
    kind = "impersonate"

    def start(self) -> None:
        super().start()
        self.seq = 0
        self.every(1.0, self.hello)
        self.every(2.0, self.claim)
        self.every(2.0, lambda: [self.send(m, t) for m, t in self.security.tick(self.host.now())])

    def claim(self) -> None:
        self.seq += 1
        H, W = self.shape
        msg = P.make(P.MAP, source=self.name, seq=self.seq, timestamp=self.host.now(), position=P.Point(*self.pos), goal=P.Point(*self.pos),
                     exploration_complete=True, origin_x=0, origin_y=0, width=W, height=H, data=np.zeros(H * W, dtype=np.int8))
        self.send(msg, P.MAP)


class ManInTheMiddle(Attacker):
    kind = "mitm"

    def on_frame(self, frame: P.Frame) -> None:
        self.open(frame)  # take part in key exchange like anyone (it gains nothing)
        forged = self.forge(frame)
        if forged is not None:
            self.stats["forged"] = self.stats.get("forged", 0) + 1
            self.raw(frame.typename, forged)

    @staticmethod
    def _erase(msg: Any) -> Any:
        # the map data and the goal are erased (the goal becomes the robot's position),
        # and the unprotected sequence number is pushed ahead so that the author's
        # genuine updates that follow look stale to the receivers
        return P.replace(msg, data=np.full(len(msg.data), -1, dtype=np.int8), goal=msg.position, seq=msg.seq + 1000, timestamp=msg.timestamp + 1e-3)

    def forge(self, frame: P.Frame) -> bytes | None:
        if frame.typename == P.MAP:
            m = frame.decode()
            return None if m is None else P.encode(self._erase(m), P.MAP)
        if frame.typename != P.SECURE:
            return None
        f = frame.decode()
        if f is None or f.inner_type != P.MAP:
            return None
        payload = bytes(f.payload)
        if f.flags & F_ENC:
            new = bytes(len(payload))  # cannot read it: erase the ciphertext
        else:
            try:
                inner = P.decode(payload, P.MAP)
            except Exception:
                return None
            new = P.encode(self._erase(inner), P.MAP)
        digest = bytes(f.digest)
        if f.flags & F_DIGEST:  # a bare digest: recompute it
            digest = hashlib.sha256(header_bytes(f.sender, int(f.seq), float(f.timestamp), int(f.key_epoch), f.inner_type, int(f.flags)) + new).digest()
        return P.encode(P.replace(f, payload=_u8(new), digest=_u8(digest)), P.SECURE)


class Eavesdropper(Attacker):
    kind = "eavesdrop"

    def __init__(self, *a: Any, **kw: Any) -> None:
        super().__init__(*a, **kw)
        self.belief = Belief(self.shape)
        self.stats.update({"frames_heard": 0, "frames_read": 0, "frames_unreadable": 0, "positions_read": 0, "bytes_recorded": 0})
        self.positions: set[tuple[str, int]] = set()

    def start(self) -> None:
        pass  # passive: never transmits

    def on_frame(self, frame: P.Frame) -> None:
        st = self.stats
        st["frames_heard"] += 1
        st["bytes_recorded"] += frame.size
        msg, typename = None, frame.typename
        if frame.typename == P.SECURE:
            f = frame.decode()
            if f is not None and not f.flags & F_ENC:
                try:
                    msg, typename = P.decode(bytes(f.payload), f.inner_type), f.inner_type
                except Exception:
                    msg = None
        elif frame.typename != P.KEYX:
            msg = frame.decode()
        if msg is None:
            st["frames_unreadable"] += 1
            return
        st["frames_read"] += 1
        src = getattr(msg, "source", None) or getattr(msg, "origin", None) or getattr(msg, "src_hop", None)
        pos = getattr(msg, "position", None) or getattr(msg, "src_position", None)
        if pos is not None and src:
            st["positions_read"] += 1
            self.positions.add((src, int(self.host.now())))
        if typename == P.MAP:
            data = np.asarray(msg.data, dtype=np.int8)
            if data.size == int(msg.width) * int(msg.height) and data.size:
                self.belief.merge_peer(msg.source, int(msg.origin_y), int(msg.origin_x), data.reshape(int(msg.height), int(msg.width)))


class Replayer(Attacker):
    kind = "replay"

    def __init__(self, *a: Any, delay: float = 15.0, rate: float = 20.0, **kw: Any) -> None:
        super().__init__(*a, **kw)
        self.delay = delay
        self.gap = 1.0 / rate
        self.next_free = 0.0
        self.stats["replayed"] = 0

    def start(self) -> None:
        pass

    def on_frame(self, frame: P.Frame) -> None:
        if frame.typename == P.KEYX:
            return
        now = self.host.now()
        t = max(now + self.delay, self.next_free)
        if t - now > self.delay * 2:
            return  # saturated: skip
        self.next_free = t + self.gap
        self.host.call_later(t - now, lambda: self._replay(frame))

    def _replay(self, frame: P.Frame) -> None:
        self.stats["replayed"] += 1
        self.raw(frame.typename, frame.data)


class Flooder(Attacker):
    kind = "flood"

    def __init__(self, *a: Any, rate: float = 40.0, size: int = 600, **kw: Any) -> None:
        super().__init__(*a, **kw)
        self.period = 1.0 / rate
        self.size = size

    def start(self) -> None:
        self.every(self.period, lambda: self.raw(P.HELLO, bytes(self.rng.integers(0, 256, self.size, dtype=np.uint8))))


class FalseRecruiter(Attacker):
    kind = "false-recruit"

    def __init__(self, *a: Any, **kw: Any) -> None:
        super().__init__(*a, **kw)
        self.heard: dict[str, tuple[float, float]] = {}
        self.req = 0
        self.stats.update({"requests": 0, "offers": 0, "confirms": 0})

    def start(self) -> None:
        super().start()
        self.every(1.0, self.hello)
        self.every(8.0, self.lure)
        self.every(2.0, lambda: [self.send(m, t) for m, t in self.security.tick(self.host.now())])

    def on_frame(self, frame: P.Frame) -> None:
        msg, typename = self.open(frame)
        if msg is None:
            return
        if typename == P.HELLO and msg.source != self.name:
            self.heard[msg.source] = (msg.position.x, msg.position.y)
        elif typename == P.PROTOCOL and msg.destination == self.name and msg.payload_type == P.RECRUIT:
            inner = P.decode(bytes(msg.payload), P.RECRUIT)
            if inner.kind == OFFER and inner.recruit_originator == self.name:
                self.stats["offers"] += 1
                conf = P.replace(inner, kind=CONFIRM, src_hop=self.name, timestamp=self.host.now())
                pkt = P.make(P.PROTOCOL, source=self.name, destination=msg.source, timestamp=self.host.now(), routing_table=[], origin=self.name,
                             final_destination=inner.dest_recruit_originator, seq=0, payload_type=P.RECRUIT, payload=_u8(P.encode(conf, P.RECRUIT)))
                self.stats["confirms"] += 1
                self.send(pkt, P.PROTOCOL)

    def lure(self) -> None:
        H, W = self.shape
        for victim, (x, y) in sorted(self.heard.items()):
            self.req += 1
            # the corner farthest from the victim
            tx = 0.0 if x > W * self.resolution / 2 else (W - 2) * self.resolution
            ty = 0.0 if y > H * self.resolution / 2 else (H - 2) * self.resolution
            self.stats["requests"] += 1
            self.send(P.make(P.RECRUIT, kind=REQUEST, request_id=self.req, ttl=1, recruit_originator=self.name, src_hop=self.name, dst_hop="",
                             dest_recruit_originator=victim, timestamp=self.host.now(), src_position=P.Point(*self.pos), originator_position=P.Point(*self.pos),
                             target=P.Point(tx, ty), residual_energy=50000.0, state=1, distance=0.0), P.RECRUIT)


class Blackhole(Attacker):
    kind = "blackhole"

    def __init__(self, *a: Any, **kw: Any) -> None:
        super().__init__(*a, **kw)
        self.protocol = Protocol(self.name)
        self.stats["dropped"] = 0

    def start(self) -> None:
        super().start()
        self.every(1.0, self.hello)
        self.every(3.0, self.lsu)
        self.every(2.0, lambda: [self.send(m, t) for m, t in self.security.tick(self.host.now())])

    def lsu(self) -> None:
        self.protocol.expire(self.host.now())
        self.send(self.protocol.lsu(self.host.now(), self.pos, 70000.0, 1), P.LSU)

    def on_frame(self, frame: P.Frame) -> None:
        msg, typename = self.open(frame)
        if msg is None:
            return
        if typename == P.HELLO:
            self.protocol.on_hello(msg, self.host.now())
        elif typename in (P.LSU, P.RECRUIT) or (typename == P.PROTOCOL and msg.destination == self.name):
            self.stats["dropped"] += 1


def make(kind: str, *args: Any, **kw: Any) -> Attacker:
    cls = {
        "impersonate": Impersonator, "impersonate-insider": Impersonator, "mitm": ManInTheMiddle, "eavesdrop": Eavesdropper,
        "replay": Replayer, "flood": Flooder, "false-recruit": FalseRecruiter, "blackhole": Blackhole,
    }[kind]
    a = cls(*args, **kw)
    a.kind = kind
    return a
