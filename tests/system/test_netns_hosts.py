"""Real separate hosts. Each host (the master's, robot A's, robot
B's, a stranger's) in its own Linux network namespace with its own loopback, on one
bridge, as robots on a LAN: a node's ports are private to its host, and a stranger
reaches nothing but the interceptors' public ports.

Needs root (CI runs as root and requires it); without root it skips and says why.
"""

from __future__ import annotations

import socket
import subprocess
import time
import xmlrpc.client

import pytest

from cryptoros.lab.netns import NetnsLab
from tests.interceptor_harness import NODE, SYS_PY, robot_network, separate_hosts
from tests.support import running
from tests.interceptor_harness import got, read_lines
from tests.ros1_flow import flow_policy, legit_flow

pytestmark = [pytest.mark.ros1]


@pytest.fixture(scope="module")
def network(tmp_path_factory):
    separate_hosts()
    with robot_network(tmp_path_factory.mktemp("netns"), start=("master", "robot_a", "robot_b", "robot_c"),
                       policy=flow_policy(), netns=True) as net:
        yield net


@pytest.fixture(scope="module")
def flow(network):
    """Robot A's /flow to robot C's listener, held around what the stranger and the
    insider (robot B) do (tests/ros1_flow.py)."""
    with legit_flow(network, "robot_a", "robot_c") as running_flow:
        yield running_flow


def test_the_lab_isolates_loopbacks_and_cleans_up():
    separate_hosts()
    with NetnsLab() as lab:
        a, s = lab.add_host("a"), lab.add_host("s")
        with a.inside():
            private = socket.create_server(("127.0.0.1", 0))
            public = socket.create_server((a.address, 0))
            socket.create_connection(private.getsockname(), timeout=2).close()  # a reaches itself
        with s.inside():
            with pytest.raises(OSError):
                socket.create_connection(private.getsockname(), timeout=2)
            socket.create_connection(public.getsockname(), timeout=2).close()
        private.close()
        public.close()
        names = [a.ns, s.ns]
    listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, timeout=10).stdout
    assert not any(name in listed for name in names)


def test_a_lab_left_behind_with_the_same_subnet_does_not_take_a_new_labs_route():
    """A killed run can leave a bridge holding 10.77.N.1/24; a new lab whose name hashes
    to the same N must pick another (the kernel would route the new hosts' replies to the
    old bridge: timeouts, the failure fresh run 1 of this round saw)."""
    import uuid

    from cryptoros.lab import netns

    separate_hosts()
    with NetnsLab() as stale:
        netns._SUBNETS_IN_USE.discard(stale.subnet_index)  # as if another process had made it
        try:
            same = next(p for p in (f"crq{i:04x}" for i in range(65536))
                        if 20 + int(uuid.uuid5(uuid.NAMESPACE_DNS, p).hex[:4], 16) % 200 == stale.subnet_index)
            with NetnsLab(prefix=same) as fresh:
                assert fresh.subnet_index != stale.subnet_index
                a = fresh.add_host("a")
                server = socket.create_server((fresh.gateway, 0))
                with a.inside():
                    socket.create_connection(server.getsockname(), timeout=2).close()  # reaches its gateway
                server.close()
        finally:
            netns._SUBNETS_IN_USE.add(stale.subnet_index)


def master_state_ns(network) -> list:
    with network.inside("master"):
        return xmlrpc.client.ServerProxy(network.rosmaster_uri).getSystemState("/test")[2]


def wait_registered(network, node, timeout=20):
    deadline = time.monotonic() + timeout
    while not any(node in nodes for _topic, nodes in master_state_ns(network)[0]):
        assert time.monotonic() < deadline, f"{node} never registered"
        time.sleep(0.1)


def test_talker_and_listener_on_separate_hosts_and_a_stranger_reaches_only_public_ports(network, flow):
    with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "40"], env=network.ros_env("robot_a")) as pub:
        read_lines(pub, "READY", 20)
        wait_registered(network, "/talker_a")
        with running([SYS_PY, NODE, "sub", "/rospy_listener", "/chatter", "30"], env=network.ros_env("robot_b")) as sub:
            read_lines(sub, "READY", 20)
            assert got(read_lines(sub, "GOT", 20)), "no message crossed the hosts"
        # the talker's own ports, as robot A's local master knows them
        a = network.hosts["robot_a"]
        with network.inside("robot_a"):
            api = xmlrpc.client.ServerProxy(a.master_uri).lookupNode("/probe", "/talker_a")[2]
            tcpros = xmlrpc.client.ServerProxy(api).requestTopic("/probe", "/chatter", [["TCPROS"]])[2]
        api_port = int(api.rstrip("/").rsplit(":", 1)[1])
        private = {
            "talker XML-RPC": api_port,
            "talker TCPROS": tcpros[2],
            "local master": a.local_master_port,
            "metrics": a.metrics_port,
        }
        stranger = network.lab.add_host("stranger")
        with flow.held("the stranger's probes"), stranger.inside():
            for what, port in private.items():
                for address in (a.address, "127.0.0.1"):
                    with pytest.raises(OSError):
                        socket.create_connection((address, port), timeout=2).close()
            m = network.hosts["master"]
            rosmaster_port = int(network.rosmaster_uri.rstrip("/").rsplit(":", 1)[1])
            for address in (m.address, "127.0.0.1"):
                with pytest.raises(OSError):
                    socket.create_connection((address, rosmaster_port), timeout=2).close()
            for name in ("master", "robot_a", "robot_b"):  # the public ports answer TCP
                h = network.hosts[name]
                socket.create_connection((h.address, h.public_port), timeout=5).close()
        assert pub.poll() is None


def test_denials_hold_across_hosts(network, flow):
    """A subscriber without a grant receives nothing; shutdown through a relay is dropped."""
    with running([SYS_PY, NODE, "pub", "/talker_a", "/secret", "100000", "20", "40"], env=network.ros_env("robot_a")) as pub:
        read_lines(pub, "READY", 20)
        wait_registered(network, "/talker_a")
        with flow.held("robot B's ungranted subscriber"), \
                running([SYS_PY, NODE, "sub", "/listener_b", "/secret", "30"], env=network.ros_env("robot_b")) as sub:
            read_lines(sub, "READY", 20)
            assert got(read_lines(sub, None, 3)) == []
        with flow.held("robot B's shutdown calls"), network.inside("robot_b"):
            local = xmlrpc.client.ServerProxy(network.hosts["robot_b"].master_uri)
            relay = local.lookupNode("/evil", "/talker_a")[2]
            assert xmlrpc.client.ServerProxy(relay).shutdown("/evil", "bye")[0] == -1
            assert local.shutdown("/evil", "bye")[0] == -1
        assert pub.poll() is None
    assert "may not subscribe /secret" in network.hosts["robot_b"].logs()
