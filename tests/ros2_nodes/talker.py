"""An unmodified rclpy talker (no cryptoros code): publishes KIND messages on TOPIC.

    talker.py KIND TOPIC COUNT HZ [--latched] [--node NAME]

Message ``seq`` carries content derived from ``seq`` (see payload.py), so a listener
can check every message arrived intact and in order.
"""

import argparse
import time

import rclpy
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from payload import TYPES, make

parser = argparse.ArgumentParser()
parser.add_argument("kind", choices=sorted(TYPES))
parser.add_argument("topic")
parser.add_argument("count", type=int)
parser.add_argument("hz", type=float)
parser.add_argument("--latched", action="store_true")
parser.add_argument("--best-effort", action="store_true")
parser.add_argument("--node", default="talker")
parser.add_argument("--offset", type=int, default=0)
parser.add_argument("--linger", type=float, default=30.0)
parser.add_argument("--keep-all", action="store_true", help="KEEP_ALL history (publish waits for the readers)")
parser.add_argument("--burst-after", type=int, default=None, help="after this many messages, publish without pause")
args = parser.parse_args()

rclpy.init()
node = rclpy.create_node(args.node)
qos = QoSProfile(
    depth=10 if not args.latched else 1,
    durability=DurabilityPolicy.TRANSIENT_LOCAL if args.latched else DurabilityPolicy.VOLATILE,
    reliability=ReliabilityPolicy.BEST_EFFORT if args.best_effort else ReliabilityPolicy.RELIABLE,
    history=HistoryPolicy.KEEP_ALL if args.keep_all else HistoryPolicy.KEEP_LAST,
)
pub = node.create_publisher(TYPES[args.kind], args.topic, qos)
print("READY", flush=True)
period = 1.0 / args.hz
next_at = time.monotonic()
for seq in range(args.count):
    msg = make(args.kind, args.offset + seq)
    while True:
        try:
            pub.publish(msg)
            break
        except Exception:  # KEEP_ALL: the readers are full for the blocking time; retry the same message
            if not rclpy.ok():  # shut down (SIGINT/SIGTERM): stop, do not retry
                raise SystemExit(0)
            time.sleep(0.001)
    if args.burst_after is not None and seq >= args.burst_after:
        continue
    next_at += period
    time.sleep(max(0.0, next_at - time.monotonic()))
print("DONE", flush=True)
end = time.monotonic() + args.linger  # keep the publisher (and a latched message) alive
while time.monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.1)
