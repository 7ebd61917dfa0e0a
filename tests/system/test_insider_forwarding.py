"""Issue 20: what an insider with a valid certificate tried by slipping bytes past the
checks, against real rosmaster, rospy and roscpp behind real interceptors.

The insider is robot B (valid certificate, token, subscribe grants only on B's side
of the policy); robot A runs the talkers. Each test reproduces one finding and shows
it no longer gets through, and that the victims (rosmaster, the talker, the stream
between A and B) are unharmed; and around each attack robot A's ``/flow`` keeps
reaching robot C (tests/ros1_flow.py): never silent 5 s during it, back within 5 s after.
"""

from __future__ import annotations

import contextlib
import socket
import struct
import time
import xmlrpc.client
from contextlib import closing
from pathlib import Path

import pytest

from tests.interceptor_harness import (
    NODE,
    SYS_PY,
    denials,
    robot_network,
    rogue_preamble,
    rogue_tcpros,
    rss_kib,
    separate_hosts,
    token_of,
    wait_registered,
)
from tests.interceptor_harness import rogue_to as rogue
from tests.support import require, run, running
from tests.interceptor_harness import got, master_state, nodes_in_state, read_lines
from tests.ros1_flow import flow_policy, legit_flow

pytestmark = [pytest.mark.ros1]

ATTACK_NODES = Path(__file__).parents[1] / "attack_nodes"
ROS1_NODES = Path(__file__).parents[1] / "ros1_nodes"
STRING_MD5 = "992ce8a1687cec8c8bd883ec73ca41d1"
HIDDEN_SETPARAM = (
    b"<methodCall><methodName>setParam</methodName><params><param><value>/spy</value></param>"
    b"<param><value>/robot_a/owned</value></param><param><value>pwned</value></param></params></methodCall>"
)
HIDDEN_SHUTDOWN = (
    b"<methodCall><methodName>shutdown</methodName><params><param><value>/spy</value></param>"
    b"<param><value>bye</value></param></params></methodCall>"
)
GETPID = b"<?xml version='1.0'?><methodCall><methodName>getPid</methodName><params><param><value>/spy</value></param></params></methodCall>"


@pytest.fixture(scope="module")
def network(tmp_path_factory):
    with robot_network(tmp_path_factory.mktemp("insider"), start=("master", "robot_a", "robot_b", "robot_c"),
                       policy=flow_policy(), netns=separate_hosts()) as net:
        yield net


@pytest.fixture(scope="module")
def flow(network):
    """Robot A's /flow to robot C's listener: two honest robots; the insider attacks
    robot A and the master, which that flow goes through."""
    with legit_flow(network, "robot_a", "robot_c") as running_flow:
        yield running_flow


def smuggling(hidden: bytes) -> bytes:
    """A getPid whose request path holds a TAB, a version, bare LFs, a Content-Length,
    a blank line and a second call: Python's http.server runs the second call."""
    path = b"/\tHTTP/1.1\nContent-Length: %d\n\n%s" % (len(hidden), hidden)
    return b"POST " + path + b" HTTP/1.1\r\nHost: x\r\nContent-Length: %d\r\n\r\n" % len(GETPID) + GETPID


def exchange(sock, data: bytes, timeout: float = 10) -> bytes:
    """Send ``data``; everything the other side answers until it closes (or timeout)."""
    sock.settimeout(timeout)
    sock.sendall(data)
    out = b""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            chunk = sock.recv(65536)
        except (socket.timeout, ConnectionError, OSError):
            break
        if not chunk:
            break
        out += chunk
        if b"</methodResponse>" in out:
            break
    return out


def rosmaster_proc(network):
    (proc,) = [p for p in network.procs if any("rosmaster" in str(a) for a in p.args)]
    return proc


def master_alive(network) -> bool:
    with network.inside("master"):
        return rosmaster_proc(network).poll() is None and \
            xmlrpc.client.ServerProxy(network.rosmaster_uri).getPid("/t")[0] == 1






# ---------------------------------------------------------------- finding 1: request-line smuggling


def test_calls_hidden_in_the_request_path_never_reach_rosmaster(network, flow):
    with flow.held():
        _hidden_calls(network)
    assert "control character, bare CR/LF" in denials(network, "master")


def _hidden_calls(network) -> None:
    master = xmlrpc.client.ServerProxy(network.rosmaster_uri)
    host, port = network.hosts["robot_b"].master_uri[len("http://"):].rstrip("/").split(":")
    # through the insider's own interceptor's local master port (plain HTTP on loopback)
    for hidden in (HIDDEN_SETPARAM, HIDDEN_SHUTDOWN):
        with network.inside("robot_b"), closing(socket.create_connection((host, int(port)), timeout=10)) as s:
            answer = exchange(s, smuggling(hidden))
        assert b"<int>-1</int>" in answer and b"denied by cryptoros" in answer, answer[:300]
    # and over a raw TLS master stream with the insider's certificate and token
    for hidden in (HIDDEN_SETPARAM, HIDDEN_SHUTDOWN):
        with rogue(network, "master", "robot_b") as s:
            assert rogue_preamble(s, token_of(network, "robot_b"), "master").ok
            answer = exchange(s, smuggling(hidden))
        assert b"<int>-1</int>" in answer, answer[:300]
    with network.inside("master"):
        assert master.hasParam("/t", "/robot_a/owned") == [1, "/robot_a/owned", False]
    assert master_alive(network), "rosmaster was shut down"


