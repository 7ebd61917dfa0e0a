"""No attack outlives itself on the ROS 2 role: what an insider or a stranger does on
its own streams never stops another peer's flow, during the attack or after it.

Robot A's rclpy talker publishes ``/chatter`` (sequence numbers from 0) to robot B's
listener through the interceptors; an insider, robot C, holds a valid certificate and
a publish grant on ``/chatter`` and floods robot B through its own interceptor (its
sequence numbers from 500000). Robot B throttles each peer to 1,000 messages a second.
Every assertion is on robot A's messages, told apart by content, with bounded waits.
"""

from __future__ import annotations

import contextlib
import signal
import struct
import threading
import time

import pytest

from cryptoros.ros2 import framing as fr
from cryptoros.ros2.target import StreamTarget

from tests.ros2_support import POLICY, Lines, ros2_network

INSIDER = 500_000
#: every legitimate flow is back within this long after an attack ends
BACK_WITHIN = 5.0
#: the insider's flood: 20 s of robot B's per-peer rate
RATE, FLOOD = 1000, 20_000
#: unthrottled, a flood large enough to overrun robot B's listener (Fast DDS wedges it
#: after some 45,000 samples at full speed here)
BIG_FLOOD = 200_000
#: unthrottled, the flood overruns robot B's listener, which Fast DDS wedges: robot B's
#: bridge makes the flooded writer anew after PUBLISH_PATIENCE (3 s), and the reader
#: delivers again (measured: 5.4 s of silence, once per wedge)
DURING_UNTHROTTLED = 8.0

FLOOD_POLICY = POLICY.replace(
    "- name: robot_c\n  fingerprint_sha256: {robot_c}\n",
    "- name: robot_c\n  fingerprint_sha256: {robot_c}\n  grants:\n    publish:\n"
    "    - {{node: /flooder, topic: /chatter, type: std_msgs/msg/String}}\n",
)


@pytest.fixture(scope="module", params=[RATE, None], ids=["throttled", "unthrottled"])
def network(request, tmp_path_factory):
    """Robot C may publish ``/chatter`` and is robot B's peer too. Throttled: robot B lets
    each peer 1,000 messages a second; unthrottled: no limit, so a flood reaches robot B's
    domain as fast as its bridge publishes (the case that overruns a local reader)."""
    rate = request.param
    extra = {"robot_b": f"[limits]\nmax_messages_per_second = {rate}"} if rate else {}
    with ros2_network(tmp_path_factory.mktemp("ros2-aftermath"), policy=FLOOD_POLICY,
                      peers={"robot_c": ("robot_a", "robot_b")}, extra=extra) as net:
        net.flood, net.throttled = (FLOOD, True) if rate else (BIG_FLOOD, False)
        yield net


