"""``cryptoros bench ros2-insider``: what two attacks of a compromised ROS 2 robot cost.

Builds the pair of ``cryptoros bench ros2`` (robot A's and robot B's interceptors,
``ros2`` role, each with its DDS bridge) with ``[limits] max_messages_per_second`` on
both, and lets robot A's certificate (a compromised robot A: it may publish
``/bench``) speak to robot B's public port by hand:

- **depth attack**: a ``/bench`` stream asking for
  ``transient_local`` with depth 1000, then ``--depth-samples`` samples of
  ``--sample-kib`` KiB. Robot B republishes it volatile with its own depth (it keeps
  nothing for late joiners on a topic its configuration does not name): printed are
  robot B's interceptor and bridge RSS before and after.
- **burst** (finding 3): ``--burst`` frames in one write, then 60 at 10 Hz, into a
  stream throttled to ``--rate`` messages a second; a listener on robot B's domain
  counts what arrives. Before the fix nothing arrived, ever, once a burst exceeded
  the bucket.

Nothing is asserted; the figures are printed.
"""

from __future__ import annotations

import contextlib
import queue
import shutil
import ssl
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import click

from cryptoros.lab.network import NetworkError, open_stream

from cryptoros.bench.ros2 import HOSTS, POLICY, _ros_env, children
from cryptoros.ros2 import framing as fr
from cryptoros.ros2.target import QoS, StreamTarget

LISTENER = """
import sys, threading, time, rclpy
from std_msgs.msg import String
expected = int(sys.argv[1])
closed = threading.Event()
threading.Thread(target=lambda: (sys.stdin.read(), closed.set()), daemon=True).start()
rclpy.init()
node = rclpy.create_node("bench_listener")
arrivals = []


def on_message(m):
    if m.data == "probe":  # the path is up: the burst may start
        if not arrivals:
            print("FIRST", flush=True)
        arrivals.append(None)
    else:
        arrivals.append(time.monotonic())


node.create_subscription(String, "/bench", on_message, 1000)
print("READY", flush=True)
end = time.monotonic() + 300
while time.monotonic() < end and not closed.is_set() and sum(t is not None for t in arrivals) < expected:
    rclpy.spin_once(node, timeout_sec=0.05)
times = [t for t in arrivals if t is not None]
print(len(times), (times[-1] - times[0]) if len(times) > 1 else 0.0, flush=True)
"""


def _rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def _string_cdr(size: int) -> bytes:
    """A std_msgs/msg/String of ``size`` bytes, as CDR (the receiver walks every sample)."""
    body = b"x" * size + b"\x00"
    cdr = b"\x00\x01\x00\x00" + len(body).to_bytes(4, "little") + body
    return cdr + b"\x00" * (-len(cdr) % 4)


def _probe_cdr() -> bytes:
    body = b"probe\x00"
    cdr = b"\x00\x01\x00\x00" + len(body).to_bytes(4, "little") + body
    return cdr + b"\x00" * (-len(cdr) % 4)


class _Lines:
    """A process's stdout lines, read by a thread so every wait is bounded."""

    def __init__(self, stream) -> None:
        self._lines: queue.Queue = queue.Queue()
        self._seen: list[str] = []
        threading.Thread(target=lambda: [self._lines.put(line.strip()) for line in stream], daemon=True).start()

    def has(self, wanted: str) -> bool:
        with contextlib.suppress(queue.Empty):
            while True:
                self._seen.append(self._lines.get_nowait())
        return wanted in self._seen

    def next_line(self, timeout: float) -> str:
        """The next line that is not FIRST."""
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            try:
                line = self._lines.get(timeout=left)
            except queue.Empty:
                break
            if line != "FIRST":
                return line
        return ""


class _RobotA:
    """Robot A's certificate and token, speaking ``ros2`` streams by hand."""

    def __init__(self, net) -> None:
        self.ctx, self.token = net.client_of("robot_a")

    def stream(self, host: str, port: int, qos: QoS) -> ssl.SSLSocket:
        target = StreamTarget(kind="topic", name="/bench", type="std_msgs/msg/String", node="/bench_pub", qos=qos)
        try:
            return open_stream(self.ctx, self.token, host, port, "ros2", target.encode())
        except NetworkError as exc:
            raise click.ClickException(f"robot B: {exc}") from None


@click.command("ros2-insider")
@click.option("--depth-samples", type=click.IntRange(1, 10_000), default=400, show_default=True,
              help="Samples sent on the transient_local depth-1000 stream.")
@click.option("--sample-kib", type=click.IntRange(1, 4096), default=256, show_default=True,
              help="Size of each of those samples.")
@click.option("--burst", type=click.IntRange(1, 100_000), default=600, show_default=True,
              help="Frames written at once into the throttled stream.")