def test_a_shutdown_hidden_in_the_path_to_a_relay_leaves_the_talker_running(network, flow):
    with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "30"],
                 env=network.ros_env("robot_a")) as pub:
        read_lines(pub, "READY", 20)
        wait_registered(network, "/talker_a")
        with flow.held(), network.inside("robot_b"):
            local_master = xmlrpc.client.ServerProxy(network.hosts["robot_b"].master_uri)
            code, _, relay = local_master.lookupNode("/spy", "/talker_a")
            assert code == 1 and relay.startswith("http://127.0.0.1:")
            host, port = relay[len("http://"):].rstrip("/").split(":")
            with closing(socket.create_connection((host, int(port)), timeout=10)) as s:
                answer = exchange(s, smuggling(HIDDEN_SHUTDOWN))
            assert b"<int>-1</int>" in answer
            # the talker answers its API and is still registered
            assert xmlrpc.client.ServerProxy(relay).getPid("/spy")[0] == 1
        assert pub.poll() is None
        assert "/talker_a" in nodes_in_state(master_state(network))
    assert master_alive(network)


# ---------------------------------------------------------------- finding 2: UDPROS redirect


@pytest.fixture(scope="module")
def roscpp_nodes(request, tmp_path_factory):
    """The roscpp talker and UDP-preferring listener, compiled once per run."""
    require("g++", "pkg-config")
    flags = run(["pkg-config", "--cflags", "--libs", "roscpp", "std_msgs"], timeout=10)
    if flags.returncode != 0:
        from tests.support import missing

        missing("roscpp development files are not installed (libroscpp-dev)")
    out = tmp_path_factory.mktemp("roscpp")
    built = {}
    for name in ("talker", "listener_udp"):
        binary = out / name
        run(["g++", "-O1", "-o", str(binary), str(ROS1_NODES / f"{name}.cpp"), *flags.stdout.split()],
            timeout=240, check=True)
        built[name] = str(binary)
    return built


def test_udpros_is_never_offered_and_a_udp_listener_gets_tcpros_through_the_tunnel(network, roscpp_nodes, flow):
    # the stranger listens for datagrams on its own host (127.0.0.9 on a shared loopback)
    stranger_host = network.lab.add_host(f"udp{time.monotonic_ns() % 10000}") if network.lab else None
    stranger_address = stranger_host.address if stranger_host else "127.0.0.9"
    with network.lab.hosts[stranger_host.name].inside() if stranger_host else contextlib.nullcontext():
        stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        stranger.bind((stranger_address, 0))
    stranger.settimeout(0.2)
    udp_port = stranger.getsockname()[1]
    with closing(stranger), running([roscpp_nodes["talker"], "/chatter", "200000"], env=network.ros_env("robot_a")):
        wait_registered(network, "/roscpp_talker", timeout=30)
        token = token_of(network, "robot_b")
        with flow.held("the UDPROS offers"):
            with rogue(network, "master", "robot_b") as s:
                assert rogue_preamble(s, token, "master").ok
                node_api = rogue_xmlrpc_value(s, "lookupNode", "/spy", "/roscpp_talker")
            header = b"callerid=/spy"  # what a UDPROS offer carries, as the attacker wrote it
            with rogue(network, "robot_a", "robot_b") as s:
                assert rogue_preamble(s, token, "node", node_api.rsplit("/", 1)[1]).ok
                udp_only = rogue_xmlrpc_value(s, "requestTopic", "/spy", "/chatter",
                                              [["UDPROS", header, stranger_address, udp_port, 1500]], whole=True)
                both = rogue_xmlrpc_value(s, "requestTopic", "/spy", "/chatter",
                                          [["UDPROS", header, stranger_address, udp_port, 1500], ["TCPROS"]],
                                          whole=True)
        assert udp_only[0] == -1
        assert both[0] == 1 and both[2][0] == "TCPROS" and both[2][1].startswith("cryptoros://")
        # a real roscpp listener that prefers UDP receives over TCPROS, through the interceptors
        with running([roscpp_nodes["listener_udp"], "/chatter", "20"], env=network.ros_env("robot_b")) as sub:
            read_lines(sub, "READY", 30)
            lines = read_lines(sub, "GOT msg", 30)
            assert any(line.startswith("GOT msg") for line in lines)
        datagrams = 0
        deadline = time.monotonic() + 2
        while time.monotonic() < deadline:
            try:
                stranger.recv(65536)
                datagrams += 1
            except socket.timeout:
                pass
        assert datagrams == 0, "the talker sent UDP datagrams to the stranger"
    assert "udpros_refused" in denials(network, "robot_a")


def rogue_xmlrpc_value(sock, method, *params, whole=False):
    from tests.interceptor_harness import rogue_xmlrpc

    value = rogue_xmlrpc(sock, method, *params).value
    return value if whole else value[2]


