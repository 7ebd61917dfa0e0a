"""Plain rclpy publisher and subscriber for ``cryptoros bench ros2`` (rclpy + rawtake.py only).

    bench_node.py pub small|image COUNT HZ     (HZ 0: as fast as the publisher can)
    bench_node.py sub small|image COUNT IDLE   prints READY, WARM, then one JSON line

Identical for both paths (direct and through the interceptor pair):

- QoS reliable + KEEP_ALL on both ends: the publisher is paced by what the path
  accepts instead of overwriting a queue, and nothing is lost on the direct path.
- Warm-up: the publisher sends marked warm-up messages (10 ms apart) until the
  controller, having seen the subscriber report ``WARM`` (one warm-up arrived, so
  the whole path is matched and streaming), writes ``GO`` on its stdin; warm-ups are
  not counted.
- Both ends use serialized messages (``raw=True`` subscription, CDR bytes published).
  The subscriber is not the bottleneck: rclpy's executors deliver only 1,100 to 1,900
  small messages a second here, so it takes messages with the lean wait-set loop of
  :mod:`rawtake` (every ready message per wake-up) on its own thread and only records
  arrival time and bytes; parsing happens after the run. Neither node's Python
  message (de)serialization is measured, only the path.
- KEEP_ALL publishers get an error when the reader stays full for the blocking
  time: the publisher retries the same message (backpressure, nothing skipped).
- Each message carries its send time (``time.time_ns``; publisher and subscriber share
  the host clock): one-way latency. The subscriber counts what it really received;
  rates are over its receive window, MB/s counts the serialized bytes received.
- Each node reports its own CPU (``time.process_time``: all threads, rclpy and DDS
  included) over its measured window: the publisher over its send loop, the
  subscriber from ``WARM`` to the last message (it prints ``DONE`` then, before
  parsing, so the controller can read the other processes' CPU at that moment).
"""

import json
import os
import select
import struct
import sys
import threading
import time

import rclpy
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image
from std_msgs.msg import String

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from rawtake import RawTaker  # noqa: E402  (rclpy only; the same loop for both paths)

IMAGE = bytes(80 * 1024)
QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1, reliability=ReliabilityPolicy.RELIABLE)
CDR_HEADER = b"\x00\x01\x00\x00"
STRING_LEN = 55  # + NUL + u32 length + CDR header = 64 B serialized
STAMP = struct.Struct("<iI")  # builtin_interfaces/Time right after the CDR header (Image.header.stamp)


def _string(text: str) -> bytes:
    body = text.ljust(STRING_LEN, ".").encode()
    return CDR_HEADER + struct.pack("<I", len(body) + 1) + body + b"\x00"


def _transport_cpu() -> dict[str, float]:
    """CPU seconds of this process's Fast DDS receive threads, by transport (``dds.shm.<port>``,
    ``dds.udp.<port>``): which one carried the row (shared memory, or UDP loopback)."""
    out: dict[str, float] = {}
    tick = os.sysconf("SC_CLK_TCK")
    for tid in os.listdir("/proc/self/task"):
        try:
            stat = open(f"/proc/self/task/{tid}/stat").read()
        except OSError:
            continue
        comm = stat[stat.index("(") + 1:stat.rindex(")")]
        if comm.startswith(("dds.shm.", "dds.udp.")):
            fields = stat[stat.rindex(")") + 2:].split()
            out[comm[:7]] = out.get(comm[:7], 0.0) + (int(fields[11]) + int(fields[12])) / tick
    return out


def _publisher(node, kind: str, count: int, hz: float) -> None:
    msg_type = Image if kind == "image" else String
    pub = node.create_publisher(msg_type, "/bench", QOS)
    if kind == "image":
        img = Image(width=160, height=128, encoding="rgba8", step=640, data=IMAGE)
        template = bytearray(serialize_message(img))

        def make(warm: bool) -> bytes:
            STAMP.pack_into(template, 4, *((0, 0) if warm else divmod(time.time_ns(), 1_000_000_000)))
            return bytes(template)
    else:
        def make(warm: bool) -> bytes:
            return _string("W" if warm else f"M {time.time_ns()} ")

    go = False
    while not go:  # warm up until the controller says GO
        try:
            pub.publish(make(True))
        except Exception:  # noqa: BLE001  (KEEP_ALL reader full: the next warm-up will do)
            pass
        ready, _, _ = select.select([sys.stdin], [], [], 0.01)
        if ready:
            line = sys.stdin.readline()
            if not line or line.strip() == "GO":
                go = True
    time.sleep(0.3)  # the warm-ups drain before the measured messages
    period = 1.0 / hz if hz else 0.0
    cpu0 = time.process_time()  # this process's CPU (all threads, incl. rclpy/DDS) over the measured loop
    start = time.monotonic()
    next_at = start
    retries = 0
    longest, longest_at = 0.0, 0.0  # the longest wait for the path to accept one message, and when it began
    for _ in range(count):
        data = make(False)
        began = time.monotonic()
        while True:
            try:
                pub.publish(data)
                break
            except Exception:  # KEEP_ALL: the reader is full; wait and retry the same message
                if not rclpy.ok():  # shut down by a signal: stop
                    raise SystemExit(1)
                retries += 1
                time.sleep(0.0005)
        waited = time.monotonic() - began
        if waited > longest:
            longest, longest_at = waited, time.time() - waited
        if period:
            next_at += period
            delay = next_at - time.monotonic()
            if delay > 0:
                time.sleep(delay)
    elapsed = time.monotonic() - start
    cpu = time.process_time() - cpu0
    print(json.dumps({"sent": count, "send_rate": count / elapsed if elapsed else 0.0, "pub_cpu_s": cpu,
                      "pub_transport_cpu_s": _transport_cpu(),
                      "pub_retries": retries,
                      "pub_longest_wait_ms": longest * 1e3, "pub_longest_wait_at": longest_at}), flush=True)
    time.sleep(3.0)  # keep the writer alive while reliable delivery finishes


