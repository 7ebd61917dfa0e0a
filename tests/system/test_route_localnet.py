"""Loopback that other hosts reach: ``net.ipv4.conf.*.route_localnet=1`` (kube-proxy and
Docker with ``--userland-proxy=false`` set it) makes the kernel accept packets for
127.0.0.0/8 from the network, so a stranger who routes 127.0.0.1 through a robot's LAN
address reaches every loopback port of that robot, bound where the socket tables say
it is private. On separate hosts (a network namespace per host, the sysctl set in the
robot's namespace only), as an attacker would act:

- robot A's interceptor refuses every call to its local master (the stranger's
  ``getSystemState`` and ``registerPublisher`` with no certificate, a node of the
  robot's own ``registerPublisher``) with one line naming the sysctl and the command
  that fixes it, and ``cryptoros status`` warns; ``all`` alone does the same (the
  kernel takes ``all`` OR the interface); set back to 0, the robot serves again;
- the master's interceptor refuses its rosmaster (``exposed_master``) the same way;
- a ROS 2 robot's interceptor carries nothing, either way, while it lasts.

Needs root (CI runs as root); without root it skips and says why.
"""

from __future__ import annotations

import contextlib
import time
import xmlrpc.client

import pytest

from cryptoros.lab.network import tool
from tests.interceptor_harness import (
    NODE,
    SYS_PY,
    reaches,
    read_lines,
    robot_network,
    run_on,
    separate_hosts,
    status_text,
)
from tests.support import running, until

pytestmark = [pytest.mark.ros1]


def _add_stranger(net) -> None:
    """A host of no robot on the LAN, known to ``net.argv`` and ``net.inside``."""
    net.add_host("stranger")




def _route_localnet(net, host: str, conf: str, value: int) -> None:
    """``sysctl -w net.ipv4.conf.<conf>.route_localnet=<value>`` in ``host``'s namespace only."""
    result = run_on(net, host, ["sysctl", "-w", f"net.ipv4.conf.{conf}.route_localnet={value}"])
    assert result.returncode == 0, result


def _route_loopback_through(net, host: str, gateway: str) -> None:
    """The stranger's own host: 127.0.0.0/8 sent to ``gateway`` on the LAN (a rule before
    the local table's, and its own route_localnet so its kernel lets such packets out)."""
    script = ("ip rule add pref 100 lookup local && ip rule del pref 0 && "
              "ip rule add pref 10 to 127.0.0.0/8 lookup 77 && "
              f"ip route add 127.0.0.0/8 via {gateway} dev eth0 table 77 && "
              "sysctl -qw net.ipv4.conf.eth0.route_localnet=1")
    result = run_on(net, host, ["sh", "-c", script])
    assert result.returncode == 0, result




def _call(net, host: str, port: int, method: str, *params) -> list:
    assert host in net.ns_hosts, f"{host} is no namespace host"
    with net.inside(host):
        return getattr(xmlrpc.client.ServerProxy(f"http://127.0.0.1:{port}/"), method)(*params)


def _refused(net, host: str, port: int, needle: str, timeout: float = 10) -> str:
    """The error of the local master at ``port`` to ``host``'s ``getSystemState`` once
    it is refused naming ``needle`` (the interceptor reads the sysctls at most once a
    second)."""
    deadline = time.monotonic() + timeout
    while True:
        with contextlib.suppress(OSError):
            code, message, _ = _call(net, host, port, "getSystemState", "/stranger")
            if code != 1 and needle in message:
                return message
        assert time.monotonic() < deadline, f"getSystemState from {host} not refused naming {needle!r} in {timeout} s"
        time.sleep(0.2)


def _served(net, host: str, port: int, timeout: float = 10) -> None:
    deadline = time.monotonic() + timeout
    while True:
        with contextlib.suppress(OSError):
            if _call(net, host, port, "getSystemState", "/probe")[0] == 1:
                return
        assert time.monotonic() < deadline, f"getSystemState from {host} not served in {timeout} s"
        time.sleep(0.2)




