"""An unmodified rclpy service client (no cryptoros code).

    client.py SERVICE COUNT TIMEOUT [--at-once]

Waits up to TIMEOUT s for SERVICE (std_srvs/srv/SetBool), calls it COUNT times and
prints ``RESULT <success> <message>`` per answer, or ``NO_SERVICE`` / ``TIMEOUT``.
``--at-once``: the COUNT calls are made together (``SENT`` once they are), then answers
are awaited until TIMEOUT.
"""

import sys
import time

import rclpy
from std_srvs.srv import SetBool

service, count, timeout = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
rclpy.init()
node = rclpy.create_node("flag_client")
client = node.create_client(SetBool, service)
if not client.wait_for_service(timeout_sec=timeout):
    print("NO_SERVICE", flush=True)
    sys.exit(1)
deadline = time.monotonic() + timeout
if "--at-once" in sys.argv:
    futures = [client.call_async(SetBool.Request(data=True)) for _ in range(count)]
    print("SENT", flush=True)
    while time.monotonic() < deadline and not all(f.done() for f in futures):
        rclpy.spin_once(node, timeout_sec=0.1)
    print(f"ANSWERED {sum(f.done() for f in futures)}", flush=True)
    sys.exit(0)
for i in range(count):
    future = client.call_async(SetBool.Request(data=i % 2 == 0))
    rclpy.spin_until_future_complete(node, future, timeout_sec=max(0.1, deadline - time.monotonic()))
    if not future.done():
        print("TIMEOUT", flush=True)
        sys.exit(1)
    r = future.result()
    print(f"RESULT {r.success} {r.message}", flush=True)
