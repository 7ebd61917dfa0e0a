"""Issue 11: an insider with a valid certificate tries to exhaust or read what it should
not (findings 2, 3, 5, 6), against real rosmaster and rospy behind real interceptors.

The insider is robot B: a valid certificate and token, subscribe grants on /chatter
(including the wildcard node ``*``). Around each attack robot A's ``/flow`` keeps
reaching robot C (tests/ros1_flow.py): never silent 5 s during it, back within 5 s after.
"""

from __future__ import annotations

import contextlib
import os
import socket
import time
import xmlrpc.client
from contextlib import closing

import pytest

from cryptoros.ros1.xmlrpc import Request, make_multicall
from tests.interceptor_harness import (
    NODE,
    SYS_PY,
    denials,
    dribble,
    robot_network,
    rogue_preamble,
    rogue_tcpros,
    rogue_xmlrpc,
    rss_kib,
    separate_hosts,
    token_of,
    wait_registered,
)
from tests.interceptor_harness import open_fds as fds
from tests.interceptor_harness import rogue_to as rogue
from tests.support import running, until
from tests.interceptor_harness import got, read_lines
from tests.ros1_flow import flow_policy, legit_flow

pytestmark = [pytest.mark.ros1]


@pytest.fixture(scope="module")
def network(tmp_path_factory):
    extra = {"master": "[limits]\nmax_relays_per_peer = 64\nmax_nodes_per_peer = 128\n",
             "robot_a": "[limits]\npreamble_timeout = 3.0\nmax_pending_per_certificate = 4\n"}
    with robot_network(tmp_path_factory.mktemp("bounds"), start=("master", "robot_a", "robot_b", "robot_c"),
                       extra=extra, policy=flow_policy(), netns=separate_hosts()) as net:
        yield net


@pytest.fixture(scope="module")
def flow(network):
    """Robot A's /flow to robot C's listener: two honest robots; the insider attacks
    robot A and the master, which that flow goes through."""
    with legit_flow(network, "robot_a", "robot_c") as running_flow:
        yield running_flow

# ---------------------------------------------------------------- finding 2: relay exhaustion
def test_a_relay_is_released_when_its_last_registration_is(network, flow):
    """The master's interceptor holds one relay per registered endpoint; unregistering
    the last registration behind it closes the relay (its fd is freed). The relays are
    counted by ``/status`` (``ros1.relays``): the fds of the process also move with its
    kept-alive connections, which close on their own (a fresh-clone run counted 7 new
    fds for 8 new relays)."""
    import json
    import urllib.request

    token = token_of(network, "robot_b")
    master = network.hosts["master"]
    master_proc = master.proc
    b = network.hosts["robot_b"]

    def relays() -> int:
        with network.inside("master"), urllib.request.urlopen(
                f"http://127.0.0.1:{master.metrics_port}/status", timeout=5) as reply:
            return json.loads(reply.read())["ros1"]["relays"]

    with flow.held(), rogue(network, "master", "robot_b") as s:
        assert rogue_preamble(s, token, "master").ok
        before, relays_before = fds(master_proc.pid), relays()
        uris = [f"cryptoros://{b.address}:{b.public_port}/x/{900000 + i}" for i in range(8)]
        results = [rogue_xmlrpc(s, "registerSubscriber", f"/temp_{i}", "/chatter", "std_msgs/String", uri).value[0]
                   for i, uri in enumerate(uris)]
        opened = results.count(1)
        during = relays() - relays_before
        for i, uri in enumerate(uris):
            if results[i] == 1:
                assert rogue_xmlrpc(s, "unregisterSubscriber", f"/temp_{i}", "/chatter", uri).value[0] == 1
        deadline = time.monotonic() + 5
        while fds(master_proc.pid) > before and time.monotonic() < deadline:
            time.sleep(0.1)
        after = fds(master_proc.pid)
    assert opened == 8 and during == 8
    assert after <= before, (before, after)




