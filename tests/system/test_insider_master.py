"""What peers make the master's interceptor and rosmaster hold, against real rosmaster
and rospy behind real interceptors: master calls (a rate per manager), parameters
(keys and bytes per manager), the state file (not rewritten for a repeated
registration), the XML-RPC tunnels to their nodes (closed when idle, and with the relay
they serve).

The insiders have valid certificates and tokens: robot B (subscribe grants on /chatter,
for any node name) and robot C (no grant at all: it may still read the graph). Around
each test's attack robot A's ``/flow`` keeps reaching a listener on robot B
(tests/ros1_flow.py): never silent 5 s during it, back within 5 s after. Robot A is the
only robot here that attacks nothing; the flow's listener is on robot B, an insider whose
other streams must not harm its own honest ones either.
"""

from __future__ import annotations

import json
import socket
import subprocess
import time
import urllib.request
import xmlrpc.client
from pathlib import Path

import pytest

from cryptoros.ros1.xmlrpc import Request, make_multicall
from tests.interceptor_harness import (
    NODE,
    SYS_PY,
    denials,
    got,
    read_lines,
    robot_network,
    rogue_preamble,
    rogue_to,
    rogue_xmlrpc,
    separate_hosts,
    token_of,
    wait_registered,
)
from tests.ros1_flow import flow_policy, legit_flow
from tests.support import running, until

pytestmark = [pytest.mark.ros1]

IDLE = 3.0  # the master's tunnel_idle_timeout here
RATE, BURST = 20.0, 300  # its max_master_calls_per_second and master_call_burst
KEYS, BYTES = 40, 65536  # its max_param_keys_per_peer and max_param_bytes_per_peer


