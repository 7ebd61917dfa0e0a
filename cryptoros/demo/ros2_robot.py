"""One demo robot on ROS 2 Jazzy: the simulator's robot logic as two rclpy nodes.

``python -m cryptoros.demo.ros2_robot CONFIG.json``, run by the ROS 2 venv's python
(``scripts/ros2-venv``) with ``ROS_DOMAIN_ID`` set to the robot's domain. The same robot
as :mod:`cryptoros.demo.robot` (ROS 1), with the same evidence and status file; only
the transport and the message codec differ:

* ``/rN`` (explorer) and ``/rN_base`` (drivers) are rclpy nodes of one process, spun
  by one executor thread; their callbacks hand the serialized message to the asyncio
  loop that runs :class:`cryptoros.sim.robot.Robot`.
* ``/rN/pose`` (``geometry_msgs/msg/PoseStamped``), ``/rN/scan``
  (``sensor_msgs/msg/LaserScan``) and ``/rN/cmd_vel`` (``geometry_msgs/msg/Twist``)
  are real ROS 2 messages (CDR).
* The team radio: ``/team/hello`` ... ``/team/protocol`` carry the simulator's packets
  as ``std_msgs/msg/UInt8MultiArray`` (a custom ``.msg`` needs generated type
  support, which the PyPI wheels cannot build; the interceptors forward any installed
  type without decoding it).
* ``/team/presence`` (``std_msgs/msg/String``): the robot's name, four times a second
  until the mission starts; a robot is ready when it has heard every team mate, so the
  path between robots (one shared domain, or the interceptors) is proven before the
  clock starts.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import rclpy
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion, Twist, Vector3
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import LaserScan
from std_msgs.msg import Header, String, UInt8MultiArray

from cryptoros.demo.robot import SCAN_BEAMS, TEAM_TOPICS, DemoRobot

log = logging.getLogger("cryptoros.demo.ros2_robot")

#: ROS 2 type of each topic kind (the policy of ``cryptoros demo --ros 2`` grants these)
TEAM_TYPE = "std_msgs/msg/UInt8MultiArray"
PRESENCE_TOPIC, PRESENCE_TYPE = "/team/presence", "std_msgs/msg/String"
POSE2, SCAN2, TWIST2 = "geometry_msgs/msg/PoseStamped", "sensor_msgs/msg/LaserScan", "geometry_msgs/msg/Twist"
RELIABLE = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)


def wrap_packet(data: bytes) -> bytes:
    """A simulator packet as the CDR of a ``std_msgs/msg/UInt8MultiArray``."""
    return serialize_message(UInt8MultiArray(data=data))


def unwrap_packet(cdr: bytes) -> bytes:
    return bytes(deserialize_message(cdr, UInt8MultiArray).data)


def _stamp(t: float) -> Any:
    from builtin_interfaces.msg import Time

    return Time(sec=int(t), nanosec=int((t % 1) * 1e9))


def spin_quietly(executor: SingleThreadedExecutor) -> None:
    """The executor's thread: spins until the executor or rclpy is shut down."""
    with contextlib.suppress(ExternalShutdownException, Exception):
        executor.spin()


class Ros2Publisher:
    """``publish_raw(bytes)`` as :class:`DemoRobot` expects; team packets are wrapped."""

    def __init__(self, publisher: Any, wrap: bool) -> None:
        self._publisher = publisher
        self._wrap = wrap
        self.closed = False

    def publish_raw(self, data: bytes) -> None:
        if not self.closed:  # the robot's last timers may fire while its nodes are destroyed
            self._publisher.publish(wrap_packet(data) if self._wrap else data)


