"""Strangers on the robots' network hold connections that never finish TLS: they fill an
interceptor's pending slots (``max_pending_streams`` in all, from accept), yet a robot
that already streamed to it still opens new streams, and the refusals are logged per
source address, aggregated. Real interceptors, rosmaster and rospy nodes."""

from __future__ import annotations

import contextlib
import socket

import pytest

from tests.interceptor_harness import (
    NODE,
    SYS_PY,
    denials,
    got,
    read_lines,
    robot_network,
    rogue_preamble,
    rogue_to,
    separate_hosts,
    token_of,
)
from tests.support import running, stop

pytestmark = [pytest.mark.ros1]

#: robot A's caps here: all its pending slots fit in what one stranger address may hold
PENDING_IN_ALL = 8


def test_strangers_filling_the_pending_slots_do_not_lock_a_known_robot_out(tmp_path):
    # strangers hold their slots for the whole test (handshake_timeout), not 10 s
    # robot B keeps no spare connection ready: its new stream needs a new accept at robot A
    extra = {"robot_a": f"[limits]\nmax_pending_streams = {PENDING_IN_ALL}\nmax_pending_per_source = 16\n"
                        "handshake_timeout = 120.0\n",
             "robot_b": "[limits]\nspare_connections = false\n"}
    with robot_network(tmp_path, start=("master", "robot_a", "robot_b"), extra=extra,
                       netns=separate_hosts()) as net:
        a = net.hosts["robot_a"]
        with _robot_b_known_to_robot_a(net, 90) as first:
            held = []
            try:
                for _ in range(PENDING_IN_ALL + 4):  # from the test's own address: a stranger to robot A
                    held.append(_hold(a))
                stranger = held[0].getsockname()[0]
                # robot A is full for strangers: each one over the cap takes the oldest one's place
                closed = _closed_once_decided(held, 4)
                assert closed == [True] * 4 + [False] * PENDING_IN_ALL, closed
                # a new subscriber on robot B: a new TCPROS stream from a robot A knows
                with running([SYS_PY, NODE, "sub", "/victim", "/chatter", "60"], env=net.ros_env("robot_b")) as second:
                    assert got(read_lines(second, "GOT", 30)), "robot B's new stream was locked out by strangers"
            finally:
                for sock in held:
                    sock.close()
            # Robot A's interceptor restarted (robot B holding no stream to it): it still knows
            # robot B's address (its state_dir). A stranger's audit: a restarted interceptor
            # knew no source, and strangers' idle connections kept every robot out of it.
            stop(first)
            net.stop("robot_a")
            net.start("robot_a")
            held = [_hold(a) for _ in range(PENDING_IN_ALL + 4)]
            try:
                with running([SYS_PY, NODE, "sub", "/after_restart", "/chatter", "60"],
                             env=net.ros_env("robot_b")) as third:
                    assert got(read_lines(third, "GOT", 40)), "robot B was locked out of robot A's restarted interceptor"
                # a robot that never streamed to robot A (robot C's certificate, from the strangers'
                # address, which robot A does not know) takes the oldest stranger's place and gets in
                assert _closed_once_decided(held, 4) == [True] * 4 + [False] * PENDING_IN_ALL
                with rogue_to(net, "robot_a", "robot_c") as s:
                    reply = rogue_preamble(s, token_of(net, "robot_c"), "refresh")
                assert reply is not None and reply.ok, reply
                assert _closed_once_decided(held, 5) == [True] * 5 + [False] * (PENDING_IN_ALL - 1)
            finally:
                for sock in held:
                    sock.close()
        log = denials(net, "robot_a")
        lines = [line for line in log.splitlines() if f"DENY tls from {stranger}:" in line]
        assert lines and all("pending_limit" in line or "unauthenticated streams" in line for line in lines), log[-2000:]
        assert len(lines) <= 2, lines  # four refusals, aggregated: one line at once, then a count per interval


def test_a_stranger_whose_handshakes_keep_failing_is_closed_at_accept_and_robots_stream_on(tmp_path):
    """Stranger audit: full TLS handshakes without a client certificate, 640 a second, took
    half of robot A's interceptor (a key exchange and a signature each) and its relayed
    messages' p50 from 0.4 to 5-10 ms. Past FAILED_HANDSHAKE_BURST failures (and their
    rate) the stranger's address is closed at accept, before any TLS, for SHUN_SECONDS,
    while a robot robot A knows opens new streams."""
    from interceptor.admission import FAILED_HANDSHAKE_BURST

    with robot_network(tmp_path, start=("master", "robot_a", "robot_b"), netns=separate_hosts()) as net:
        a = net.hosts["robot_a"]
        with _robot_b_known_to_robot_a(net, 60):
            outcomes = [_handshake_without_certificate(a) for _ in range(FAILED_HANDSHAKE_BURST + 5)]
            # the first ones reach TLS and are refused there; the last are closed before a ServerHello
            assert outcomes[0] == "refused in TLS" and outcomes[-1] == "closed at accept", outcomes
            with running([SYS_PY, NODE, "sub", "/victim", "/chatter", "60"], env=net.ros_env("robot_b")) as second:
                assert got(read_lines(second, "GOT", 30)), "robot B's new stream was refused with the stranger"
        log = denials(net, "robot_a")
        assert "handshake_failures" in log, log[-2000:]


def _handshake_without_certificate(host) -> str:
    """A stranger's TLS 1.3 handshake with ``host``'s public port, no client certificate:
    "refused in TLS" (the client's part done, the server's alert after) or "closed at
    accept" (no ServerHello: the handshake itself fails)."""
    import ssl

    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.check_hostname, ctx.verify_mode = False, ssl.CERT_NONE
    ctx.minimum_version = ssl.TLSVersion.TLSv1_3
    with ctx.wrap_socket(_hold(host), server_hostname="robot", do_handshake_on_connect=False) as tls:
        try:
            tls.do_handshake()
        except OSError:
            return "closed at accept"
        with contextlib.suppress(OSError):
            tls.recv(1)  # the server's alert: certificate required
    return "refused in TLS"


@contextlib.contextmanager
def _robot_b_known_to_robot_a(net, seconds: int):
    """Robot A's talker and robot B's first subscriber, running ``seconds``, once a message
    went through: robot B's address is a known source to robot A. Yields the subscriber."""
    with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", str(seconds)],
                 env=net.ros_env("robot_a")) as pub, \
            running([SYS_PY, NODE, "sub", "/rospy_listener", "/chatter", str(seconds)],
                    env=net.ros_env("robot_b")) as first:
        read_lines(pub, "READY", 20)
        assert got(read_lines(first, "GOT", 30)), "robot B's first subscriber got nothing"
        yield first


def _hold(host) -> socket.socket:
    """A connection to ``host``'s public port that never starts TLS (a stranger's)."""
    sock = socket.socket()
    if not separate_hosts():
        sock.bind(("127.0.0.99", 0))
    sock.settimeout(5)
    sock.connect((host.address, host.public_port))
    return sock


def _closed_once_decided(socks: list[socket.socket], expected: int, within: float = 10.0) -> list[bool]:
    """Which of ``socks`` robot A closed, read once ``expected`` of them are (bounded)."""
    import select
    import time

    closed = [False] * len(socks)
    deadline = time.monotonic() + within
    while sum(closed) < expected and time.monotonic() < deadline:
        readable, _, _ = select.select([s for s, c in zip(socks, closed) if not c], [], [], 0.1)
        for sock in readable:
            try:
                gone = sock.recv(1) == b""
            except OSError:
                gone = True
            closed[socks.index(sock)] = closed[socks.index(sock)] or gone
    return closed