# ---------------------------------------------------------------- finding 3: header field count


def _bomb_header(count: int) -> bytes:
    fields = [b"a%d=" % i for i in range(count)]
    body = b"".join(struct.pack("<I", len(f)) + f for f in fields)
    return struct.pack("<I", len(body)) + body


def test_headers_of_many_fields_are_refused_and_the_talker_to_listener_stream_keeps_flowing(network, flow):
    with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "50", "60"], env=network.ros_env("robot_a")) as pub:
        read_lines(pub, "READY", 20)
        with running([SYS_PY, NODE, "sub", "/listener_b", "/chatter", "60"], env=network.ros_env("robot_b")) as sub:
            read_lines(sub, "READY", 20)
            assert got(read_lines(sub, "GOT", 20))
            token = token_of(network, "robot_b")
            with rogue(network, "master", "robot_b") as s:
                assert rogue_preamble(s, token, "master").ok
                node_api = rogue_xmlrpc_value(s, "lookupNode", "/spy", "/talker_a")
            with rogue(network, "robot_a", "robot_b") as s:
                assert rogue_preamble(s, token, "node", node_api.rsplit("/", 1)[1]).ok
                t_host = rogue_xmlrpc_value(s, "requestTopic", "/listener_b", "/chatter", [["TCPROS"]])[1]
            a_proc = network.hosts["robot_a"].proc
            rss_before = rss_kib(a_proc.pid)
            with flow.held("the header bombs"):
                socks = []
                for _ in range(16):
                    s = rogue(network, "robot_a", "robot_b")
                    socks.append(s)
                    assert rogue_preamble(s, token, "topic", t_host.rsplit("/", 1)[1]).ok
                    s.sendall(_bomb_header(60_000))
                closed = 0
                for s in socks:
                    s.settimeout(10)
                    try:
                        closed += s.recv(1) == b""
                    except (OSError, ConnectionError):
                        closed += 1
                    s.close()
            assert closed == 16, "a header bomb was not refused"
            # the legitimate stream still delivers, and the interceptor did not balloon
            read_lines(sub, None, 0.5)
            assert got(read_lines(sub, "GOT", 10))
            assert rss_kib(a_proc.pid) - rss_before < 64 * 1024
        assert pub.poll() is None
    assert "more than 32 fields" in denials(network, "robot_a")


def test_a_genuine_header_with_an_extra_field_reaches_the_node_without_it(network, flow):
    with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "30"], env=network.ros_env("robot_a")) as pub:
        read_lines(pub, "READY", 20)
        token = token_of(network, "robot_b")
        with rogue(network, "master", "robot_b") as s:
            assert rogue_preamble(s, token, "master").ok
            node_api = rogue_xmlrpc_value(s, "lookupNode", "/spy", "/talker_a")
        with rogue(network, "robot_a", "robot_b") as s:
            assert rogue_preamble(s, token, "node", node_api.rsplit("/", 1)[1]).ok
            t_host = rogue_xmlrpc_value(s, "requestTopic", "/listener_b", "/chatter", [["TCPROS"]])[1]
        with flow.held(), rogue(network, "robot_a", "robot_b") as s:
            assert rogue_preamble(s, token, "topic", t_host.rsplit("/", 1)[1]).ok
            answer = rogue_tcpros(s, {"callerid": "/listener_b", "topic": "/chatter", "type": "std_msgs/String",
                                      "md5sum": STRING_MD5, "tcp_nodelay": "1", "x_evil": "1"})
        assert answer.get("md5sum") == STRING_MD5 and "x_evil" not in answer
        assert pub.poll() is None


# ---------------------------------------------------------------- finding 4: frame size


def test_a_frame_declaring_2_gib_is_cut_before_it_reaches_the_listener(network, flow):
    """A rogue publisher on robot A (an insider there) declares a 2 GiB frame to robot
    B's listener; robot A's /flow to robot C goes on around it."""
    b_proc = network.hosts["robot_b"].proc
    with running([SYS_PY, NODE, "sub", "/listener_b", "/chatter", "60"], env=network.ros_env("robot_b")) as sub:
        read_lines(sub, "READY", 20)
        rss_before = rss_kib(b_proc.pid)
        with flow.held("the 2 GiB frame"), running([SYS_PY, str(ATTACK_NODES / "big_frame_publisher.py"), "/talker_a", "/chatter",
                      str(2**31), str(32 << 20)], env=network.ros_env("robot_a")) as rogue_pub:
            read_lines(rogue_pub, "CONNECTED", 30)
            ended = read_lines(rogue_pub, None, 30)
            assert any(line.startswith(("CUT", "SENT")) for line in ended), ended
        assert got(read_lines(sub, None, 1)) == []
        assert sub.poll() is None
        assert rss_kib(b_proc.pid) - rss_before < 16 * 1024, "robot B's interceptor buffered the frame"
    assert "message_too_large" in denials(network, "robot_b")
    assert "exceeds max_message_size 16777216" in denials(network, "robot_b")