@click.option("--rate", type=click.FloatRange(1, 100_000), default=200.0, show_default=True,
              help="[limits] max_messages_per_second of both interceptors.")
@click.option("--python", "python", default=None, help="The ROS 2 venv's python (default: .ros2-venv).")
def ros2_insider(depth_samples: int, sample_kib: int, burst: int, rate: float, python: str | None) -> None:
    """Robot B's RSS under a depth attack and the delivered rate after a burst (ROS 2)."""
    from cryptoros.lab.network import lab_network
    from interceptor.config import default_ros2_python

    py = Path(python) if python else default_ros2_python()
    if not py.exists():
        raise click.ClickException(f"{py} does not exist: create the ROS 2 venv with scripts/ros2-venv")
    work = Path(tempfile.mkdtemp(prefix="cryptoros-bench-ros2-insider-"))
    domains = (60, 61)
    try:
        with lab_network(work, POLICY, hosts=HOSTS, master="none", ros2=dict(zip(HOSTS, domains, strict=True)),
                         ros2_python=py, limits={"max_messages_per_second": rate},
                         progress=lambda m: click.echo(f"... {m}")) as net:
            b = net.hosts["robot_b"]
            b_pids = {"interceptor_b": b.proc.pid, **{f"bridge_b ({pid})": pid for pid in children(b.proc.pid)}}
            me = _RobotA(net)

            click.echo(f"... depth attack: transient_local depth 1000, {depth_samples} x {sample_kib} KiB")
            before = {k: _rss_kib(p) for k, p in b_pids.items()}
            sample = fr.encode(fr.DATA, 0, _string_cdr(sample_kib * 1024 - 9))
            with me.stream(b.address, b.public_port, QoS(reliability="reliable", durability="transient_local",
                                                         depth=1000)) as s:
                for _ in range(depth_samples):
                    s.sendall(sample)
                time.sleep(2.0)  # let the bridge republish what it got before RSS is read
                after = {k: _rss_kib(p) for k, p in b_pids.items()}

            click.echo(f"... burst: {burst} frames at once, then 60 at 10 Hz, throttled to {rate:g}/s")
            listener = subprocess.Popen([str(py), "-c", LISTENER, str(burst + 60)], env=_ros_env(domains[1]),
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                        text=True)
            try:
                if listener.stdout.readline().strip() != "READY":
                    raise click.ClickException("the listener on robot B's domain did not start")
                small = fr.encode(fr.DATA, 0, _string_cdr(16))
                probe = fr.encode(fr.DATA, 0, _probe_cdr())
                with me.stream(b.address, b.public_port, QoS()) as s:
                    # robot B republishes on a DDS publisher made when the stream opens: the
                    # burst starts once the listener has matched it (a probe arrived)
                    first = _Lines(listener.stdout)
                    deadline = time.monotonic() + 30
                    while not first.has("FIRST"):
                        if time.monotonic() > deadline:
                            raise click.ClickException("no probe reached the listener on robot B within 30 s")
                        s.sendall(probe)
                        time.sleep(0.1)
                    t0 = time.monotonic()
                    s.sendall(small * burst)
                    for _ in range(60):
                        time.sleep(0.1)
                        s.sendall(small)
                    sent_s = time.monotonic() - t0
                    # the listener ends when all arrived; what has not within 15 s more is not coming
                    with contextlib.suppress(subprocess.TimeoutExpired):
                        listener.wait(timeout=15)
                    listener.stdin.close()
                    answer = (first.next_line(30).split() or ["0", "0"])
                    delivered, span = int(answer[0]), float(answer[1])
            finally:
                listener.kill()
                listener.wait(timeout=10)
    finally:
        shutil.rmtree(work, ignore_errors=True)

    click.echo("")
    click.echo(f"Depth attack on robot B ({depth_samples} x {sample_kib} KiB asked to be kept, depth 1000):")
    click.echo(f"  {'process':<22} {'RSS before':>12} {'RSS after':>12} {'growth':>10}")
    for k in b_pids:
        click.echo(f"  {k:<22} {before[k] / 1024:>9.1f} MB {after[k] / 1024:>9.1f} MB "
                   f"{(after[k] - before[k]) / 1024:>7.1f} MB")
    asked = depth_samples * sample_kib / 1024
    click.echo(f"  (a receiver that kept what the sender asked would hold about {asked:.0f} MB more)")
    click.echo("")
    click.echo(f"Burst of {burst} (bucket {rate:g}/s) then 60 at 10 Hz, {sent_s:.1f} s of sending:")
    click.echo(f"  delivered to robot B's listener: {delivered} of {burst + 60}, first to last in {span:.1f} s "
               f"(at least {burst / rate:.1f} s for the burst at {rate:g}/s, then the 60 at 10 Hz)")