class Ros2DemoRobot(DemoRobot):
    """:class:`DemoRobot` on rclpy: codec and transport; the evidence is inherited."""

    # -- codec: real ROS 2 messages ---------------------------------------------------------------

    def pose_bytes(self, seq: int, stamp: float, x: float, y: float) -> bytes:
        return serialize_message(PoseStamped(
            header=Header(stamp=_stamp(stamp), frame_id="map"),
            pose=Pose(position=Point(x=float(x), y=float(y)), orientation=Quaternion(w=1.0))))

    def scan_bytes(self, seq: int, stamp: float, ranges: np.ndarray) -> bytes:
        return serialize_message(LaserScan(
            header=Header(stamp=_stamp(stamp), frame_id="base_scan"), angle_min=0.0, angle_max=float(2 * math.pi),
            angle_increment=float(2 * math.pi / SCAN_BEAMS), time_increment=0.0, scan_time=0.2, range_min=0.12,
            range_max=3.5, ranges=[float(r) for r in ranges]))

    def twist_bytes(self, speed: float, seq: int, heading: float) -> bytes:
        return serialize_message(Twist(linear=Vector3(x=speed, y=0.0, z=float(seq)), angular=Vector3(z=heading)))

    def read_pose(self, data: bytes) -> tuple[float, float]:
        m = deserialize_message(data, PoseStamped)
        return m.pose.position.x, m.pose.position.y

    def read_scan(self, data: bytes) -> tuple[float, float, Any]:
        m = deserialize_message(data, LaserScan)
        return m.angle_min, m.angle_increment, np.asarray(m.ranges, dtype=float)

    def read_twist_speed(self, data: bytes) -> float:
        return float(deserialize_message(data, Twist).linear.x)

    # -- transport --------------------------------------------------------------------------------

    def _publisher(self, node: Any, cls: type, topic: str, qos: Any = 10, wrap: bool = False) -> Ros2Publisher:
        pub = Ros2Publisher(node.create_publisher(cls, topic, qos), wrap=wrap)
        self.publishers.append(pub)
        return pub

    def _subscribe(self, node: Any, cls: type, topic: str, loop: asyncio.AbstractEventLoop,
                   handler: Callable[[bytes], None], qos: Any = 10) -> None:
        def callback(data: bytes) -> None:  # the executor's thread: hand over to the robot's loop
            loop.call_soon_threadsafe(self._safe, handler, data)

        node.create_subscription(cls, topic, callback, qos, raw=True)

    def _safe(self, handler: Callable[[bytes], None], data: bytes) -> None:
        try:
            handler(data)
        except Exception:  # a malformed message (an attacker's) must not stop the robot
            if self.host is not None:
                self.host.errors += 1
            log.debug("callback failed", exc_info=True)

    def _on_team_cdr(self, typename: str, cdr: bytes) -> None:
        self._on_team(typename, unwrap_packet(cdr))

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, self.stop.set)
        cfg = self.cfg
        self.base_published: set[str] = set()
        self.explorer_published: set[str] = set()
        self._cmd_seq = 0
        self.cmd_pub = None
        self.publishers: list[Ros2Publisher] = []
        rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        options = {"enable_rosout": False, "start_parameter_services": False}
        explorer = rclpy.create_node(self.name, **options)
        base = rclpy.create_node(f"{self.name}_base", **options)
        heard: set[str] = set()
        executor = SingleThreadedExecutor()
        spinner: threading.Thread | None = None
        try:
            pose_pub = self._publisher(base, PoseStamped, f"/{self.name}/pose")
            scan_pub = self._publisher(base, LaserScan, f"/{self.name}/scan")
            self._subscribe(base, Twist, f"/{self.name}/cmd_vel", loop, self._on_cmd)
            self.cmd_pub = self._publisher(explorer, Twist, f"/{self.name}/cmd_vel")
            self._subscribe(explorer, PoseStamped, f"/{self.name}/pose", loop, self._on_pose)
            self._subscribe(explorer, LaserScan, f"/{self.name}/scan", loop, self._on_scan)
            for typename, topic in TEAM_TOPICS.items():
                self.pubs[typename] = self._publisher(explorer, UInt8MultiArray, topic, RELIABLE, wrap=True)
                self._subscribe(explorer, UInt8MultiArray, topic, loop,
                                lambda d, t=typename: self._on_team_cdr(t, d), RELIABLE)
            presence = explorer.create_publisher(String, PRESENCE_TOPIC, 10)
            explorer.create_subscription(String, PRESENCE_TOPIC, lambda m: heard.add(m.data), 10)
            executor.add_node(explorer)
            executor.add_node(base)
            spinner = threading.Thread(target=spin_quietly, args=(executor,), name="rclpy", daemon=True)
            spinner.start()
            # ready when this robot hears every team mate (through whatever connects the robots)
            others = set(self.team) - {self.name}
            deadline = time.monotonic() + float(cfg.get("connect_timeout", 30))
            while not others <= heard and time.monotonic() < deadline and not self.stop.is_set():
                presence.publish(String(data=self.name))
                await asyncio.sleep(0.25)
            self.ready = others <= heard
            # team mates may still be waiting to hear us
            await self._run_mission(loop, pose_pub, scan_pub, lambda: presence.publish(String(data=self.name)), 0.25)
        finally:
            self.stop.set()
            with contextlib.suppress(Exception):
                self.write_status(final=True)
            for pub in self.publishers:
                pub.closed = True
            executor.shutdown(timeout_sec=2)
            for node in (explorer, base):
                with contextlib.suppress(Exception):
                    node.destroy_node()
            with contextlib.suppress(Exception):
                rclpy.try_shutdown()
            if spinner is not None:
                spinner.join(timeout=3)


def main() -> None:
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s ros2 robot %(name)s %(levelname)s %(message)s")
    cfg = json.loads(Path(sys.argv[1]).read_text())
    asyncio.run(Ros2DemoRobot(cfg).run())


__all__ = ["PRESENCE_TOPIC", "PRESENCE_TYPE", "POSE2", "SCAN2", "TEAM_TYPE", "TWIST2", "Ros2DemoRobot",
           "spin_quietly", "unwrap_packet", "wrap_packet"]

if __name__ == "__main__":
    main()
