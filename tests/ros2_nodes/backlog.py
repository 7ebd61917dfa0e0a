"""How many samples a reliable KEEP_ALL path holds before its writer blocks.

    backlog.py hold TOPIC     subscribes (reliable, KEEP_ALL), never takes a sample;
                              prints READY, exits when stdin closes
    backlog.py fill TOPIC N   once a reader is matched, publishes Strings (reliable,
                              KEEP_ALL) until one publish fails (the writer and the
                              reader are full) or N went out; prints SENT <count>

Every sample the publisher got out before it blocked is held by the writer (not yet
acknowledged) or the reader (acknowledged, not taken): the two histories' sizes, which
the Fast DDS profile in force decides.
"""

import sys
import time

import rclpy
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

role, topic = sys.argv[1], sys.argv[2]
QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1, reliability=ReliabilityPolicy.RELIABLE)
rclpy.init()
node = rclpy.create_node(f"backlog_{role}")
try:
    if role == "hold":
        node.create_subscription(String, topic, lambda _msg: None, QOS)
        print("READY", flush=True)
        sys.stdin.read()
    else:
        limit = int(sys.argv[3])
        pub = node.create_publisher(String, topic, QOS)
        deadline = time.monotonic() + 30
        while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.5)  # the reader has matched the writer too
        msg, sent = String(data="x" * 32), 0
        while sent < limit:
            try:
                pub.publish(msg)
            except Exception:  # noqa: BLE001  (KEEP_ALL: full past the writer's blocking time)
                break
            sent += 1
        print(f"SENT {sent}", flush=True)
finally:
    node.destroy_node()
    rclpy.try_shutdown()