def test_a_robot_whose_loopback_other_hosts_reach_refuses_its_local_master_and_names_the_sysctl(tmp_path):
    separate_hosts()
    with robot_network(tmp_path, start=("master", "robot_a", "robot_b"), netns=True) as net:
        _add_stranger(net)
        robot = net.hosts["robot_a"]
        port = robot.local_master_port
        _route_loopback_through(net, "stranger", robot.address)
        assert not reaches(net, "stranger", "127.0.0.1", port)  # route_localnet=0: the robot's loopback is its own
        assert _call(net, "robot_a", port, "getSystemState", "/probe")[0] == 1
        # a relay robot A opened for robot B's talker (its node API, as robot A's nodes are handed it)
        net.cli("grant", "robot_b", "publish", "/talker_b", "/chatter", "std_msgs/String")
        talker_b = running([SYS_PY, NODE, "pub", "/talker_b", "/chatter", "100000", "20", "120"],
                           env=net.ros_env("robot_b"))
        read_lines(talker_b.__enter__(), "READY", 30)
        relay_port = int(_call(net, "robot_a", port, "lookupNode", "/probe", "/talker_b")[2].rstrip("/").rsplit(":", 1)[1])
        until(lambda: _call(net, "robot_a", relay_port, "getPid", "/probe")[0] == 1, 15,
              "robot B's talker answering through robot A's relay")

        _route_localnet(net, "robot_a", "eth0", 1)
        assert reaches(net, "stranger", "127.0.0.1", port)  # what the check is about
        fix = "sysctl -w net.ipv4.conf.eth0.route_localnet=0"
        # the stranger, with no certificate, at the robot's local master
        message = _refused(net, "stranger", port, "exposed_endpoint")
        assert "net.ipv4.conf.eth0.route_localnet=1" in message, message
        assert fix in message and "\n" not in message
        code, message, _ = _call(net, "stranger", port, "registerPublisher", "/evil", "/chatter", "std_msgs/String",
                                 "http://127.0.0.1:1/")
        assert code != 1 and "route_localnet" in message, message
        # nor does a relay serve it: the stranger would call robot B's talker as robot A
        with pytest.raises((OSError, xmlrpc.client.ProtocolError)):
            _call(net, "stranger", relay_port, "getPid", "/stranger")
        talker_b.__exit__(None, None, None)
        # a node of the robot's own: its registration refused with the same line
        with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100", "20", "5"],
                     env=net.ros_env("robot_a")) as pub:
            lines = read_lines(pub, "exposed_endpoint", 30)
        assert "net.ipv4.conf.eth0.route_localnet=1" in lines[-1] and fix in lines[-1], lines
        assert "DENY local-master from local node: exposed_endpoint" in robot.logs()
        status = status_text(net, "robot_a")
        assert "warning   this host's loopback answers other hosts: net.ipv4.conf.eth0.route_localnet=1" in status, \
            status
        # unhealthy (status exits 1, /healthz 503), and a start or --check refuses the host in one line
        assert run_on(net, "robot_a", [tool("cryptoros"), "status", "--config", str(robot.config)]).returncode == 1
        check = run_on(net, "robot_a", [tool("cryptoros-interceptor"), "--config", str(robot.config), "--check"])
        lines = check.stderr.strip().splitlines()
        assert check.returncode == 1 and len(lines) == 1 and "route_localnet=1" in lines[0], check

        # all alone opens every interface (the kernel takes all OR the interface's)
        _route_localnet(net, "robot_a", "eth0", 0)
        _route_localnet(net, "robot_a", "all", 1)
        assert reaches(net, "stranger", "127.0.0.1", port)
        message = _refused(net, "stranger", port, "net.ipv4.conf.all.route_localnet=1")
        assert "sysctl -w net.ipv4.conf.all.route_localnet=0" in message, message

        # fixed: the stranger no longer reaches it, the robot's nodes are served, no warning
        _route_localnet(net, "robot_a", "all", 0)
        assert not reaches(net, "stranger", "127.0.0.1", port)
        _served(net, "robot_a", port)
        assert "route_localnet" not in status_text(net, "robot_a")