class Arrivals:
    """A listener's GOT lines, timed as they are read, split by sender."""

    def __init__(self, lines: Lines) -> None:
        self.lines = lines
        self.a: list[tuple[float, int]] = []  # (arrival, seq) of robot A's messages
        self.insider: list[tuple[float, int]] = []
        self.bad: list[str] = []

    def _read(self, timeout: float) -> bool:
        try:
            line = self.lines.queue.get(timeout=timeout)
        except Exception:  # queue.Empty
            return False
        if line is None:
            raise AssertionError("robot B's listener ended")
        if line.startswith("GOT "):
            seq = int(line.split()[1])
            (self.insider if seq >= INSIDER else self.a).append((time.monotonic(), seq))
        elif line.startswith("BAD"):
            self.bad.append(line)
        return True

    def until(self, done, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not done():
            left = deadline - time.monotonic()
            assert left > 0, f"{what} within {timeout} s (robot A: {len(self.a)}, insider: {len(self.insider)})"
            self._read(min(left, 0.2))

    def more_from_a(self, count: int, timeout: float, what: str) -> None:
        target = len(self.a) + count
        self.until(lambda: len(self.a) >= target, timeout, what)

    def a_silence(self, start: float, stop: float | None = None) -> float:
        """The longest silence of robot A's flow from ``start`` to ``stop`` (None: to its
        last message), both ends counted."""
        times = [start] + [t for t, _ in self.a if t > start and (stop is None or t < stop)]
        times += [stop] if stop is not None else []
        return max((b - a for a, b in zip(times, times[1:])), default=float("inf"))


def assert_flow_held(network, seen: Arrivals, start: float, end: float) -> None:
    """Robot A's flow during the attack (``start`` to ``end``) and after it."""
    assert not seen.bad, seen.bad[:3]
    during, after = seen.a_silence(start, end), seen.a_silence(end)
    bound = BACK_WITHIN if network.throttled else DURING_UNTHROTTLED
    print(f"robot A's longest silence: {during:.2f} s during the flood, {after:.2f} s after it")
    assert during < bound, f"robot A's flow was silent for {during:.1f} s during the flood"
    assert after < BACK_WITHIN, f"robot A's flow was silent for {after:.1f} s after the flood"


def test_an_insiders_flood_on_its_own_stream_never_stops_robot_as_flow(network):
    """The attack run's finding: once the insider's flood stream drained and ended,
    robot A's ``/chatter`` stopped reaching robot B for minutes."""
    with network.node("robot_b", "listener.py", "string", "/chatter", "300") as sub:
        sub.until("READY", 20)
        seen = Arrivals(sub)
        with network.node("robot_a", "talker.py", "string", "/chatter", "1000000", "20"):
            seen.more_from_a(10, 40, "robot A's /chatter did not reach robot B before the attack")
            # the flood starts once the insider's path is up (its first message arrived):
            # volatile messages sent before robot C's bridge matched would reach no one
            with network.node("robot_c", "talker.py", "string", "/chatter", str(min(network.flood, 60_000)), "50",
                              "--node", "flooder",
                              "--offset", str(INSIDER), "--keep-all", "--burst-on-signal", "--linger", "25") as flood:
                flood.until("READY", 20)
                seen.until(lambda: seen.insider, 40, "the insider's stream never reached robot B")
                flood.proc.send_signal(signal.SIGUSR1)
                attack_start = time.monotonic()
                seen.more_from_a(20, 20, "robot A's flow stopped during the flood")
                flood.until("DONE", 90)
                published = time.monotonic()
                # the flood ends once its backlog drained (throttled at B): no insider message for 3 s
                seen.until(lambda: time.monotonic() - max(published, seen.insider[-1][0]) > 3, 90,
                           "the insider's flood never ended")
            attack_end = max(published, seen.insider[-1][0])
            seen.more_from_a(100, 60, "robot A's flow did not come back after the flood")
    span = seen.insider[-1][1] - seen.insider[0][1]
    assert span > 1000, f"the flood was too small to test anything (seq {seen.insider[0][1]}..{seen.insider[-1][1]})"
    assert_flow_held(network, seen, attack_start, attack_end)


def _string_sample(seq: int) -> bytes:
    """The CDR of std_msgs/msg/String ``secret-<seq>`` (what the test talker sends)."""
    text = f"secret-{seq}".encode() + b"\x00"
    return b"\x00\x01\x00\x00" + struct.pack("<I", len(text)) + text + b"\x00" * (-len(text) % 4)


def test_an_insiders_flood_on_a_stream_it_opened_itself_never_stops_robot_as_flow(network):
    """The same flood written by the insider straight into its own TLS stream (its valid
    certificate, a token carrying its grant), as fast as robot B reads it, then closed."""
    from tests.interceptor_harness import rogue_preamble, rogue_tls, token_of

    b = network.robots["robot_b"]
    target = StreamTarget(kind="topic", name="/chatter", type="std_msgs/msg/String", node="/flooder").encode()
    with network.node("robot_b", "listener.py", "string", "/chatter", "300") as sub:
        sub.until("READY", 20)
        seen = Arrivals(sub)
        with network.node("robot_a", "talker.py", "string", "/chatter", "1000000", "20"):
            seen.more_from_a(10, 40, "robot A's /chatter did not reach robot B before the attack")
            with rogue_tls(b.address, b.public_port, ca=network.pki.ca_cert,
                           cert=network.pki.pki.cert_path_for("robot_c"),
                           key=network.pki.pki.key_path_for("robot_c")) as s:
                assert rogue_preamble(s, token_of(network, "robot_c"), "ros2", target).ok
                sent = [0]

                def flood() -> None:  # as fast as robot B reads, in writes of 500 messages
                    s.settimeout(None)
                    with contextlib.suppress(OSError):
                        for seq in range(INSIDER, INSIDER + network.flood, 500):
                            s.sendall(b"".join(fr.encode(fr.DATA, 0, _string_sample(seq + i)) for i in range(500)))
                            sent[0] = seq + 500 - INSIDER

                flooder = threading.Thread(target=flood, daemon=True)
                flooder.start()
                seen.until(lambda: seen.insider, 30, "the insider's flood never reached robot B")
                attack_start = time.monotonic()
                seen.more_from_a(60, 30, "robot A's flow stopped during the flood")
                flooder.join(timeout=90)
                assert not flooder.is_alive(), "robot B never read the whole flood"
                written = time.monotonic()
                s.close()  # the flood stream ends (what robot B had not read yet is its backlog)
            seen.until(lambda: time.monotonic() - max(written, seen.insider[-1][0]) > 3, 60,
                       "the insider's flood never ended")
            attack_end = max(written, seen.insider[-1][0])
            seen.more_from_a(100, 60, "robot A's flow did not come back after the flood")
    assert sent[0] == network.flood
    assert_flow_held(network, seen, attack_start, attack_end)