def test_fresh_names_from_one_insider_keep_fds_bounded_and_others_registering(network, flow):
    master_proc = network.hosts["master"].proc
    fds_before, rss_before = fds(master_proc.pid), rss_kib(master_proc.pid)
    token = token_of(network, "robot_b")
    b_host, b_port = network.hosts["robot_b"].address, network.hosts["robot_b"].public_port
    with flow.held(), rogue(network, "master", "robot_b") as s:
        assert rogue_preamble(s, token, "master").ok
        # unregister* with never-seen endpoints: no relay is ever opened for them
        for batch in range(10):
            calls = [Request(method="unregisterSubscriber",
                             params=("/spy", "/nothing", f"cryptoros://{b_host}:{b_port}/x/{batch * 256 + i + 100000}"))
                     for i in range(256)]
            reply = rogue_xmlrpc(s, "system.multicall", make_multicall(calls).params[0])
            assert all(r[0][0] == -1 and r[0][1].startswith("denied by cryptoros") for r in reply.value)
        # a multicall over the cap is refused whole
        calls = [Request(method="getPid", params=("/spy",))] * 2500
        reply = rogue_xmlrpc(s, "system.multicall", make_multicall(calls).params[0])
        assert reply.value == [-1, "denied by cryptoros: malformed", 0]  # a ROS error, never a fault
        # register* of fresh names (the wildcard grant allows /chatter for any node of B):
        # each fresh endpoint needs a relay at the master's interceptor, up to its cap
        answers = []
        for i in range(300):
            answers.append(rogue_xmlrpc(s, "registerSubscriber", f"/fresh_{i}", "/chatter", "std_msgs/String",
                                        f"cryptoros://{b_host}:{b_port}/x/{200000 + i}").value[0])
        assert answers.count(1) <= 64 and answers.count(-1) >= 236
    assert fds(master_proc.pid) - fds_before <= 64 + 16
    assert rss_kib(master_proc.pid) - rss_before < 64 * 1024
    log = denials(network, "master")
    assert "unknown_endpoint" in log or "never registered" in log
    assert "max_relays_per_peer" in log
    # another robot's granted registrations still work: robot A's talker and subscriber
    # register and talk (the insider used up only its own quota)
    with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "30"], env=network.ros_env("robot_a")) as pub:
        read_lines(pub, "READY", 20)
        wait_registered(network, "/talker_a")
        with running([SYS_PY, NODE, "sub", "/victim", "/chatter", "30"], env=network.ros_env("robot_a")) as sub:
            read_lines(sub, "READY", 20)
            wait_registered(network, "/victim")
            assert got(read_lines(sub, "GOT", 20))


# ---------------------------------------------------------------- finding 3: preamble slowloris


def test_dribbled_preambles_are_cut_at_the_deadline_and_capped_per_certificate(network, flow):
    """60 connections of the insider's certificate sending one preamble byte a second
    (each read gets its byte in time): all are closed by the preamble's overall
    deadline (3 s here) or refused at once past the per-certificate cap (4 here)."""
    from cryptoros.tunnel import Preamble, encode

    preamble = encode(Preamble(token=token_of(network, "robot_b"), purpose="node", target="1"))
    with flow.held():
        socks = [rogue(network, "robot_a", "robot_b") for _ in range(8)]
        start = time.monotonic()
        try:
            open_ = dribble(socks, preamble, steps=15)
            elapsed = time.monotonic() - start
        finally:
            for s in socks:
                s.close()
    assert not open_, f"{len(open_)} dribbling connections still open after {elapsed:.0f} s"
    log = denials(network, "robot_a")
    assert log.count("4 unauthenticated streams from this certificate already") >= 4
    assert log.count("preamble_timeout") >= 1