def _subscriber(node, kind: str, count: int, idle: float) -> None:
    arrivals: list[tuple[int, bytes]] = []
    record = arrivals.append
    warm = threading.Event()

    def on_batch(batch) -> None:
        now = time.time_ns()
        for _, data, _ in batch:
            record((now, data))

    sub = node.create_subscription(Image if kind == "image" else String, "/bench", lambda _: None, QOS, raw=True)
    taker = RawTaker(node.context)
    taker.add(0, sub)
    threading.Thread(target=taker.run, args=(on_batch,), daemon=True).start()
    print("READY", flush=True)

    def is_warm(data: bytes) -> bool:
        return data[8:9] == b"W" if kind == "small" else STAMP.unpack_from(data, 4) == (0, 0)

    deadline = time.monotonic() + 60
    while not warm.is_set() and time.monotonic() < deadline:
        if any(is_warm(d) for _, d in arrivals[-5:]):
            warm.set()
        time.sleep(0.005)
    print("WARM", flush=True)
    cpu0 = time.process_time()  # this process's CPU (all threads) from WARM until the last message
    skip = len(arrivals)
    deadline = time.monotonic() + 180
    last_n, last_change = skip, time.monotonic()
    while time.monotonic() < deadline:
        time.sleep(0.02)
        n = len(arrivals)
        if n == last_n and time.monotonic() - last_change > idle:
            break
        if n - skip >= count and sum(1 for _, d in arrivals[skip:] if not is_warm(d)) >= count:
            break
        if n != last_n:
            last_n, last_change = n, time.monotonic()
    cpu = time.process_time() - cpu0
    print("DONE", flush=True)  # the controller reads the other processes' CPU now, before the parsing below
    got = [(t, d) for t, d in arrivals[skip:] if not is_warm(d)]
    latencies = []
    for t, d in got:
        if kind == "image":
            sec, nsec = STAMP.unpack_from(d, 4)
            sent = sec * 1_000_000_000 + nsec
        else:
            sent = int(d[8:8 + STRING_LEN].split()[1])
        latencies.append((t - sent) / 1e6)
    lat = sorted(latencies)
    n = len(lat)
    elapsed = (got[-1][0] - got[0][0]) / 1e9 if n > 1 else 0.0
    size = sum(len(d) for _, d in got[1:])
    print(json.dumps({
        "received": n,
        "rate": (n - 1) / elapsed if elapsed else 0.0,
        "mbps": size / elapsed / 1e6 if elapsed else 0.0,
        "p50": lat[n // 2] if n else None,
        "p99": lat[min(n - 1, int(n * 0.99))] if n else None,
        "sub_cpu_s": cpu,
        "sub_transport_cpu_s": _transport_cpu(),
        # longest silence between two arrivals: a reliable DDS repair (heartbeat, NACK, resend) shows here
        "max_gap_ms": max(((b[0] - a[0]) / 1e6 for a, b in zip(got, got[1:])), default=0.0),
        "gaps_over_100ms": sum(1 for a, b in zip(got, got[1:]) if b[0] - a[0] > 100_000_000),
        # when the longest silence began (epoch seconds), to line it up with other processes' logs
        "max_gap_at": max(((b[0] - a[0], a[0] / 1e9) for a, b in zip(got, got[1:])), default=(0, 0.0))[1],
    }), flush=True)


def main() -> None:
    role, kind, count, arg = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
    rclpy.init()
    node = rclpy.create_node(f"bench_{role}")
    try:
        if role == "pub":
            _publisher(node, kind, count, arg)
        else:
            _subscriber(node, kind, count, arg)
    finally:  # say goodbye in discovery: a reader left matched would hold a KEEP_ALL writer of the next row
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