def test_the_masters_interceptor_refuses_a_rosmaster_on_a_loopback_other_hosts_reach(tmp_path):
    separate_hosts()
    with robot_network(tmp_path, start=("master", "robot_a"), netns=True) as net:
        master = net.hosts["master"]
        _add_stranger(net)
        port = int(net.rosmaster_uri.rstrip("/").rsplit(":", 1)[1])
        _route_loopback_through(net, "stranger", master.address)
        _route_localnet(net, "master", "eth0", 1)
        assert reaches(net, "stranger", "127.0.0.1", port)  # rosmaster, bound to 127.0.0.1 only

        deadline = time.monotonic() + 15
        while "master streams refused (exposed_master)" not in master.logs():
            assert time.monotonic() < deadline, master.logs()
            time.sleep(0.1)
        refusal = master.logs().split("master streams refused (exposed_master)", 1)[1].splitlines()[0]
        assert "net.ipv4.conf.eth0.route_localnet=1" in refusal, refusal
        assert "sysctl -w net.ipv4.conf.eth0.route_localnet=0" in refusal, refusal
        status = status_text(net, "master")
        assert "warning   master streams refused (exposed_master)" in status and "route_localnet" in status, status
        # start-up and --check refuse it too: exit 1, one line
        check = run_on(net, "master", [tool("cryptoros-interceptor"), "--config", str(master.config), "--check"])
        lines = check.stderr.strip().splitlines()
        assert check.returncode == 1 and len(lines) == 1 and "route_localnet=1" in lines[0], check

        _route_localnet(net, "master", "eth0", 0)
        deadline = time.monotonic() + 15
        while "answers on loopback only now" not in master.logs():
            assert time.monotonic() < deadline, master.logs()
            time.sleep(0.1)


def test_a_ros2_robot_whose_loopback_other_hosts_reach_carries_nothing_until_it_does_not(tmp_path):
    """The ros2 role: the robot's DDS domain is on its loopback, which route_localnet
    opens to strangers (its samples read, samples injected as its nodes'). The sysctl set
    while robot A runs: robot A stops offering its topics and taking peers' streams,
    ``cryptoros status`` says why (exit 1); set back, robot B's listener receives again."""
    import subprocess

    from cryptoros.lab.network import lab_network
    from cryptoros.lab.policy import policy_yaml
    from tests.ros2_support import NODES, STRING2, fresh_domains, ros2_env, ros2_python

    separate_hosts()
    python = ros2_python()
    domains = dict(zip(("robot_a", "robot_b"), fresh_domains(2), strict=True))
    policy = policy_yaml({"robot_a": {"publish": [("/talker", "/chatter", STRING2)]},
                          "robot_b": {"subscribe": [("/listener", "/chatter", STRING2)]}})
    hosts = {"robot_a": "127.0.0.2", "robot_b": "127.0.0.3"}
    with lab_network(tmp_path, policy, hosts=hosts, master="none", metrics=True, ros2=domains, ros2_python=python,
                     netns=True, log_level="info") as net:
        def node(host: str, *args: str) -> subprocess.Popen:
            env = {**ros2_env(domains[host]), "PYTHONUNBUFFERED": "1"}
            return subprocess.Popen(net.argv(host, [str(python), *args]), env=env, cwd=str(NODES),
                                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

        talker = node("robot_a", "talker.py", "string", "/chatter", "100000", "20")
        listener = node("robot_b", "listener.py", "string", "/chatter", "150")
        try:
            read_lines(listener, "GOT", 60)  # flowing
            _route_localnet(net, "robot_a", "eth0", 1)
            robot = net.hosts["robot_a"]
            until(lambda: "no longer offering topic /chatter" in robot.logs()
                  and "this host's loopback answers other hosts" in robot.logs(), 20,
                  "robot A withdrawing /chatter once its loopback answers other hosts")
            status = run_on(net, "robot_a", [tool("cryptoros"), "status", "--config", str(robot.config)])
            assert status.returncode == 1 and "exposed_endpoint" in status.stdout, status
            assert "net.ipv4.conf.eth0.route_localnet=1" in status.stdout, status.stdout
            _route_localnet(net, "robot_a", "eth0", 0)
            until(lambda: run_on(net, "robot_a", [tool("cryptoros"), "status", "--config",
                                                  str(robot.config)]).returncode == 0, 20, "robot A healthy again")
            read_lines(listener, None, 0.2)  # what it printed before
            read_lines(listener, "GOT", 60)  # and the flow is back
        finally:
            for proc in (talker, listener):
                proc.terminate()
                with contextlib.suppress(subprocess.TimeoutExpired):
                    proc.wait(timeout=10)
