"""One demo robot: the simulator's robot logic as live ROS 1 nodes on real sockets.

``python -m cryptoros.demo.robot CONFIG.json`` runs two nodes in one process, as a
robot would run its control code and its drivers:

* ``/rN`` (explorer): the transport-independent :class:`cryptoros.sim.robot.Robot` on a
  :class:`LiveHost`. Its radio is ROS topics: every packet type of the simulator is a
  team topic (``/team/hello``, ``/team/lsu``, ``/team/map``, ``/team/recruit``,
  ``/team/protocol``) that every robot publishes and subscribes to. It publishes its
  drive command on ``/rN/cmd_vel`` and subscribes to its driver's ``/rN/pose`` and
  ``/rN/scan``.
* ``/rN_base`` (drivers): publishes ``/rN/pose`` (PoseStamped, 20 Hz) and ``/rN/scan``
  (LaserScan, 5 Hz) computed from the ground-truth world, and executes ``/rN/cmd_vel``.

The clock is scaled (``scale`` simulated seconds per wall second, shared by all robots
through a common start time), so a mission of minutes takes tens of seconds.

Victim-side evidence: the robot keeps a short hash of every message it published (so
an eavesdropper's haul is counted in the robots' own messages, and its own messages
are not counted as received), and what foreign messages did to it, per sender (a
spoofed pose, a noisy scan marked into its map, a stop command that halted it, an
erased team map relayed by another node, a ``shutdown`` call it executed). It writes
its status as JSON (atomically) twice a second and a final one with the hashes on
SIGTERM; :mod:`cryptoros.demo.run` judges from those.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import logging
import math
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from cryptoros.attack.lib import digest
from cryptoros.demo.compromise import FALSE_MAP_HZ, FLOOD_HZ, Compromise
from cryptoros.ros1 import msgs
from cryptoros.ros1.node import Node
from cryptoros.sim import packets as P
from cryptoros.sim.robot import DEAD, DONE, EXPLORE, HOME, RECRUITED, STATE_NAMES, Robot, RobotConfig
from cryptoros.sim.security import SecurityConfig, make_managers
from cryptoros.sim.world import OCC, Lidar, generate

log = logging.getLogger("cryptoros.demo.robot")

TEAM_TOPICS = {P.HELLO: "/team/hello", P.LSU: "/team/lsu", P.MAP: "/team/map", P.RECRUIT: "/team/recruit",
               P.PROTOCOL: "/team/protocol"}
SHORT = {P.HELLO: "hello", P.LSU: "lsu", P.MAP: "map", P.RECRUIT: "recruit", P.PROTOCOL: "protocol"}
POSE, SCAN, TWIST = "geometry_msgs/PoseStamped", "sensor_msgs/LaserScan", "geometry_msgs/Twist"
SCAN_BEAMS = 72
HALT_S = 0.5  # wall seconds a stop command holds the base


def start_cells(world: Any, n: int) -> list[tuple[int, int]]:
    from cryptoros.sim.scenario import _start_cells

    return _start_cells(world, n, 0)


def make_world(cfg: dict[str, Any]) -> Any:
    return generate(int(cfg["seed"]), int(cfg["width"]), int(cfg["height"]), resolution=0.2, n_bases=1)


class LiveHost:
    """:class:`cryptoros.sim.robot.Host` on an asyncio loop and ROS topics."""

    def __init__(self, loop: asyncio.AbstractEventLoop, t0: float, scale: float, world: Any, lidar: Lidar,
                 observed: np.ndarray, broadcast: Callable[[str, bytes], None]) -> None:
        self.loop = loop
        self.t0 = t0
        self.scale = scale
        self.world = world
        self.lidar = lidar
        self.observed = observed
        self._broadcast = broadcast
        self.robot: Robot | None = None
        self.halted_until = 0.0
        self.halted_s = 0.0
        self.errors = 0

    def now(self) -> float:
        return max(0.0, (time.time() - self.t0) * self.scale)

    def call_later(self, delay: float, fn: Callable[[], None]) -> None:
        self.loop.call_later(max(0.0, delay) / self.scale, self._run, fn)

    def _run(self, fn: Callable[[], None]) -> None:
        if getattr(fn, "__func__", None) is Robot._step or getattr(fn, "is_motion_step", False):
            wait = self.halted_until - self.loop.time()
            if wait > 0:  # the base obeys the stop command it received: no motion now
                self.halted_s += wait
                self.loop.call_later(wait, self._run, fn)
                return
        try:
            fn()
        except Exception:
            self.errors += 1
            log.exception("robot callback failed")

    def broadcast(self, typename: str, data: bytes) -> None:
        self._broadcast(typename, data)

    def scan(self) -> tuple[np.ndarray, np.ndarray]:
        r, c = self.robot.cell  # type: ignore[union-attr]
        flat, occ = self.lidar.scan(self.world.occupied, r, c)
        self.observed.flat[flat] = True
        return flat, occ

    def move(self, cell: tuple[int, int]) -> bool:
        return not bool(self.world.occupied[cell])


def laser_ranges(occupied: np.ndarray, cell: tuple[int, int], resolution: float, max_m: float = 3.5) -> np.ndarray:
    """Ranges of :data:`SCAN_BEAMS` beams from ``cell`` to the first occupied cell."""
    angles = np.linspace(0, 2 * math.pi, SCAN_BEAMS, endpoint=False)
    steps = np.arange(1, int(max_m / resolution) + 1)
    rr = np.rint(cell[0] + np.outer(np.sin(angles), steps)).astype(int)
    cc = np.rint(cell[1] + np.outer(np.cos(angles), steps)).astype(int)
    H, W = occupied.shape
    inside = (rr >= 0) & (rr < H) & (cc >= 0) & (cc < W)
    hit = np.ones_like(inside)
    hit[inside] = occupied[rr[inside], cc[inside]]
    first = np.where(hit.any(axis=1), hit.argmax(axis=1) + 1, len(steps) + 1)
    return np.minimum(first * resolution, max_m + resolution).astype(np.float32)


class DemoRobot:
    def __init__(self, cfg: dict[str, Any]) -> None:
        self.cfg = cfg
        self.name = cfg["name"]
        self.team = list(cfg["team"])
        self.status_path = Path(cfg["status"])
        self.go_path = Path(cfg["go"])
        self.scale = float(cfg["scale"])
        self.world = make_world(cfg)
        self.index = self.team.index(self.name)
        self.start_cell = start_cells(self.world, len(self.team))[self.index]
        self.observed = np.zeros(self.world.shape, dtype=bool)
        self.published: set[str] = set()
        self.stats: dict[str, Any] = {
            "tx_messages": 0, "tx_bytes": 0, "rx_messages": 0, "rx_bytes": 0,
            "pose_received": 0, "pose_foreign": 0, "pose_max_error_m": 0.0,
            "scan_received": 0, "scan_foreign": 0, "scan_cells_corrupted": 0,
            "cmd_received": 0, "cmd_foreign": 0, "cmd_foreign_stop": 0,
            "map_received": 0, "map_from_non_team": 0, "map_erased": 0,
            "shutdown_calls": 0, "shutdown_reasons": [], "shut_down_at": None,
            "pose_replayed": 0, "map_complete_claims": 0,
            #: key -> publisher -> {n, first, last (Unix time), effect}: the foreign (or replayed)
            #: messages of that key
            "by_publisher": {},
        }
        self._poses_seen: set[str] = set()
        self.robot: Robot | None = None
        self.host: LiveHost | None = None
        self.stop = asyncio.Event()
        self.ready = False
        self.t0: float | None = None
        self.done_at_s: float | None = None
        self.pubs: dict[str, Any] = {}
        #: a compromised robot (monitor datasets): set once the start time is known
        self.compromise: Compromise | None = None

    # -- evidence -----------------------------------------------------------------------------

    def _publish_raw(self, pub: Any, data: bytes) -> None:
        self.published.add(digest(data))
        self.stats["tx_messages"] += 1
        self.stats["tx_bytes"] += len(data)
        pub.publish_raw(data)

    def _received(self, key: str, data: bytes) -> str | None:
        """Record a received message; None when it is our own (a self-connection)."""
        h = digest(data)
        if h in self.published:
            return None
        self.stats["rx_messages"] += 1
        self.stats["rx_bytes"] += len(data)
        return h

    # -- team radio ---------------------------------------------------------------------------

    def _broadcast(self, typename: str, data: bytes) -> None:
        pub = self.pubs.get(typename)
        if pub is not None:
            self._publish_raw(pub, data)

    def _on_team(self, typename: str, data: bytes, header: dict[str, str] | None = None) -> None:
        key = SHORT[typename]
        if self._received(key, data) is None or self.robot is None:
            return
        frame = P.Frame("?", typename, bytes(data))
        if typename == P.MAP:
            m = frame.decode()
            if m is not None:
                self.stats["map_received"] += 1
                publisher = (header or {}).get("callerid", "")
                if m.source in self.team and publisher and publisher != f"/{m.source}":
                    # a team member's update sent by another node: relayed, altered or not
                    # (seed 000's man in the middle); per sender, so a refused one counts nothing
                    erased = len(m.data) > 0 and not np.any(np.asarray(m.data) != -1)
                    self._foreign("map_relayed", publisher, 1.0 if erased else 0.0)
                if m.exploration_complete and m.source != self.name:
                    self.stats["map_complete_claims"] += 1
                    by_source = self.stats.setdefault("map_complete_claims_from", {})
                    if m.source in by_source or len(by_source) < 64:  # bounded: claimed sources are any strings
                        by_source[m.source] = by_source.get(m.source, 0) + 1
                if m.source not in self.team:
                    self.stats["map_from_non_team"] += 1
                elif len(m.data) and not np.any(np.asarray(m.data) != -1):
                    self.stats["map_erased"] += 1
        self.robot.on_frame(frame)

    # -- drivers (base) and their consumers --------------------------------------------------

    def _foreign(self, key: str, publisher: str, effect: float = 0.0, *, worst: bool = False) -> None:
        """A foreign message of ``key`` from ``publisher`` (its callerid; "" where the
        transport does not say): when such messages came, per publisher, and their
        ``effect`` (summed, or the ``worst`` one), so that attacks on one topic are told apart."""
        now = round(time.time(), 3)
        table = self.stats["by_publisher"].setdefault(key, {})
        entry = table.get(publisher)
        if entry is None:
            if len(table) >= 64:  # bounded: the 64 first publishers are enough evidence
                return
            entry = table[publisher] = {"n": 0, "first": now, "last": now, "effect": 0.0}
        entry["n"] += 1
        entry["last"] = now
        entry["effect"] = round(max(entry["effect"], effect) if worst else entry["effect"] + effect, 3)

    def _on_pose(self, data: bytes, header: dict[str, str] | None = None) -> None:
        publisher = (header or {}).get("callerid", "")
        seen = digest(data)
        if seen in self._poses_seen:  # a second copy of a pose already received: a replay
            self.stats["pose_replayed"] += 1
            self._foreign("pose_replayed", publisher, self._pose_error(data), worst=True)
            return
        if len(self._poses_seen) > 200_000:
            self._poses_seen.clear()
        self._poses_seen.add(seen)
        h = self._received("pose", data)
        if h is None:
            return
        self.stats["pose_received"] += 1
        if h in self.base_published:
            return
        self.stats["pose_foreign"] += 1
        self._foreign("pose", publisher, self._pose_error(data), worst=True)

    def _pose_error(self, data: bytes) -> float:
        """How far a foreign pose puts the robot from where it is."""
        err = 0.0
        with contextlib.suppress(Exception):
            px, py = self.read_pose(data)
            x, y = self.robot.pos if self.robot else (0.0, 0.0)
            err = math.hypot(px - x, py - y)
            self.stats["pose_max_error_m"] = round(max(self.stats["pose_max_error_m"], err), 3)
        return err

    def _on_scan(self, data: bytes, header: dict[str, str] | None = None) -> None:
        h = self._received("scan", data)
        if h is None:
            return
        self.stats["scan_received"] += 1
        if h in self.base_published or self.robot is None:
            return
        self.stats["scan_foreign"] += 1
        cells = 0
        try:  # the robot believes its scan: phantom obstacles where the noise says so
            angle_min, angle_increment, ranges = self.read_scan(data)
            ranges = np.asarray(ranges, dtype=float)[:SCAN_BEAMS]
            angles = float(angle_min) + float(angle_increment or (2 * math.pi / max(1, len(ranges)))) * np.arange(len(ranges))
            r, c = self.robot.cell
            res = self.robot.cfg.resolution
            rows = np.rint(r + np.sin(angles) * ranges / res).astype(int)
            cols = np.rint(c + np.cos(angles) * ranges / res).astype(int)
            H, W = self.world.shape
            ok = (rows >= 0) & (rows < H) & (cols >= 0) & (cols < W) & ((rows != r) | (cols != c)) & np.isfinite(ranges)
            flat = rows[ok] * W + cols[ok]
            if flat.size:
                self.robot.belief.observe(flat, np.ones(flat.size, dtype=bool))
                cells = int(flat.size)
                self.stats["scan_cells_corrupted"] += cells
        except Exception:
            log.debug("unreadable scan", exc_info=True)
        self._foreign("scan", (header or {}).get("callerid", ""), cells)

    def _on_cmd(self, data: bytes, header: dict[str, str] | None = None) -> None:
        h = self._received("cmd_vel", data)
        if h is None:
            return
        self.stats["cmd_received"] += 1
        if h in self.explorer_published:
            return
        self.stats["cmd_foreign"] += 1
        stop = 0
        with contextlib.suppress(Exception):
            if abs(self.read_twist_speed(data)) < 1e-6 and self.host is not None:
                self.stats["cmd_foreign_stop"] += 1
                self.host.halted_until = max(self.host.halted_until, self.host.loop.time() + HALT_S)
                stop = 1
        self._foreign("cmd_vel", (header or {}).get("callerid", ""), stop)

    # -- message codec (ROS 1 here; the ROS 2 robot overrides these six) --------------------------

    def pose_bytes(self, seq: int, stamp: float, x: float, y: float) -> bytes:
        store = P.store()
        pose = msgs.msg_class(POSE, store)(
            header=msgs.msg_class("std_msgs/Header", store)(seq=seq, stamp=_time(store, stamp), frame_id="map"),
            pose=msgs.msg_class("geometry_msgs/Pose", store)(
                position=P.Point(x, y), orientation=msgs.msg_class("geometry_msgs/Quaternion", store)(x=0.0, y=0.0, z=0.0, w=1.0)))
        return msgs.serialize(pose, POSE, store)

    def scan_bytes(self, seq: int, stamp: float, ranges: np.ndarray) -> bytes:
        store = P.store()
        scan = msgs.msg_class(SCAN, store)(
            header=msgs.msg_class("std_msgs/Header", store)(seq=seq, stamp=_time(store, stamp), frame_id="base_scan"),
            angle_min=0.0, angle_max=float(2 * math.pi), angle_increment=float(2 * math.pi / SCAN_BEAMS),
            time_increment=0.0, scan_time=0.2, range_min=0.12, range_max=3.5, ranges=ranges,
            intensities=np.zeros(0, dtype=np.float32))
        return msgs.serialize(scan, SCAN, store)

    def twist_bytes(self, speed: float, seq: int, heading: float) -> bytes:
        store = P.store()
        vec = msgs.msg_class("geometry_msgs/Vector3", store)
        t = msgs.msg_class(TWIST, store)(linear=vec(x=speed, y=0.0, z=float(seq)), angular=vec(x=0.0, y=0.0, z=heading))
        return msgs.serialize(t, TWIST, store)

    def read_pose(self, data: bytes) -> tuple[float, float]:
        m = msgs.deserialize(data, POSE, P.store())
        return m.pose.position.x, m.pose.position.y

    def read_scan(self, data: bytes) -> tuple[float, float, Any]:
        m = msgs.deserialize(data, SCAN, P.store())
        return m.angle_min, m.angle_increment, m.ranges

    def read_twist_speed(self, data: bytes) -> float:
        return float(msgs.deserialize(data, TWIST, P.store()).linear.x)

    async def _drivers(self, pose_pub: Any, scan_pub: Any) -> None:
        i = 0
        while not self.stop.is_set():
            if self.robot is not None and self.robot.state != DEAD:
                x, y = self.robot.pos
                stamp = time.time()
                bad = self.compromise
                px, py, pstamp = bad.pose(x, y, stamp) if bad is not None else (x, y, stamp)
                raw = self.pose_bytes(i, pstamp, px, py)
                self.base_published.add(digest(raw))
                self._publish_raw(pose_pub, raw)
                if i % 4 == 0:
                    ranges = laser_ranges(self.world.occupied, self.robot.cell, self.robot.cfg.resolution)
                    if bad is not None:
                        ranges = bad.ranges(ranges, 0.12, 3.5)
                    raw = self.scan_bytes(i, stamp, ranges)
                    self.base_published.add(digest(raw))
                    self._publish_raw(scan_pub, raw)
                i += 1
            await asyncio.sleep(0.05)

    def _command(self) -> None:
        """The explorer's drive command after each step (what a controller publishes)."""
        r = self.robot
        if r is None or self.cmd_pub is None or r.state not in (EXPLORE, HOME, RECRUITED) or not r.path:
            return
        nxt = r.path[0]
        heading = math.atan2(nxt[0] - r.cell[0], nxt[1] - r.cell[1])
        self._cmd_seq += 1
        raw = self.twist_bytes(float(r.cfg.speed), self._cmd_seq, float(heading))
        self.explorer_published.add(digest(raw))
        self._publish_raw(self.cmd_pub, raw)

    # -- status ---------------------------------------------------------------------------------

    def status(self, final: bool = False) -> dict[str, Any]:
        r = self.robot
        out: dict[str, Any] = {
            "name": self.name, "pid": os.getpid(), "ready": self.ready, "started": self.t0 is not None,
            "t": round(self.host.now(), 3) if self.host and self.t0 else 0.0,
            "state": STATE_NAMES[r.state] if r else "starting",
            "shut_down": self.stats["shut_down_at"] is not None,
            "observed": base64.b64encode(np.packbits(self.observed)).decode(),
            "stats": self.stats,
            "counters": dict(r.counters) if r else {},
            "rejected": dict(r.rejected) if r else {},
            "halted_s": round(self.host.halted_s, 3) if self.host else 0.0,
            "callback_errors": self.host.errors if self.host else 0,
            "travelled_m": round(r.travelled_m, 2) if r else 0.0,
            "final": final,
        }
        if r is not None and r.state == DONE and self.done_at_s is None:
            self.done_at_s = round(time.time(), 3)  # when it stopped exploring, believing the map explored
        out["done_at"] = self.done_at_s
        if r is not None:
            known = r.belief.known
            out["belief"] = base64.b64encode(np.packbits(known != -1)).decode()
            out["belief_free"] = base64.b64encode(np.packbits(known == 0)).decode()
            out["false_obstacles"] = int(np.count_nonzero((known == OCC) & ~self.world.occupied))
            out["cell"] = list(r.cell)
        if final:
            out["published"] = sorted(self.published)
        return out

    def write_status(self, final: bool = False) -> None:
        tmp = self.status_path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.status(final)))
        os.replace(tmp, self.status_path)

    # -- lifecycle --------------------------------------------------------------------------------

    def _shutdown_called(self, node: Node) -> None:
        self.stats["shutdown_calls"] += 1
        self.stats["shutdown_reasons"].append(f"{node.name}: {node.shutdown_reason}")
        node.shutdown_requested.clear()
        if self.stats["shut_down_at"] is None:
            self.stats["shut_down_at"] = round(self.host.now(), 3) if self.host else 0.0
        if self.robot is not None:  # a ROS node that is told to shut down stops working
            self.robot.state = DEAD
            self.robot.finished_at = self.host.now() if self.host else 0.0

    async def _watch_shutdown(self, node: Node) -> None:
        while not self.stop.is_set():
            await node.shutdown_requested.wait()
            self._shutdown_called(node)

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, self.stop.set)
        cfg = self.cfg
        store = P.store()
        self.base_published: set[str] = set()
        self.explorer_published: set[str] = set()
        self._cmd_seq = 0
        self.cmd_pub = None
        explorer = Node(f"/{self.name}", cfg["master_uri"], host=cfg["ros_ip"], store=store, api_timeout=10)
        base = Node(f"/{self.name}_base", cfg["master_uri"], host=cfg["ros_ip"], store=store, api_timeout=10)
        tasks: list[asyncio.Task] = []
        try:
            await explorer.start()
            await base.start()
            tasks.append(asyncio.ensure_future(self._watch_shutdown(explorer)))
            tasks.append(asyncio.ensure_future(self._watch_shutdown(base)))
            pose_pub = await base.advertise(f"/{self.name}/pose", POSE)
            scan_pub = await base.advertise(f"/{self.name}/scan", SCAN)
            await base.subscribe(f"/{self.name}/cmd_vel", TWIST, self._on_cmd, raw=True, with_publisher=True)
            self.cmd_pub = await explorer.advertise(f"/{self.name}/cmd_vel", TWIST)
            await explorer.subscribe(f"/{self.name}/pose", POSE, self._on_pose, raw=True, with_publisher=True)
            await explorer.subscribe(f"/{self.name}/scan", SCAN, self._on_scan, raw=True, with_publisher=True)
            for typename, topic in TEAM_TOPICS.items():
                self.pubs[typename] = await explorer.advertise(topic, typename)
            subs = []
            for typename, topic in TEAM_TOPICS.items():
                subs.append(await explorer.subscribe(topic, typename, lambda d, h, t=typename: self._on_team(t, d, h),
                                                     raw=True, with_publisher=True))
            # ready when this robot hears every team member on the team topics (bounded)
            with contextlib.suppress(TimeoutError, asyncio.TimeoutError):
                await asyncio.wait_for(_all_connected(subs, len(self.team)), float(cfg.get("connect_timeout", 20)))
            self.ready = True
            await self._run_mission(loop, pose_pub, scan_pub)
        finally:
            self.stop.set()
            for t in tasks:
                t.cancel()
            with contextlib.suppress(Exception):
                self.write_status(final=True)
            for n in (explorer, base):
                with contextlib.suppress(Exception):
                    async with asyncio.timeout(3):
                        await n.close()

    async def _run_mission(self, loop: asyncio.AbstractEventLoop, pose_pub: Any, scan_pub: Any,
                           waiting: Callable[[], None] = lambda: None, period: float = 0.05) -> None:
        """Once ready: wait for the common start (``waiting()`` every ``period``), then run the
        robot and its drivers, writing the status twice a second, until stopped."""
        self.write_status()
        while not self.go_path.exists() and not self.stop.is_set():
            waiting()
            await asyncio.sleep(period)
        if self.stop.is_set():
            return
        self.t0 = float(json.loads(self.go_path.read_text())["t0"])
        while time.time() < self.t0:
            await asyncio.sleep(0.01)
        self._start_robot(loop)
        drivers = asyncio.ensure_future(self._drivers(pose_pub, scan_pub))
        misuse = {"cmd-flood": self._flood, "false-map": self._false_map}.get(self._compromise_kind() or "")
        flood = asyncio.ensure_future(misuse()) if misuse is not None else None
        try:
            while not self.stop.is_set():
                self.write_status()
                with contextlib.suppress(asyncio.TimeoutError, TimeoutError):
                    await asyncio.wait_for(self.stop.wait(), 0.5)
        finally:
            drivers.cancel()
            if flood is not None:
                flood.cancel()

    def _compromise_kind(self) -> str | None:
        return (self.cfg.get("compromise") or {}).get("kind")

    async def _false_map(self) -> None:
        """A compromised explorer: "the whole map is free and explored" on /team/map, which it may publish."""
        bad = self.compromise
        while bad is not None and not bad.active() and not self.stop.is_set():
            await asyncio.sleep(0.05)
        height, width = self.world.shape
        seq = 0
        while not self.stop.is_set():
            seq += 1
            claim = P.make(P.MAP, source=self.name, seq=1_000_000 + seq, timestamp=self.host.now() if self.host else 0.0,
                           position=P.Point(0.0, 0.0), goal=P.Point(0.0, 0.0), exploration_complete=True, origin_x=0,
                           origin_y=0, width=width, height=height, data=np.zeros(width * height, dtype=np.int8))
            self._broadcast(P.MAP, P.encode(claim, P.MAP))
            await asyncio.sleep(1.0 / FALSE_MAP_HZ)

    async def _flood(self) -> None:
        """A compromised explorer: stop commands at FLOOD_HZ on its own cmd_vel."""
        bad = self.compromise
        while bad is not None and not bad.active() and not self.stop.is_set():
            await asyncio.sleep(0.05)
        seq = 0
        while not self.stop.is_set() and self.cmd_pub is not None:
            seq += 1
            raw = self.twist_bytes(0.0, 10_000_000 + seq, 0.0)
            self.explorer_published.add(digest(raw))
            self._publish_raw(self.cmd_pub, raw)
            await asyncio.sleep(1.0 / FLOOD_HZ)

    def _start_robot(self, loop: asyncio.AbstractEventLoop) -> None:
        seed = int(self.cfg["seed"])
        kind = self._compromise_kind()
        if kind is not None:
            height, width = self.world.shape
            self.compromise = Compromise(kind, (self.t0 or time.time()) + float(self.cfg["compromise"]["onset"]),
                                         seed, (width * 0.2, height * 0.2))
        rng = np.random.default_rng(seed * 1000 + self.index)
        managers, _, _ = make_managers([self.name], SecurityConfig(), seed, {self.name: rng})
        self.host = LiveHost(loop, self.t0 or time.time(), self.scale, self.world, Lidar(3.5 / 0.2), self.observed, self._broadcast)
        rcfg = RobotConfig(resolution=0.2, recruit=True)
        self.robot = Robot(self.name, self.host, rng, start=self.start_cell, shape=self.world.shape, bases=self.world.bases,
                           config=rcfg, security=managers[self.name])
        self.host.robot = self.robot
        original_step = self.robot._step
        explorer = self

        def step() -> None:
            original_step()
            explorer._command()

        # the command after each step is published by the explorer itself
        self.robot._schedule_step = _wrap_schedule(self.robot, step)  # type: ignore[method-assign]
        self.robot.start()


