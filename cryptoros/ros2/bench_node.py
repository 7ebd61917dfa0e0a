"""Plain rclpy publisher and subscriber for ``cryptoros bench ros2`` (no cryptoros code).

    bench_node.py pub small|image COUNT HZ     (HZ 0: as fast as rclpy publishes)
    bench_node.py sub small|image COUNT IDLE   prints one JSON line of figures

Each message carries its send time (``time.time_ns``; publisher and subscriber share
the host clock), so the subscriber measures one-way latency.
"""

import json
import sys
import time

import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image
from std_msgs.msg import String

IMAGE = bytes(80 * 1024)
QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)


def main() -> None:
    role, kind, count, arg = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
    rclpy.init()
    node = rclpy.create_node(f"bench_{role}")
    msg_type = Image if kind == "image" else String
    if role == "pub":
        pub = node.create_publisher(msg_type, "/bench", QOS)
        deadline = time.monotonic() + 60
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
        time.sleep(3.0)  # let a bridged path finish setting up its streams
        period = 1.0 / arg if arg else 0.0
        next_at = time.monotonic()
        msg = msg_type()
        if kind == "image":
            msg.width, msg.height, msg.encoding, msg.step, msg.data = 160, 128, "rgba8", 640, IMAGE
        for seq in range(count):
            now = time.time_ns()
            if kind == "image":
                msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(now, 1_000_000_000)
                msg.header.frame_id = str(seq)
            else:
                msg.data = f"{seq} {now} ".ljust(56, ".")
            pub.publish(msg)
            if period:
                next_at += period
                delay = next_at - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
        print("DONE", flush=True)
        time.sleep(3.0)
        return
    latencies, first, last = [], None, None
    size = 0

    def on_message(m) -> None:
        nonlocal first, last, size
        t = time.time_ns()
        sent = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec if kind == "image" else int(m.data.split()[1])
        latencies.append((t - sent) / 1e6)
        first = first or time.monotonic()
        last = time.monotonic()
        size = len(m.data)

    node.create_subscription(msg_type, "/bench", on_message, QOS)
    print("READY", flush=True)
    deadline = time.monotonic() + 120
    while len(latencies) < count and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
        if last is not None and time.monotonic() - last > arg:
            break
    lat = sorted(latencies)
    n = len(lat)
    elapsed = (last - first) if n > 1 else 0.0
    print(json.dumps({
        "received": n,
        "rate": (n - 1) / elapsed if elapsed else 0.0,
        "mbps": (n - 1) * size / elapsed / 1e6 if elapsed else 0.0,
        "p50": lat[n // 2] if n else None,
        "p99": lat[min(n - 1, int(n * 0.99))] if n else None,
    }), flush=True)


if __name__ == "__main__":
    main()
