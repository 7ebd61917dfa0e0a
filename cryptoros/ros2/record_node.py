"""``cryptoros monitor record --ros 2``: the recording node, run by the ROS 2 venv's python.

    python -m cryptoros.ros2.record_node CONFIG.json

``CONFIG``: ``{"topics": [...], "seconds": s, "out": "run.bag", "discovery_timeout": s}``.
On this process's ``ROS_DOMAIN_ID`` it waits until every topic has a publisher (to learn
its type), subscribes raw (serialized CDR, with a reader that matches reliable and
best-effort writers alike), takes the samples with their writers' GIDs
(:class:`cryptoros.ros2.rawtake.RawTaker`), names each writer by the ROS graph (its
node, as the DDS bridge does) and writes a ROS 1 bag: each sample converted to the ROS
1 serialization (``rosbags``), one connection per (topic, publisher node), the arrival
time as the record time. That is what ``cryptoros monitor train`` and ``eval`` read:
the features are those of the same messages over ROS 1, so one model serves both
roles. Prints ``recording`` once subscribed and a JSON line of counts at the end;
stops after ``seconds`` or at SIGTERM or SIGINT (the bag is closed either way).
"""

from __future__ import annotations

import importlib
import json
import signal
import sys
import threading
import time
from pathlib import Path

import rclpy
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from cryptoros.ros2.rawtake import RawTaker

#: samples kept per topic by the reader before the oldest are dropped
DEPTH = 1000
#: publishers named per topic at most (the rest are recorded under their GID)
MAX_WRITERS = 1024


def _message_class(typename: str) -> type:
    package, _, name = typename.split("/")
    return getattr(importlib.import_module(f"{package}.msg"), name)


def _node_name(namespace: str, name: str) -> str:
    return f"{namespace.rstrip('/')}/{name}" if namespace not in ("", "/") else f"/{name}"


class Recorder:
    def __init__(self, topics: list[str], out: Path, discovery_timeout: float) -> None:
        from rosbags.rosbag1 import Writer
        from rosbags.typesys import Stores, get_typestore

        self.node = rclpy.create_node("monitor_recorder", start_parameter_services=False, enable_rosout=False)
        self.data = rclpy.create_node("monitor_recorder_data", start_parameter_services=False, enable_rosout=False)
        self.store = get_typestore(Stores.ROS2_JAZZY)
        self.types = self._discover(topics, discovery_timeout)
        self.writer = Writer(out)
        self.connections: dict[tuple[str, str], object] = {}
        self.writers: dict[tuple[str, bytes], str] = {}
        self.counts: dict[str, int] = {}
        self.errors = 0
        self.taker = RawTaker(self.data.context)
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=DEPTH, reliability=ReliabilityPolicy.BEST_EFFORT,
                         durability=DurabilityPolicy.VOLATILE)
        for topic, typename in self.types.items():
            sub = self.data.create_subscription(_message_class(typename), topic, lambda _msg: None, qos, raw=True)
            self.taker.add(topic, sub)

    def _discover(self, topics: list[str], timeout: float) -> dict[str, str]:
        deadline = time.monotonic() + timeout
        while True:
            known = dict(self.node.get_topic_names_and_types())
            types = {t: known[t][0] for t in topics if known.get(t)}
            if len(types) == len(topics):
                return types
            if time.monotonic() > deadline:
                missing = ", ".join(t for t in topics if t not in types)
                raise SystemExit(f"no publisher of {missing} appeared within {timeout:g} s on ROS_DOMAIN_ID "
                                 "(is this the robot's domain?)")
            time.sleep(0.1)

    def _publisher(self, topic: str, gid: bytes) -> str:
        """The node that owns the writer ``gid`` (looked up in the graph once per writer)."""
        key = (topic, gid)
        name = self.writers.get(key)
        if name is None:
            name = f"gid:{gid.hex()[:16]}"
            for info in self.node.get_publishers_info_by_topic(topic):
                if bytes(info.endpoint_gid)[: len(gid)] == gid:
                    name = _node_name(info.node_namespace, info.node_name)
                    break
            if len(self.writers) < MAX_WRITERS:
                self.writers[key] = name
        return name

    def on_batch(self, batch: list[tuple[object, bytes, bytes]]) -> None:
        now = time.time_ns()
        for topic, cdr, gid in batch:
            typename = self.types[str(topic)]
            publisher = self._publisher(str(topic), gid)
            try:
                ros1 = self.store.cdr_to_ros1(bytes(cdr), typename)
            except Exception:  # a sample that does not decode as its type: not recorded, counted
                self.errors += 1
                continue
            conn = self.connections.get((str(topic), publisher))
            if conn is None:
                conn = self.writer.add_connection(str(topic), typename, typestore=self.store, callerid=publisher)
                self.connections[(str(topic), publisher)] = conn
            self.writer.write(conn, now, ros1)
            label = f"{publisher} on {topic}"
            self.counts[label] = self.counts.get(label, 0) + 1

    def run(self, seconds: float, stop: threading.Event) -> None:
        self.writer.open()
        thread = threading.Thread(target=self.taker.run, args=(self.on_batch,), daemon=True)
        thread.start()
        try:
            print(f"recording {', '.join(self.types)}", flush=True)
            stop.wait(seconds)
        finally:
            self.taker.stop()
            thread.join(timeout=10)
            self.writer.close()


def main() -> None:
    cfg = json.loads(Path(sys.argv[1]).read_text())
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    rclpy.init(signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    try:
        recorder = Recorder(list(cfg["topics"]), Path(cfg["out"]), float(cfg.get("discovery_timeout", 20.0)))
        recorder.run(float(cfg["seconds"]), stop)
        print(json.dumps({"counts": recorder.counts, "undecodable": recorder.errors}), flush=True)
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