def test_a_broken_tls_record_after_the_handshake_is_a_denial_line_not_a_traceback(network, flow):
    """Insider audit: mutual TLS completed with the insider's certificate, then a TLS
    record the interceptor cannot decrypt: every connection logged "Task exception was
    never retrieved" and a 17-line ssl.SSLError traceback (200 connections, 190 of them)."""
    a = network.hosts["robot_a"]
    before = len(a.logs())
    with flow.held():
        for _ in range(5):
            with closing(rogue(network, "robot_a", "robot_b")) as s:
                os.write(s.fileno(), b"\x17\x03\x03\x00\x20" + bytes(32))  # application data, 32 zero bytes
                s.settimeout(5)
                with contextlib.suppress(OSError):
                    s.recv(100)  # until the interceptor closes
    new = until(lambda: a.logs()[before:] if a.logs()[before:].count("SSLError") >= 5 else None, 10,
                "a denial line for each broken record")
    assert "Traceback" not in new and "never retrieved" not in new, new
    assert len([line for line in new.splitlines() if "DENY stream from" in line and "SSLError" in line]) == 5, new


def test_connections_that_never_start_tls_hold_capped_slots_not_descriptors(network, flow):
    """No certificate needed: 200 TCP connections to robot A's public port that never
    send a ClientHello. Each counts against ``max_pending_per_source`` (16) from its
    accept: the rest are closed at once, before any TLS work, so the interceptor's
    descriptors stay bounded; a peer from another address still gets through meanwhile."""
    a = network.hosts["robot_a"]
    with flow.held():
        _silent_connections(network, a)
    assert "16 unauthenticated streams from this source already" in denials(network, "robot_a")


def _silent_connections(network, a) -> None:
    import select

    before = fds(a.proc.pid)
    socks = [socket.create_connection((a.address, a.public_port), timeout=5) for _ in range(200)]
    try:
        closed: set[int] = set()
        deadline = time.monotonic() + 8  # under the 10 s handshake timeout of the 16 let in
        while len(closed) < 200 - 16 and time.monotonic() < deadline:
            readable, _, _ = select.select([s for i, s in enumerate(socks) if i not in closed], [], [], 0.2)
            for s in readable:
                try:
                    data = s.recv(1)
                except OSError:
                    data = b""
                if data == b"":
                    closed.add(socks.index(s))
        assert len(closed) >= 200 - 16, f"only {len(closed)} of 200 silent connections were closed"
        held = fds(a.proc.pid) - before
        assert held <= 16 + 8, f"robot A holds {held} more descriptors with the flood on"
        if separate_hosts():  # the flood's source is capped, not the port: the master still gets in
            with network.inside("master"), rogue(network, "robot_a", "master") as s:
                reply = rogue_preamble(s, token_of(network, "master"), "node", "1")
                assert reply is not None  # TLS done and the preamble answered: not capped
    finally:
        for s in socks:
            s.close()


def test_an_insiders_topic_streams_opened_and_closed_by_the_hundred_leave_other_flows_alone(network, flow):
    """The insider (valid certificate, token, a subscribe grant on /chatter) opens a
    TCPROS stream to robot A's talker through robot A's interceptor, takes the header
    reply and closes it, 150 times as fast as robot A lets it (new streams per second
    are limited per peer), while robot A's /flow to robot C goes on."""
    from tests.interceptor_harness import STRING_MD5

    token = token_of(network, "robot_b")
    with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "60"],
                 env=network.ros_env("robot_a")) as pub:
        read_lines(pub, "READY", 20)
        wait_registered(network, "/talker_a")
        with rogue(network, "master", "robot_b") as s:
            assert rogue_preamble(s, token, "master").ok
            node_api = rogue_xmlrpc(s, "lookupNode", "/spy", "/talker_a").value[2]
        with rogue(network, "robot_a", "robot_b") as s:
            assert rogue_preamble(s, token, "node", node_api.rsplit("/", 1)[1]).ok
            t_host = rogue_xmlrpc(s, "requestTopic", "/rospy_listener", "/chatter", [["TCPROS"]]).value[2][1]
        header = {"callerid": "/rospy_listener", "topic": "/chatter", "type": "std_msgs/String",
                  "md5sum": STRING_MD5, "tcp_nodelay": "1"}
        opened = 0
        with flow.held("150 streams opened and closed"):
            for _ in range(150):
                try:
                    with rogue(network, "robot_a", "robot_b") as s:
                        reply = rogue_preamble(s, token, "topic", t_host.rsplit("/", 1)[1])
                        if reply is not None and reply.ok and rogue_tcpros(s, header).get("md5sum") == STRING_MD5:
                            opened += 1
                except OSError:
                    pass
        assert opened >= 20, f"only {opened} of the insider's streams were opened (the test would test nothing)"
        assert pub.poll() is None


