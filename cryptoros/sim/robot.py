"""A robot built from the paper's modules, independent of any transport.

The robot talks to the outside world only through a :class:`Host` (given at
construction), so the discrete-event engine (:mod:`cryptoros.sim.engine`) is one
driver and a live ROS node over sockets is another::

    class Host(Protocol):
        def now(self) -> float                          # the driver's clock, seconds
        def call_later(self, delay: float, fn) -> None  # run fn() after delay seconds
        def broadcast(self, typename: str, data: bytes) -> None
                                                        # one radio frame: ROS 1 bytes
        def scan(self) -> tuple[ndarray, ndarray]       # lidar: flat cell indices seen
                                                        #   and whether each is occupied
        def move(self, cell: tuple[int, int]) -> bool   # drive one cell; False if blocked

and the driver calls :meth:`Robot.start` once and :meth:`Robot.on_frame` for every
frame the radio receives (a :class:`~cryptoros.sim.packets.Frame`: sender, ROS type
name, bytes). Randomness comes from the ``rng`` passed in; there is no wall clock and
no global random state anywhere in the robot.

Modules (each usable and testable alone): :class:`~cryptoros.sim.explorer.Explorer`
and :class:`~cryptoros.sim.explorer.Belief`, :class:`~cryptoros.sim.battery.Battery`,
:class:`~cryptoros.sim.buffer.FrameBuffer`, :class:`~cryptoros.sim.home.HomeHandler`,
:class:`~cryptoros.sim.protocol.Protocol`, :class:`~cryptoros.sim.recruit.Recruit`,
:class:`~cryptoros.sim.comm.Comm` and the security manager
(:mod:`cryptoros.sim.security`). This class only wires them together.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Protocol as TypingProtocol

import numpy as np

from cryptoros.sim import packets as P
from cryptoros.sim.battery import Battery, BatterySpec
from cryptoros.sim.buffer import FrameBuffer
from cryptoros.sim.comm import Comm
from cryptoros.sim.explorer import Belief, Explorer
from cryptoros.sim.home import HomeHandler
from cryptoros.sim.protocol import Protocol
from cryptoros.sim.recruit import CONFIRM, OFFER, REQUEST, Recruit
from cryptoros.sim.world import OCC

EXPLORE, HOME, CHARGING, IDLE, RECRUITED, DONE, DEAD = 1, 2, 3, 4, 5, 6, 7
STATE_NAMES = {EXPLORE: "explore", HOME: "home", CHARGING: "charging", IDLE: "idle", RECRUITED: "recruited", DONE: "done", DEAD: "dead"}


class Host(TypingProtocol):
    def now(self) -> float: ...
    def call_later(self, delay: float, fn: Callable[[], None]) -> None: ...
    def broadcast(self, typename: str, data: bytes) -> None: ...
    def scan(self) -> tuple[np.ndarray, np.ndarray]: ...
    def move(self, cell: tuple[int, int]) -> bool: ...


@dataclass
class RobotConfig:
    resolution: float = 0.2
    speed: float = 0.22  # TurtleBot3 Burger max linear speed, m/s
    lidar_m: float = 3.5  # LDS-01 range
    hello_period: float = 1.0
    lsu_period: float = 10.0
    share_period: float = 5.0
    recruit_period: float = 60.0
    recruit: bool = True
    plausibility: bool = False
    battery: BatterySpec | None = None
    frames_per_m: float = 2.0
    recruit_timeout: float = 1.5
    max_ttl: int = 6
    offer_backoff: float = 0.3  # an OFFER waits uniform [0, this) s: idle robots hearing one request do not all answer at once
    min_buffer_free: float = 0.1  # a robot with less free frame buffer is not recruited (it must unload first)
    resume_after: float = 20.0  # a recharged robot idles at its base (recruitable) this long, then resumes (paper 5.2, incremental recruit)


class Robot:
    def __init__(self, name: str, host: Host, rng: np.random.Generator, *, start: tuple[int, int], shape: tuple[int, int],
                 bases: list[tuple[int, int]], config: RobotConfig, security: Any, idle: bool = False) -> None:
        self.name = name
        self.host = host
        self.rng = rng
        self.cfg = config
        self.cell = start
        self.belief = Belief(shape)
        self.explorer = Explorer(sep_cells=config.lidar_m / config.resolution)
        self.battery = Battery(config.battery or BatterySpec())
        self.buffer = FrameBuffer(frames_per_m=config.frames_per_m)
        self.home = HomeHandler(bases, config.resolution, config.speed)
        self.protocol = Protocol(name, hello_period=config.hello_period, lsu_period=config.lsu_period)
        self.recruit = Recruit(name, timeout=config.recruit_timeout, max_ttl=config.max_ttl)
        self.comm = Comm(name, config.resolution, share_period=config.share_period, lidar_cells=config.lidar_m / config.resolution,
                         max_speed=config.speed, plausibility=config.plausibility)
        self.security = security
        self.state = IDLE if idle else EXPLORE
        self.path: list[tuple[int, int]] = []
        self.goal: tuple[int, int] = start
        self.target: tuple[int, int] | None = None
        self._last_t = 0.0
        self._stepping = False
        self._cpu_backlog = 0.0
        self._belief_checked = -1
        self._pending_lsu = False
        self._last_lsu = -1e9
        self._resume_pending = False
        self.out_of_reach = False  # recharged, but the nearest frontier is beyond a full battery
        self.travelled_m = 0.0
        self.finished_at: float | None = None
        self.counters = {"rx": 0, "tx": 0, "rejected": 0, "forwarded": 0, "recruited": 0, "recruit_requests": 0,
                         "returns_home": 0, "charges": 0, "resumed": 0, "false_done": 0,
                         "offers_sent": 0, "offers_received": 0}
        self.rejected: dict[str, int] = {}

    # -- helpers -----------------------------------------------------------------------

    @property
    def pos(self) -> tuple[float, float]:
        return (self.cell[1] * self.cfg.resolution, self.cell[0] * self.cfg.resolution)

    def to_cell(self, x: float, y: float) -> tuple[int, int]:
        H, W = self.belief.shape
        r = min(H - 1, max(0, int(round(y / self.cfg.resolution))))
        c = min(W - 1, max(0, int(round(x / self.cfg.resolution))))
        return r, c

    def alive(self) -> bool:
        return self.state != DEAD

    @property
    def active(self) -> bool:
        """Doing or about to do something for the mission: moving, charging, waiting for
        recruit offers, or idle at a base with a resumption scheduled."""
        if self.state == DEAD:
            return False
        return self.state in (EXPLORE, HOME, RECRUITED, CHARGING) or bool(self.recruit.pending) or self._resume_pending

    def _sync(self) -> None:
        now = self.host.now()
        dt = now - self._last_t
        if dt > 0:
            if self.state == CHARGING or (self.state == IDLE and self.home.at_base(self.cell)):
                self.battery.charge(dt)  # a robot idle at a base stays on the charger
            else:
                self.battery.elapse(dt)
            self._last_t = now
        if self.battery.empty and self.state != DEAD:
            self.state = DEAD
            self.finished_at = now

    def _charge_cpu(self) -> None:
        cpu = self.security.take_cpu()
        if cpu:
            self.battery.crypto(cpu)
            self._cpu_backlog += cpu

    def send(self, msg: Any, typename: str) -> None:
        if self.state == DEAD:
            return
        out_type, data = self.security.seal(msg, typename, self.host.now())
        self._charge_cpu()
        self.battery.tx(len(data))
        self.counters["tx"] += 1
        self.host.broadcast(out_type, data)

    def _send_later(self, msg: Any, typename: str, max_delay: float = 0.05) -> None:
        """Forwarding jitter: neighbours that heard the same flood do not all answer at once."""
        self.host.call_later(float(self.rng.random()) * max_delay, lambda: (self._sync(), self.send(msg, typename)))

    def _jitter(self, period: float) -> float:
        return period * (0.9 + 0.2 * float(self.rng.random()))

    # -- lifecycle -----------------------------------------------------------------------

    def start(self) -> None:
        self._last_t = self.host.now()
        self._observe()
        self.host.call_later(float(self.rng.random()) * self.cfg.hello_period, self._hello_timer)
        self.host.call_later(self.cfg.lsu_period * float(self.rng.random()), self._lsu_timer)
        self.host.call_later(self.cfg.share_period * (0.5 + float(self.rng.random())), self._share_timer)
        if self.cfg.recruit:
            self.host.call_later(self.cfg.recruit_period * (0.5 + float(self.rng.random())), self._recruit_timer)
        for msg, typename in self.security.start(self.host.now()):
            self.send(msg, typename)
        if self.state == EXPLORE:
            self._schedule_step(0.0)

    def _schedule_step(self, delay: float) -> None:
        if not self._stepping:
            self._stepping = True
            self.host.call_later(delay, self._step)

    # -- timers -------------------------------------------------------------------------

    def _hello_timer(self) -> None:
        self._sync()
        if self.state == DEAD:
            return
        now = self.host.now()
        changed = self.protocol.expire(now)
        self.security.expire(set(self.protocol.neighbours), now)
        self.send(self.protocol.hello(now, self.pos, self.battery.energy, self.state, self.buffer.free_share), P.HELLO)
        for msg, typename in self.security.tick(now):
            self.send(msg, typename)
        if changed or self.protocol.neighbour_set_changed():
            self._request_lsu()
        if self.state == DONE and self.belief.version != self._belief_checked:
            self._belief_checked = self.belief.version
            if self.explorer.plan_frontier(self.belief.known, self.cell) is not None:
                self.state = EXPLORE  # the map changed under us: explore again
                self.finished_at = None
                self._schedule_step(0.0)
        self.host.call_later(self._jitter(self.cfg.hello_period), self._hello_timer)

    def _request_lsu(self) -> None:
        if not self._pending_lsu and self.host.now() - self._last_lsu >= 2.0:
            self._pending_lsu = True
            self.host.call_later(0.2 + 0.3 * float(self.rng.random()), self._send_lsu)

    def _send_lsu(self) -> None:
        self._pending_lsu = False
        self._last_lsu = self.host.now()
        self._sync()
        if self.state != DEAD:
            self.send(self.protocol.lsu(self.host.now(), self.pos, self.battery.energy, self.state, self.buffer.free_share), P.LSU)

    def _forward_lsu(self, fwd: Any) -> None:
        self._sync()
        if self.protocol.still_worth_forwarding(fwd):
            self.counters["forwarded"] += 1
            self.send(fwd, P.LSU)
        else:
            self.counters["suppressed"] = self.counters.get("suppressed", 0) + 1

    def _lsu_timer(self) -> None:
        self._send_lsu()
        if self.state != DEAD:
            self.host.call_later(self._jitter(self.cfg.lsu_period), self._lsu_timer)

    def _share_timer(self) -> None:
        self._sync()
        if self.state == DEAD:
            return
        gx, gy = self.goal[1] * self.cfg.resolution, self.goal[0] * self.cfg.resolution
        self.send(self.comm.share(self.host.now(), self.belief, self.pos, (gx, gy), self.state == DONE), P.MAP)
        self.host.call_later(self._jitter(self.cfg.share_period), self._share_timer)

    def _recruit_timer(self) -> None:
        self._sync()
        if self.state == DEAD:
            return
        if self.state == EXPLORE and not self.recruit.pending:
            idle = [n for n, info in sorted(self.protocol.known_robots().items()) if info.state == IDLE]
            if idle:
                self._start_recruit(self.goal, dest="")
        self.host.call_later(self._jitter(self.cfg.recruit_period), self._recruit_timer)

    # -- motion ---------------------------------------------------------------------------

    def _observe(self) -> None:
        flat, occ = self.host.scan()
        self.belief.observe(flat, occ)

    def _step(self) -> None:
        self._stepping = False
        self._sync()
        if self.state not in (EXPLORE, HOME, RECRUITED):
            return
        now = self.host.now()
        if self.state in (EXPLORE, RECRUITED) and (self.home.must_return(self.battery, self.cell, self.cfg.resolution) or self.buffer.full):
            # low battery, or no room for more frames: unload and charge at a base (paper 4.2)
            self._go_home(now)
        if not self.path or (self.state == EXPLORE and not self.explorer.is_frontier(self.belief.known, self.goal)):
            if not self._replan(now):
                return
        nxt = self.path[0]
        if self.belief.known[nxt] == OCC or not self.host.move(nxt):
            self.belief.mark(nxt, OCC)
            self.path = []
            self._schedule_step(0.05)
            return
        self.path.pop(0)
        step_m = math.hypot(nxt[0] - self.cell[0], nxt[1] - self.cell[1]) * self.cfg.resolution
        self.cell = nxt
        self.battery.move(step_m)
        self.buffer.travelled(step_m)
        self.travelled_m += step_m
        self._observe()
        if not self.path:
            self._arrived(now)
            if self.state not in (EXPLORE, HOME, RECRUITED):
                return
        delay = step_m / self.cfg.speed + self._cpu_backlog
        self._cpu_backlog = 0.0
        self._schedule_step(delay)

    def _replan(self, now: float) -> bool:
        if self.state == HOME:
            base, _ = self.home.nearest(self.cell)
            self.path = self.explorer.plan_to(self.belief.known, self.cell, base)
            if not self.path:
                self._arrived(now)
                return False
            return True
        if self.state == RECRUITED and self.target is not None:
            self.path = self.explorer.plan_to(self.belief.known, self.cell, self.target)
            if self.path:
                self.goal = self.path[-1]
                return True
            self.state = EXPLORE
        others = [(y / self.cfg.resolution, x / self.cfg.resolution) for x, y in self.comm.others(now)]
        path = self.explorer.plan_frontier(self.belief.known, self.cell, others)
        if path is None:
            self.state = DONE
            self.finished_at = now
            self._belief_checked = self.belief.version
            return False
        if not path:  # standing on a frontier that scanning cannot resolve
            self.explorer.blacklist.add(self.cell[0] * self.belief.shape[1] + self.cell[1])
            self._schedule_step(0.05)
            return False
        self.path = path
        self.goal = path[-1]
        return True

    def _arrived(self, now: float) -> None:
        if self.state == HOME:
            if self.home.at_base(self.cell):
                self.state = CHARGING
                self.counters["charges"] += 1
                self.buffer.unload()
                self.host.call_later(self.battery.time_to_full(), self._charged)
            else:
                self.path = []
        elif self.state == RECRUITED:
            self.state = EXPLORE
            self.target = None
        elif self.state == EXPLORE and self.explorer.is_frontier(self.belief.known, self.goal):
            self.explorer.blacklist.add(self.goal[0] * self.belief.shape[1] + self.goal[1])

    def _charged(self) -> None:
        self._sync()
        if self.state == CHARGING:
            # inactive at the base, where a recruit request may wake it (paper 5.2, general
            # recruit); if none does within resume_after, it resumes by itself (paper 5.2,
            # incremental recruit: a robot is resumed every pre-fixed amount of time)
            self.state = IDLE
            self._resume_pending = True
            self.host.call_later(self.cfg.resume_after, self._resume)

    def _resume(self) -> None:
        self._sync()
        self._resume_pending = False
        self.out_of_reach = False
        if self.state != IDLE:
            return  # recruited meanwhile, or dead
        path = self.explorer.plan_frontier(self.belief.known, self.cell)
        if path is None:
            self.state = DONE  # nothing left on its map; the HELLO timer re-checks on news
            self.finished_at = self.host.now()
            self._belief_checked = self.belief.version
            return
        if path and not self.home.can_reach(self.battery, self.cell, path[-1]):
            self.out_of_reach = True  # a full battery cannot take it there and back: stay recruitable
            return
        self.counters["resumed"] += 1
        self.state = EXPLORE
        self.finished_at = None
        self.path = []
        self._schedule_step(0.0)

    def _go_home(self, now: float) -> None:
        self.counters["returns_home"] += 1
        left_at = self.goal
        self.state = HOME
        self.path = []
        if self.cfg.recruit:
            dest = self._pick_candidate(left_at)
            self._start_recruit(left_at, dest=dest)

    # -- recruiting ---------------------------------------------------------------------

    def _pick_candidate(self, target: tuple[int, int]) -> str:
        """Specific recruit: idle at a base first, then nearest to the target; only robots
        with the energy to get there and back and room in their frame buffer to record it
        (the link-state metrics of paper 5: residual energy, buffer space, distance)."""
        tx, ty = target[1] * self.cfg.resolution, target[0] * self.cfg.resolution
        best, key = "", None
        for n, info in sorted(self.protocol.known_robots().items()):
            if info.state not in (IDLE, EXPLORE, DONE):
                continue
            d = math.hypot(info.position[0] - tx, info.position[1] - ty)
            need = self.battery.cost_to_travel(d * 2 * self.home.detour, self.cfg.speed)
            if info.energy <= need or info.buffer_free < self.cfg.min_buffer_free:
                continue
            k = (info.state != IDLE, d)
            if key is None or k < key:
                best, key = n, k
        return best

    def _start_recruit(self, target: tuple[int, int], dest: str) -> None:
        now = self.host.now()
        t = (target[1] * self.cfg.resolution, target[0] * self.cfg.resolution)
        msg, p = self.recruit.start(now, t, self.pos, self.battery.energy, dest=dest)
        self.counters["recruit_requests"] += 1
        self.send(msg, P.RECRUIT)
        self.host.call_later(p.deadline - now, lambda rid=p.request_id: self._recruit_timeout(rid))

    def _recruit_timeout(self, rid: int) -> None:
        self._sync()
        if self.state == DEAD:
            return
        now = self.host.now()
        what, val = self.recruit.on_timeout(rid, now, self.pos, self.battery.energy)
        if what == "resend":
            self.send(val, P.RECRUIT)
            p = self.recruit.pending[rid]
            self.host.call_later(p.deadline - now, lambda: self._recruit_timeout(rid))
        elif what == "confirm":
            self._route(val.dest_recruit_originator, self.recruit.confirm(val, now, self.pos), P.RECRUIT, hint=val.src_hop)

    def _eligible(self, req: Any) -> bool:
        if self.state not in (IDLE, EXPLORE, DONE) or self.buffer.free_share < self.cfg.min_buffer_free:
            return False
        if req.dest_recruit_originator == self.name:
            pass
        elif self.state != IDLE:  # general requests only wake robots idle at a base
            return False
        return self.home.can_reach(self.battery, self.cell, self.to_cell(req.target.x, req.target.y))

    def _on_recruit(self, msg: Any, now: float) -> None:
        if msg.kind == REQUEST:
            consider, fwd = self.recruit.on_request(msg, now, self.pos)
            if fwd is not None:
                self.counters["forwarded"] += 1
                self._send_later(fwd, P.RECRUIT)
            if consider and self._eligible(msg):
                # random back-off, as a MAC would: two idle robots at one base hear the
                # same request at the same instant, and answering at once collides
                self.recruit.promise(msg)
                delay = float(self.rng.random()) * self.cfg.offer_backoff
                self.host.call_later(delay, lambda: self._send_offer(msg))
        elif msg.kind == OFFER:
            self.recruit.on_offer(msg, now)
            self.counters["offers_received"] += 1
        elif msg.kind == CONFIRM and msg.dest_recruit_originator == self.name:
            if self.state in (IDLE, EXPLORE, DONE):
                self.counters["recruited"] += 1
                self.out_of_reach = False
                self.state = RECRUITED
                self.finished_at = None
                self.target = self.to_cell(msg.target.x, msg.target.y)
                self.path = []
                self._schedule_step(0.0)

    def _send_offer(self, req: Any) -> None:
        self._sync()
        if not self._eligible(req):  # state or battery changed during the back-off
            return
        now = self.host.now()
        tc = self.to_cell(req.target.x, req.target.y)
        d = math.hypot(tc[0] - self.cell[0], tc[1] - self.cell[1]) * self.cfg.resolution
        offer = self.recruit.offer(req, now, self.pos, self.battery.energy, self.state, d)
        self.counters["offers_sent"] += 1
        self._route(req.recruit_originator, offer, P.RECRUIT, hint=req.src_hop)

    # -- routed unicast (ProtocolPacket) -----------------------------------------------

    def _route(self, dest: str, inner: Any, inner_type: str, hint: str = "", origin: str | None = None, seq: int = 0) -> None:
        if dest == self.name:
            self._deliver_inner(inner, inner_type, self.host.now())
            return
        nh = self.protocol.next_hop(dest) or hint
        if not nh:
            return
        pkt = P.make(
            P.PROTOCOL, source=self.name, destination=nh, timestamp=self.host.now(), routing_table=self.protocol.routing_table(),
            origin=origin or self.name, final_destination=dest, seq=seq, payload_type=inner_type, payload=np.frombuffer(P.encode(inner, inner_type), dtype=np.uint8),
        )
        self.send(pkt, P.PROTOCOL)

    def _on_protocol(self, msg: Any, now: float) -> None:
        if msg.destination != self.name:
            return
        try:
            inner = P.decode(bytes(msg.payload), msg.payload_type)
        except Exception:
            self._reject("malformed")
            return
        if msg.final_destination == self.name:
            self._deliver_inner(inner, msg.payload_type, now)
            return
        hint = ""
        if msg.payload_type == P.RECRUIT:
            key = (inner.recruit_originator, int(inner.request_id))
            if inner.kind == OFFER:
                self.recruit.forward[key] = msg.source
                hint = self.recruit.reverse.get(key, "")
            else:
                hint = self.recruit.forward.get(key, "")
        self.counters["forwarded"] += 1
        self._route(msg.final_destination, inner, msg.payload_type, hint=hint, origin=msg.origin, seq=msg.seq)

    def _deliver_inner(self, inner: Any, typename: str, now: float) -> None:
        if typename == P.RECRUIT:
            self._on_recruit(inner, now)

    # -- receiving ------------------------------------------------------------------------

    def _reject(self, reason: str) -> None:
        self.counters["rejected"] += 1
        self.rejected[reason] = self.rejected.get(reason, 0) + 1

    def on_frame(self, frame: P.Frame) -> None:
        self._sync()
        if self.state == DEAD:
            return
        now = self.host.now()
        self.battery.rx(frame.size)
        self.counters["rx"] += 1
        msg, typename, reason, replies = self.security.open(frame, now)
        self._charge_cpu()
        for rmsg, rtype in replies:
            self._send_later(rmsg, rtype)
        if msg is None:
            if reason:
                self._reject(reason)
            return
        if typename == P.HELLO:
            if msg.source == self.name:
                return
            if self.protocol.on_hello(msg, now):
                self._request_lsu()
                for m, t in self.security.on_neighbour(msg.source, now):
                    self.send(m, t)
            self.comm.note_position(msg.source, now, (msg.position.x, msg.position.y), self.belief.shape)
        elif typename == P.LSU:
            fwd = self.protocol.on_lsu(msg, now)
            if fwd is not None:
                self.host.call_later(float(self.rng.random()) * 0.1, lambda: self._forward_lsu(fwd))
        elif typename == P.MAP:
            ok, why, _ = self.comm.on_map(msg, now, self.belief)
            if not ok and why not in ("own", "stale"):
                self._reject(why)
        elif typename == P.RECRUIT:
            self._on_recruit(msg, now)
        elif typename == P.PROTOCOL:
            self._on_protocol(msg, now)
