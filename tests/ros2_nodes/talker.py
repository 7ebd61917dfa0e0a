"""An unmodified rclpy talker (no cryptoros code): publishes KIND messages on TOPIC.

    talker.py KIND TOPIC COUNT HZ [--latched] [--node NAME]

Message ``seq`` carries content derived from ``seq`` (see payload.py), so a listener
can check every message arrived intact and in order.
"""

import argparse
import signal
import threading
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
parser.add_argument("--burst-on-signal", action="store_true",
                    help="publish without pause from the first SIGUSR1 on (the caller saw the path up)")
args = parser.parse_args()
burst = threading.Event()
signal.signal(signal.SIGUSR1, lambda *_: burst.set())

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
    if burst.is_set():
        continue
    next_at += period
    burst.wait(max(0.0, next_at - time.monotonic()))
print("DONE", flush=True)
end = time.monotonic() + args.linger  # keep the publisher (and a latched message) alive
while time.monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.1)