# ---------------------------------------------------------------- finding 5: endpoint leaks


def test_node_api_replies_to_a_peer_name_no_loopback_endpoint(network, flow):
    token = token_of(network, "robot_b")
    with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "30"], env=network.ros_env("robot_a")) as pub:
        read_lines(pub, "READY", 20)
        wait_registered(network, "/talker_a")
        # a subscriber on A: its bus info names the publisher's loopback URI
        with running([SYS_PY, NODE, "sub", "/victim", "/chatter", "30"], env=network.ros_env("robot_a")) as sub:
            read_lines(sub, "READY", 20)
            wait_registered(network, "/victim")
            assert got(read_lines(sub, "GOT", 20))
            with flow.held():
                with rogue(network, "master", "robot_b") as s:
                    assert rogue_preamble(s, token, "master").ok
                    node_api = rogue_xmlrpc(s, "lookupNode", "/spy", "/victim").value[2]
                with rogue(network, "robot_a", "robot_b") as s:
                    assert rogue_preamble(s, token, "node", node_api.rsplit("/", 1)[1]).ok
                    master_uri = rogue_xmlrpc(s, "getMasterUri", "/spy").value
                    bus = rogue_xmlrpc(s, "getBusInfo", "/spy").value
        assert master_uri[0] == 1 and master_uri[2] == "cryptoros://master"
        assert bus[0] == 1 and bus[2], bus
        assert "127.0.0.1" not in repr(bus) and "127.0.0.1" not in repr(master_uri)


# ---------------------------------------------------------------- finding 6: fragile spots


def test_an_oversized_body_is_refused_with_a_ros_error_without_reading_it(network, flow):
    host, port = network.hosts["robot_b"].master_uri[len("http://"):].rstrip("/").split(":")
    with flow.held(), network.inside("robot_b"), closing(socket.create_connection((host, int(port)), timeout=10)) as s:
        s.sendall(b"POST /RPC2 HTTP/1.1\r\nHost: x\r\nContent-Type: text/xml\r\nContent-Length: 104857600\r\n\r\n")
        s.settimeout(10)
        answer = s.recv(65536)
        assert b"200 OK" in answer and b"<int>-1</int>" in answer
        sent = 0
        chunk = b"<" * 65536
        try:
            while sent < 100 << 20:
                sent += s.send(chunk)
        except OSError:
            pass
    assert sent < 16 << 20, f"the interceptor read {sent} bytes of a refused body"


def test_with_its_manager_disabled_the_local_master_answers_ros_errors_not_tracebacks(network, flow):
    with network.inside("robot_b"):
        assert xmlrpc.client.ServerProxy(network.hosts["robot_b"].master_uri).getPid("/probe")[0] == 1
    with flow.held("robot B's manager disabled"):
        _disabled(network)


def _disabled(network) -> None:
    network.cli("disable-manager", "robot_b")
    try:
        deadline = time.monotonic() + 20
        answer = None
        while time.monotonic() < deadline:
            with network.inside("robot_b"):
                answer = xmlrpc.client.ServerProxy(network.hosts["robot_b"].master_uri).registerSubscriber(
                    "/rospy_listener", "/chatter", "std_msgs/String", "http://127.0.0.1:9/")
            if answer[0] == -1:
                break
            time.sleep(0.3)
        assert answer is not None and answer[0] == -1 and answer[1].startswith("denied by cryptoros")
        assert network.hosts["robot_b"].proc.poll() is None
        assert "Traceback" not in network.hosts["robot_b"].logs()
    finally:
        network.cli("enable-manager", "robot_b")