@pytest.fixture(scope="module")
def network(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("master")
    extra = {"master": f'state_dir = "{workdir / "state"}"\n'
                       f"[limits]\ntunnel_idle_timeout = {IDLE}\nspare_connections = false\n"
                       f"max_master_calls_per_second = {RATE}\nmaster_call_burst = {BURST}\n"
                       f"max_param_keys_per_peer = {KEYS}\nmax_param_bytes_per_peer = {BYTES}\n"}
    with robot_network(workdir, start=("master", "robot_a", "robot_b"), extra=extra,
                       policy=flow_policy(listener="robot_b"), netns=separate_hosts()) as net:
        yield net


@pytest.fixture(scope="module")
def flow(network):
    """Robot A's /flow to a listener on robot B (robot C holds no grant here)."""
    with legit_flow(network, "robot_a", "robot_b") as running_flow:
        yield running_flow


def status(network, host: str) -> dict:
    with network.inside(host):
        url = f"http://127.0.0.1:{network.hosts[host].metrics_port}/status"
        with urllib.request.urlopen(url, timeout=5) as reply:
            return json.loads(reply.read())


def saved_after(network, saves: int | None) -> dict:
    """The master's ROS 1 status once no state save is pending (and, given ``saves``,
    more than that many were written): a change is written a moment after it."""
    def settled():
        ros1 = status(network, "master")["ros1"]
        return ros1 if not ros1["state_save_pending"] and (saves is None or ros1["state_saves"] > saves) else None
    return until(settled, 10, "the master's state file written")


def connections_to(network, host: str, peer: str) -> int:
    """TCP connections established from ``host``'s network to ``peer``'s public port
    (the kernel's own table: every tunnel the interceptor there holds open to it)."""
    p = network.hosts[peer]
    want = f"{socket.inet_aton(p.address)[::-1].hex().upper()}:{p.public_port:04X}"
    table = Path(f"/proc/{network.hosts[host].proc.pid}/net/tcp").read_text().splitlines()[1:]
    return sum(1 for line in table if line.split()[2] == want and line.split()[3] == "01")


def metric(network, host: str, name: str) -> float:
    with network.inside(host):
        url = f"http://127.0.0.1:{network.hosts[host].metrics_port}/metrics"
        with urllib.request.urlopen(url, timeout=5) as reply:
            body = reply.read().decode()
    return sum(float(line.rsplit(" ", 1)[1]) for line in body.splitlines() if line.startswith(name))


#: a rospy subscriber that unregisters and exits when told to (a line on stdin)
LISTENER = """
import sys, rospy
from std_msgs.msg import String
rospy.init_node("rospy_listener", disable_signals=True)
rospy.Subscriber("/chatter", String, lambda m: print("GOT", m.data, flush=True))
print("READY", flush=True)
sys.stdin.readline()
rospy.signal_shutdown("asked")
print("END", flush=True)
"""


def test_tunnels_to_a_node_close_when_idle_and_its_pool_goes_with_its_relay(network, flow):
    """rosmaster tells robot B's subscriber of a new publisher through the master's
    interceptor (a relay there, a pooled tunnel to B's interceptor). Idle, the tunnel
    is closed after tunnel_idle_timeout, the pool kept while the node is registered;
    once the node unregisters, its relay is released and the pool with it."""
    before = status(network, "master")["ros1"]
    with flow.held("tunnels opened and closed"), \
            running([SYS_PY, "-c", LISTENER], env=network.ros_env("robot_b"), stdin=subprocess.PIPE) as listener:
        read_lines(listener, "READY", 20)
        wait_registered(network, "/rospy_listener")
        with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "20", "20", "0.5"],
                     env=network.ros_env("robot_a")) as talker:
            read_lines(talker, "READY", 20)
            assert got(read_lines(listener, "GOT", 20))  # publisherUpdate went through the pool
            read_lines(talker, "SENT", 20)
            talker.wait(20)  # it unregistered: rosmaster told the listener again, through the pool
        held = status(network, "master")["ros1"]
        assert held["tunnel_pools"] > before["tunnel_pools"]
        # idle: closed by this side after tunnel_idle_timeout (the peer would wait 600 s)
        until(lambda: status(network, "master")["ros1"]["tunnels_closed_idle"] > before["tunnels_closed_idle"],
              IDLE + 15, "an idle tunnel closed")
        until(lambda: connections_to(network, "master", "robot_b") == 0
              and status(network, "master")["ros1"]["idle_tunnels"] == 0, IDLE + 15, "every idle tunnel closed")
        # the pool stays while the node is registered
        assert status(network, "master")["ros1"]["tunnel_pools"] == held["tunnel_pools"]
        assert listener.poll() is None
        listener.stdin.write("stop\n")
        listener.stdin.flush()
        read_lines(listener, "END", 20)
        listener.wait(20)
        # unregistered: the relay of its node API is released, and its pool closed with it
        until(lambda: status(network, "master")["ros1"]["tunnel_pools"] == before["tunnel_pools"], 15,
              "the pool dropped with its relay")
    after = status(network, "master")["ros1"]
    assert after["relays"] <= before["relays"] and after["idle_tunnels"] == 0
    assert connections_to(network, "master", "robot_b") == 0


def test_a_flood_of_master_calls_is_rate_limited_and_another_manager_still_registers(network, flow):
    """Robot C floods the master with multicalls of getPid (allowed to anyone): past the
    burst its calls are refused (rate_limited: a ROS error each, counted, logged once a
    while), and robot A's nodes still register and talk."""
    refused_metric = 'cryptoros_interceptor_denied_total{kind="master",reason="rate_limited"}'
    before = metric(network, "master", refused_metric)
    calls = [Request(method="getPid", params=("/flood",))] * 256
    answers = []
    with flow.held("robot C's flood of master calls"), rogue_to(network, "master", "robot_c") as s:
        assert rogue_preamble(s, token_of(network, "robot_c"), "master").ok
        started = time.monotonic()
        for _ in range(4):
            answers += rogue_xmlrpc(s, "system.multicall", make_multicall(calls).params[0]).value
        elapsed = time.monotonic() - started
    allowed = sum(1 for a in answers if isinstance(a, list) and a[0][0] == 1)
    refused = [a for a in answers if isinstance(a, list) and a[0][0] == -1]
    assert allowed + len(refused) == 1024
    assert allowed <= BURST + RATE * elapsed + 1, (allowed, elapsed)
    assert refused and refused[0] == [[-1, "denied by cryptoros: rate_limited", 0]]
    assert metric(network, "master", refused_metric) - before == len(refused)
    log = denials(network, "master")
    assert "rate_limited" in log and log.count("rate_limited") < len(refused)  # not one line per call
    # robot A's nodes: not robot C's budget
    with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "30"], env=network.ros_env("robot_a")) as pub:
        read_lines(pub, "READY", 20)
        wait_registered(network, "/talker_a")
        with running([SYS_PY, NODE, "sub", "/victim", "/chatter", "30"], env=network.ros_env("robot_a")) as sub:
            read_lines(sub, "READY", 20)
            assert got(read_lines(sub, "GOT", 20))


