"""No attack outlives itself on the ROS 2 role: what an insider or a stranger does on
its own streams never stops another peer's flow, during the attack or after it.

Robot A's rclpy talker publishes ``/chatter`` (sequence numbers from 0) to robot B's
listener through the interceptors; an insider, robot C, holds a valid certificate and
a publish grant on ``/chatter`` and floods robot B through its own interceptor (its
sequence numbers from 500000). Robot B holds each peer to a message rate
(``[limits] max_messages_per_second``, on by default) of :data:`RATE` a second: the
default's mechanism at a level any flood exceeds (at the default 5,000 a second, an
insider's flood relayed by a busy two-core machine once arrived slower than the rate, and
nothing was held back to show). Every assertion is on robot A's messages, told apart by
content, with bounded waits.
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

from tests.ros2_support import BACK_WITHIN, INSIDER, POLICY, Arrivals, assert_flow_held, flow_around, ros2_network

#: robot B's per-peer message rate in this module (robot A's flow is 20 a second)
RATE = 1000
#: the insider's flood: 20 s of robot B's per-peer budget
DEFAULT_FLOOD = 20 * RATE
#: with no rate (``max_messages_per_second = 0``) a flood overruns robot B's listener, which
#: Fast DDS wedges: 0.8 to 12.5 s of silence on a quiet machine, over 20 s during and over
#: 60 s after the flood in loaded suite runs. No bound is claimed without a rate
#: (docs/ros2.md), so no test asserts one; the rate is on by default.

FLOOD_POLICY = POLICY.replace(
    "- name: robot_c\n  fingerprint_sha256: {robot_c}\n",
    "- name: robot_c\n  fingerprint_sha256: {robot_c}\n  grants:\n    publish:\n"
    "    - {{node: /flooder, topic: /chatter, type: std_msgs/msg/String}}\n",
)


@pytest.fixture(scope="module")
def network(tmp_path_factory):
    """Robot C may publish ``/chatter`` and is robot B's peer too; robot B holds each peer
    to :data:`RATE` messages a second."""
    with ros2_network(tmp_path_factory.mktemp("ros2-aftermath"), policy=FLOOD_POLICY,
                      peers={"robot_c": ("robot_a", "robot_b")},
                      extra={"robot_b": f"[limits]\nmax_messages_per_second = {RATE}"}) as net:
        net.flood = DEFAULT_FLOOD
        yield net


def test_an_insiders_flood_on_its_own_stream_never_stops_robot_as_flow(network):
    """The attack run's finding: once the insider's flood stream drained and ended,
    robot A's ``/chatter`` stopped reaching robot B for minutes."""
    _flood_through_the_insiders_interceptor(network)


def _flood_through_the_insiders_interceptor(network) -> None:
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
            seen.more_from_a(100, 60, "robot A's flow did not come back after the flood", since=attack_end)
    span = seen.insider[-1][1] - seen.insider[0][1]
    assert span > 1000, f"the flood was too small to test anything (seq {seen.insider[0][1]}..{seen.insider[-1][1]})"
    assert_flow_held(seen, attack_start, attack_end, during_bound=_during(network))
    _held_back_only_the_insider(network)


def _during(network) -> float:
    """How long robot A's flow may be silent during the attack (the rate holds it)."""
    return BACK_WITHIN


def _held_back_only_the_insider(network) -> None:
    """Robot B's status (``cryptoros status``'s JSON) says whose streams its rate held
    back: the insider's, never robot A's 20 Hz flow."""
    import json
    import urllib.request

    url = f"http://127.0.0.1:{network.robots['robot_b'].metrics_port}/status"
    with urllib.request.urlopen(url, timeout=5) as reply:
        status = json.loads(reply.read())
    assert status["message_rate"] and "robot_c" in status["throttled"] and "robot_a" not in status["throttled"], \
        (status["message_rate"], status["throttled"])


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
            seen.more_from_a(100, 60, "robot A's flow did not come back after the flood", since=attack_end)
    assert sent[0] == network.flood
    assert_flow_held(seen, attack_start, attack_end, during_bound=_during(network))
    _held_back_only_the_insider(network)


def test_a_strangers_half_open_connections_never_stop_robot_as_flow(network):
    """A stranger (no certificate) holds 200 TCP connections to robot B's public port
    that never finish the TLS handshake, for 10 s, then drops them."""
    import socket

    b = network.robots["robot_b"]

    def attack(seen: Arrivals) -> None:
        held = []
        try:
            for _ in range(200):
                with contextlib.suppress(OSError):
                    held.append(socket.create_connection((b.address, b.public_port), timeout=2))
            seen.more_from_a(100, 30, "robot A's flow stopped while the stranger held connections")
            assert held, "the stranger could not connect at all (the test would test nothing)"
        finally:
            for s in held:
                s.close()

    flow_around(network, attack, during_bound=_during(network))


def test_an_insiders_streams_opened_and_closed_by_the_hundred_never_stop_robot_as_flow(network):
    """The insider (valid certificate, token and grant) opens a ``/chatter`` stream to
    robot B, sends a sample and closes it, 150 times as fast as robot B lets it."""
    from tests.interceptor_harness import rogue_preamble, rogue_tls, token_of

    b = network.robots["robot_b"]
    token = token_of(network, "robot_c")
    target = StreamTarget(kind="topic", name="/chatter", type="std_msgs/msg/String", node="/flooder").encode()

    def attack(seen: Arrivals) -> None:
        opened = 0
        for i in range(150):
            with contextlib.suppress(OSError), rogue_tls(b.address, b.public_port, ca=network.pki.ca_cert,
                                                         cert=network.pki.pki.cert_path_for("robot_c"),
                                                         key=network.pki.pki.key_path_for("robot_c")) as s:
                reply = rogue_preamble(s, token, "ros2", target)
                if reply is not None and reply.ok:
                    opened += 1
                    s.sendall(fr.encode(fr.DATA, 0, _string_sample(INSIDER + i)))
        assert opened >= 20, f"only {opened} of the insider's streams were opened (the test would test nothing)"

    flow_around(network, attack, during_bound=_during(network))
