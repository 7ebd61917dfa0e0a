"""An unmodified rclpy listener (no cryptoros code).

    listener.py KIND TOPIC SECONDS [--latched] [--node NAME]

Prints READY, then ``GOT <seq>`` for every intact message and ``BAD <seq>`` for any
other, for SECONDS seconds.
"""

import argparse
import time

import rclpy
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from payload import TYPES, intact, seq_of

parser = argparse.ArgumentParser()
parser.add_argument("kind", choices=sorted(TYPES))
parser.add_argument("topic")
parser.add_argument("seconds", type=float)
parser.add_argument("--latched", action="store_true")
parser.add_argument("--node", default="listener")
parser.add_argument("--keep-all", action="store_true", help="KEEP_ALL history (the publisher waits for this reader)")
parser.add_argument("--stall-after", type=int, default=None,
                    help="after this many messages, stop taking any (a stuck subscriber: its reader fills up)")
args = parser.parse_args()

rclpy.init()
node = rclpy.create_node(args.node)
qos = QoSProfile(
    depth=100,
    durability=DurabilityPolicy.TRANSIENT_LOCAL if args.latched else DurabilityPolicy.VOLATILE,
    reliability=ReliabilityPolicy.RELIABLE,
    history=HistoryPolicy.KEEP_ALL if args.keep_all else HistoryPolicy.KEEP_LAST,
)


received = 0


def on_message(msg) -> None:
    global received
    received += 1
    print(f"{'GOT' if intact(args.kind, msg) else 'BAD'} {seq_of(args.kind, msg)}", flush=True)


node.create_subscription(TYPES[args.kind], args.topic, on_message, qos)
print("READY", flush=True)
end = time.monotonic() + args.seconds
while time.monotonic() < end:
    if args.stall_after is not None and received >= args.stall_after:
        print("STALLED", flush=True)
        time.sleep(max(0.0, end - time.monotonic()))
        break
    rclpy.spin_once(node, timeout_sec=0.05)
print("END", flush=True)