def test_an_insider_flooding_its_private_namespace_is_stopped_at_its_quota(network, flow):
    """Robot B needs no parameter grant to write under its nodes' names: 100 fresh keys
    are refused past max_param_keys_per_peer (rosmaster holds no more), deleteParam
    frees the quota, a value past max_param_bytes_per_peer is refused, and so are
    parameter subscriptions past the quota."""
    b = network.hosts["robot_b"]
    with flow.held("robot B's parameter flood"), rogue_to(network, "master", "robot_b") as s:
        assert rogue_preamble(s, token_of(network, "robot_b"), "master").ok
        answers = [rogue_xmlrpc(s, "setParam", "/rospy_listener", f"~flood/k{i}", "x" * 100) for i in range(100)]
        stored = [a for a in answers if a.value[0] == 1]
        refused = [a for a in answers if a.value[0] == -1]  # a ROS error, never a fault
        assert len(stored) + len(refused) == 100
        assert refused and refused[0].value == [-1, "denied by cryptoros: param_quota", 0]
        with network.inside("master"):
            held = xmlrpc.client.ServerProxy(network.rosmaster_uri).getParam("/operator", "/rospy_listener/flood")
        assert held[0] == 1 and len(held[2]) == len(stored)
        assert 2 + len(stored) <= KEYS  # with the namespaces /rospy_listener and flood: what rosmaster holds
        assert status(network, "master")["ros1"]["param_usage"]["robot_b"][0] <= KEYS
        # deleteParam frees it; then one big value fits and a second is past the bytes
        assert rogue_xmlrpc(s, "deleteParam", "/rospy_listener", "~flood").value[0] == 1
        assert rogue_xmlrpc(s, "setParam", "/rospy_listener", "~blob1", "y" * 40000).value[0] == 1
        assert rogue_xmlrpc(s, "setParam", "/rospy_listener", "~blob2", "y" * 40000).value[0] == -1
        assert rogue_xmlrpc(s, "deleteParam", "/rospy_listener", "~blob1").value[0] == 1
        # parameter subscriptions: rosmaster keeps each too
        api = f"cryptoros://{b.address}:{b.public_port}/x/970001"
        # (a node robot B names exactly: one covered only by "*" has no private namespace to watch)
        subscribed = [rogue_xmlrpc(s, "subscribeParam", "/rospy_client", api, f"~watch/k{i}").value[0] for i in range(60)]
        assert subscribed.count(1) <= KEYS and subscribed.count(-1) >= 60 - KEYS
    with network.inside("master"):
        assert xmlrpc.client.ServerProxy(network.rosmaster_uri).hasParam("/operator", "/rospy_listener/blob2")[2] is False
    assert denials(network, "master").count("param_quota") >= len(refused)


def test_a_repeated_registration_changes_nothing_and_rewrites_no_state_file(network, flow):
    """rosmaster keeps one registration per node and topic: the same registerSubscriber
    50 times over writes the master's state file once, and one unregisterSubscriber
    releases it (its relay too)."""
    b = network.hosts["robot_b"]
    state = network.workdir / "state" / "master.state.json"
    api = f"cryptoros://{b.address}:{b.public_port}/x/980001"
    call = ("registerSubscriber", "/repeat_listener", "/chatter", "std_msgs/String", api)
    before = status(network, "master")["ros1"]
    with flow.held("robot B's repeated registrations"), rogue_to(network, "master", "robot_b") as s:
        assert rogue_preamble(s, token_of(network, "robot_b"), "master").ok
        assert rogue_xmlrpc(s, *call).value[0] == 1
        first = saved_after(network, before["state_saves"])
        written = state.stat()
        assert first["relays"] == before["relays"] + 1
        assert all(rogue_xmlrpc(s, *call).value[0] == 1 for _ in range(50))
        assert rogue_xmlrpc(s, "getPid", "/repeat_listener").value[0] == 1
        repeated = saved_after(network, None)
        assert repeated["state_saves"] == first["state_saves"]
        assert (state.stat().st_mtime_ns, state.stat().st_ino) == (written.st_mtime_ns, written.st_ino)
        # one unregister undoes the one registration rosmaster kept: node and relay released
        assert rogue_xmlrpc(s, "unregisterSubscriber", "/repeat_listener", "/chatter", api).value[0] == 1
        after = saved_after(network, repeated["state_saves"])
    assert after["relays"] == before["relays"]
    assert "/repeat_listener" not in json.loads(state.read_text())["owners"]