def _wrap_schedule(robot: Robot, step: Callable[[], None]) -> Callable[[float], None]:
    host = robot.host

    class _Step:
        # recognised by LiveHost as a motion step: a halted base obeys the stop commands it
        # received. A flag, not ``__func__ = Robot._step``: an instance reads that as a bound
        # method, never ``Robot._step`` itself, and a stop flood would halt nothing.
        is_motion_step = True

        def __call__(self) -> None:
            step()

    def schedule(delay: float) -> None:
        if not robot._stepping:
            robot._stepping = True
            host.call_later(delay, _Step())

    return schedule


async def _all_connected(subs: list[Any], n: int) -> None:
    while any(s.num_connections < n for s in subs):
        await asyncio.sleep(0.05)


def _time(store: Any, t: float) -> Any:
    return msgs.msg_class("builtin_interfaces/msg/Time", store)(sec=int(t), nanosec=int((t % 1) * 1e9))


def main() -> None:
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s robot %(name)s %(levelname)s %(message)s")
    cfg = json.loads(Path(sys.argv[1]).read_text())
    with contextlib.suppress(Exception):
        from cryptoros.ros1.node import install_uvloop

        install_uvloop()
    asyncio.run(DemoRobot(cfg).run())


if __name__ == "__main__":
    main()
