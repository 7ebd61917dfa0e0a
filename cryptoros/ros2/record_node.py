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
#: seconds between two graph look-ups of a writer not in the graph yet
LOOKUP_RETRY_S = 0.2
#: a writer's samples are held this long for discovery to name it (then written under its GID)
HOLD_S = 3.0
#: samples held per unnamed writer at most (and at most MAX_WRITERS writers held at once)
HOLD_MAX = 20_000


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
        self._unnamed_until: dict[tuple[str, bytes], float] = {}
        #: samples of writers discovery has not named yet: (topic, gid) -> [(arrival ns, ROS 1 bytes)]
        self._held: dict[tuple[str, bytes], list[tuple[int, bytes]]] = {}
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

    def _publisher(self, topic: str, gid: bytes) -> str | None:
        """The node that owns the writer ``gid``, looked up in the graph (again every
        LOOKUP_RETRY_S while it is not there: a writer's first samples can arrive before
        discovery names it); None while unnamed."""
        key = (topic, gid)
        name = self.writers.get(key)
        if name is not None:
            return name
        now = time.monotonic()
        if self._unnamed_until.get(key, 0.0) > now:
            return None
        for info in self.node.get_publishers_info_by_topic(topic):
            # the writer can be discovered before its node: "_NODE_NAME_UNKNOWN_" until then
            if bytes(info.endpoint_gid)[: len(gid)] == gid and not info.node_name.startswith("_NODE_NAME_UNKNOWN_"):
                name = _node_name(info.node_namespace, info.node_name)
                if len(self.writers) < MAX_WRITERS:
                    self.writers[key] = name
                self._unnamed_until.pop(key, None)
                return name
        if len(self._unnamed_until) < MAX_WRITERS:
            self._unnamed_until[key] = now + LOOKUP_RETRY_S
        return None

    def _write(self, topic: str, publisher: str, arrival_ns: int, ros1: bytes) -> None:
        conn = self.connections.get((topic, publisher))
        if conn is None:
            conn = self.writer.add_connection(topic, self.types[topic], typestore=self.store, callerid=publisher)
            self.connections[(topic, publisher)] = conn
        self.writer.write(conn, arrival_ns, ros1)
        label = f"{publisher} on {topic}"
        self.counts[label] = self.counts.get(label, 0) + 1

    def _release(self, *, everything: bool = False) -> None:
        """Write the held samples of writers named since, and (or at the end, all of them)
        of writers still unnamed after HOLD_S, under their GID."""
        now = time.time_ns()
        for key in list(self._held):
            topic, gid = key
            name = self._publisher(topic, gid)
            if name is None and not everything and now - self._held[key][0][0] < HOLD_S * 1e9:
                continue
            if name is None:
                name = f"gid:{gid.hex()[:16]}"
                if len(self.writers) < MAX_WRITERS:
                    self.writers[key] = name  # given up on: recorded under its GID from now on
            for arrival_ns, ros1 in self._held.pop(key):
                self._write(topic, name, arrival_ns, ros1)

    def on_batch(self, batch: list[tuple[object, bytes, bytes]]) -> None:
        now = time.time_ns()
        for topic_key, cdr, gid in batch:
            topic = str(topic_key)
            try:
                ros1 = self.store.cdr_to_ros1(bytes(cdr), self.types[topic])
            except Exception:  # a sample that does not decode as its type: not recorded, counted
                self.errors += 1
                continue
            held = self._held.get((topic, gid))
            publisher = self._publisher(topic, gid) if held is None else None
            if publisher is not None:
                self._write(topic, publisher, now, ros1)
            elif (held is not None and len(held) >= HOLD_MAX) or (held is None and len(self._held) >= MAX_WRITERS):
                self._write(topic, f"gid:{gid.hex()[:16]}", now, ros1)  # bounded: no more held
            else:
                self._held.setdefault((topic, gid), []).append((now, ros1))
        if self._held:
            self._release()

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
            self._release(everything=True)
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