def test_an_insiders_parameter_reads_on_many_streams_at_once_leave_nothing_held(network, flow):
    """Insider audit: robot B read back 13.5 MB of its nodes' parameters on 120 streams at
    once; the master's interceptor grew to 4.8 GB and kept it while the streams stayed
    open, and robot A's master calls waited 20 s. A peer now has at most
    PARAM_READS_PER_PEER parameter reads under way, each until its answer is written
    out in slices, and a stream keeps nothing of an answer once written: 16 reads of
    5.4 MB here held about 180 MB before, and the master's interceptor grows by a few
    answers' worth now."""
    import contextlib

    from cryptoros.ros1.xmlrpc import NEED_DATA, Role, XmlRpcConnection
    from tests.interceptor_harness import rss_kib

    value = "v" * 900_000
    with network.inside("master"):  # put there by the operator: past robot B's quota, still its to read
        master = xmlrpc.client.ServerProxy(network.rosmaster_uri)
        for i in range(6):
            assert master.setParam("/operator", f"/rospy_listener/big/k{i}", value)[0] == 1
    pid = network.hosts["master"].proc.pid
    before = rss_kib(pid)
    token = token_of(network, "robot_b")
    with flow.held("robot B's parameter reads"), contextlib.ExitStack() as stack:
        streams, conns = [], []
        for _ in range(16):  # one after the other: at most max_pending_per_certificate unverified
            s = stack.enter_context(rogue_to(network, "master", "robot_b"))
            assert rogue_preamble(s, token, "master").ok
            streams.append(s)
            conn = XmlRpcConnection(Role.CLIENT)
            s.sendall(conn.send(Request(method="getParam", params=("/rospy_listener", "/rospy_listener/big"))))
            conns.append(conn)
        for s, conn in zip(streams, conns):  # answers read one stream after the other
            s.settimeout(30)
            while (event := conn.next_event()) is NEED_DATA:
                conn.receive_data(s.recv(1 << 20))
            assert event.value[0] == 1 and len(event.value[2]) == 6, str(event.value)[:200]
        held_mib = (rss_kib(pid) - before) / 1024  # the streams still open
    assert held_mib < 120, f"the master's interceptor holds {held_mib:.0f} MiB more after 16 answers of 5.4 MB"
    # insider re-audit: one multicall of such reads kept every answer for its reply (256
    # reads of 13.5 MB: 13.5 GB); its answers together now stop at 64 MiB: 30 reads of
    # 5.4 MB, the first dozen answered, the rest refused
    calls = [{"methodName": "getParam", "params": ["/rospy_listener", "/rospy_listener/big"]}] * 30
    with rogue_to(network, "master", "robot_b") as s:
        assert rogue_preamble(s, token, "master").ok
        s.settimeout(60)
        conn = XmlRpcConnection(Role.CLIENT, max_body_size=256 << 20)
        s.sendall(conn.send(Request(method="system.multicall", params=(calls,))))
        while (event := conn.next_event()) is NEED_DATA:
            conn.receive_data(s.recv(1 << 20))
        answers = event.value
    assert len(answers) == 30 and len(answers[0][0][2]) == 6, str(answers)[:300]
    refused = [a for a in answers if isinstance(a, list) and a and a[0] == [-1, "denied by cryptoros: answer_too_large", 0]]
    assert 10 <= 30 - len(refused) <= 14 and refused, [str(a)[:80] for a in answers]
    with network.inside("master"):
        assert master.deleteParam("/operator", "/rospy_listener/big")[0] == 1
