"""A fresh rclpy participant that prints who publishes TOPIC, as DDS discovery tells it.

    publishers.py TOPIC SECONDS

Prints ``PUB <node>`` for each publisher of TOPIC it sees within SECONDS (polled every
0.2 s), then ``DONE``.
"""

import sys
import time

import rclpy

topic, seconds = sys.argv[1], float(sys.argv[2])
rclpy.init()
node = rclpy.create_node("graph_probe")
seen: set[str] = set()
deadline = time.monotonic() + seconds
while time.monotonic() < deadline:
    rclpy.spin_once(node, timeout_sec=0.2)
    for info in node.get_publishers_info_by_topic(topic):
        if info.node_name not in seen:
            seen.add(info.node_name)
            print(f"PUB {info.node_name}", flush=True)
print("DONE", flush=True)
