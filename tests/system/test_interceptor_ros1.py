"""The interceptor with real, unmodified ROS 1 nodes (Debian rospy, roscpp, rostopic, rosnode).

Hosts on loopback: the master's interceptor on 127.0.0.4 in front of a real rosmaster,
robot A on 127.0.0.2, robot B on 127.0.0.3, robot C (a manager with no grants) on
127.0.0.5, and a real cryptoros-authz daemon. Nodes only get ROS_MASTER_URI pointing at
their host's interceptor; their code is unchanged.
"""

from __future__ import annotations

import subprocess
import time

import pytest

from tests.interceptor_harness import NODE, NODES, SYS_PY, robot_network, separate_hosts
from tests.interceptor_harness import got, master_state, nodes_in_state, read_lines
from tests.support import on_host, require, running

pytestmark = [pytest.mark.ros1]


@pytest.fixture(scope="module")
def network(tmp_path_factory):
    with robot_network(tmp_path_factory.mktemp("net"), start=("master", "robot_a", "robot_b", "robot_c"),
                       netns=separate_hosts()) as net:
        yield net


def start_sub(network, host, node, topic="/chatter", seconds=30):
    return running([SYS_PY, NODE, "sub", node, topic, str(seconds)], env=network.ros_env(host))


def start_pub(network, host, node, count, hz=0, linger=2, topic="/chatter"):
    return running([SYS_PY, NODE, "pub", node, topic, str(count), str(hz), str(linger)], env=network.ros_env(host))


# ------------------------------------------------------------------ works


def test_rospy_talker_on_a_reaches_rospy_listener_on_b(network):
    with running([SYS_PY, str(NODES / "listener.py"), "/chatter", "10"], env=network.ros_env("robot_b")) as listener:
        read_lines(listener, "READY", 20)
        with running([SYS_PY, str(NODES / "talker.py"), "/chatter", "10"], env=network.ros_env("robot_a")) as talker:
            lines = read_lines(listener, "DONE", 40)
            read_lines(talker, "SENT 10", 10)
    received = [line.split()[1:4] for line in lines if line.startswith("GOT")]
    assert [f"{a} {b}" for a, b, _ in received] == [f"msg {i}" for i in range(10)]
    assert {md5 for *_, md5 in received} == {"992ce8a1687cec8c8bd883ec73ca41d1"}


def test_roscpp_talker_through_interceptors(network, roscpp_talker):  # noqa: F811
    with start_sub(network, "robot_b", "/listener_cpp") as listener:
        read_lines(listener, "READY", 20)
        with running([roscpp_talker, "/chatter", "50"], env=network.ros_env("robot_a")) as talker:
            read_lines(talker, "SENT 50", 40)
            lines = read_lines(listener, "GOT msg 49", 20)
    assert got(lines) == [f"msg {i}" for i in range(50)]


def test_rostopic_echo_list_and_rosnode_list_through_interceptors(network):
    rostopic, rosnode = require("rostopic", "rosnode").values()
    env_b = network.ros_env("robot_b")
    with start_pub(network, "robot_a", "/talker_a", 400, hz=20, linger=1):
        echo = subprocess.run(on_host([rostopic, "echo", "-n", "3", "/chatter"], env_b), env=env_b,
                              capture_output=True, text=True, timeout=40)
        assert echo.returncode == 0, echo.stderr
        assert echo.stdout.count("data: \"secret-") == 3
        topics = subprocess.run(on_host([rostopic, "list"], env_b), env=env_b, capture_output=True, text=True,
                                timeout=20)
        assert "/chatter" in topics.stdout.split()
        nodes = subprocess.run(on_host([rosnode, "list"], env_b), env=env_b, capture_output=True, text=True,
                               timeout=20)
        assert "/talker_a" in nodes.stdout.split()


def test_rospy_service_call_across_hosts(network):
    services = str(NODES / "services.py")
    with running([SYS_PY, services, "serve"], env=network.ros_env("robot_a")) as server:
        read_lines(server, "READY", 20)
        with running([SYS_PY, services, "call", "/rospy_loggers"], env=network.ros_env("robot_b")) as client:
            lines = read_lines(client, "LOGGERS", 30)
    assert "rospy.server=debug,x=warn" in lines[-1]


def test_sigterm_lets_a_call_under_way_finish_and_cuts_topic_streams_at_once(network):
    """SIGTERM to robot A's interceptor while a service call is in flight through it and a
    topic stream flows: the call gets its reply within the grace period (5 s), and the
    interceptor exits as soon as the call is done, without waiting the grace out for the
    topic stream, which never ends by itself."""
    import signal

    services = str(NODES / "services.py")
    host = network.hosts["robot_a"]
    try:
        with running([SYS_PY, services, "serve", "1.5"], env=network.ros_env("robot_a")) as server, \
                start_sub(network, "robot_b", "/listener_b") as sub:
            read_lines(server, "READY", 20)
            read_lines(sub, "READY", 20)
            with start_pub(network, "robot_a", "/talker_a", 100000, hz=20):
                read_lines(sub, "GOT secret-", 30)  # the topic stream is up
                with running([SYS_PY, services, "call", "/rospy_loggers"], env=network.ros_env("robot_b")) as client:
                    read_lines(server, "CALLED", 30)
                    signalled = time.monotonic()
                    host.proc.send_signal(signal.SIGTERM)
                    assert host.proc.wait(timeout=15) == 0
                    took = time.monotonic() - signalled
                    lines = read_lines(client, "LOGGERS", 10)
        assert "rospy.server=debug,x=warn" in lines[-1]  # the call under way was answered
        assert took < 4.5, f"the interceptor waited {took:.1f} s: the grace period went to the topic stream"
    finally:
        network.start("robot_a")


def test_nodes_shut_down_cleanly_and_the_master_is_empty_after(network):
    with start_sub(network, "robot_b", "/listener_b", seconds=4) as sub:
        read_lines(sub, "READY", 20)
        with start_pub(network, "robot_a", "/talker_a", 5, hz=10, linger=0.5) as pub:
            assert pub.wait(timeout=30) == 0
        lines = read_lines(sub, "END", 30)
        assert sub.wait(timeout=10) == 0
    assert got(lines) == [f"secret-{i}" for i in range(5)]
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and {"/talker_a", "/listener_b"} & nodes_in_state(master_state(network)):
        time.sleep(0.1)
    assert not {"/talker_a", "/listener_b"} & nodes_in_state(master_state(network))


def test_one_process_serves_master_and_node_roles(tmp_path):
    """The master host's interceptor also fronts a talker on the master host."""
    from tests.interceptor_harness import DEFAULT_POLICY

    policy = DEFAULT_POLICY.replace(
        "- name: master\n  fingerprint_sha256: {master}\n",
        "- name: master\n  fingerprint_sha256: {master}\n  grants:\n    publish:\n"
        "    - {{node: /talker_m, topic: /chatter, type: std_msgs/String}}\n",
    )
    with robot_network(tmp_path, policy=policy, roles={"master": ["master", "node"]}) as net:
        assert net.hosts["master"].proc.poll() is None
        with start_sub(net, "robot_b", "/listener_b") as sub:
            read_lines(sub, "READY", 20)
            with running([SYS_PY, NODE, "pub", "/talker_m", "/chatter", "5", "20", "1"], env=net.ros_env("master")):
                lines = read_lines(sub, "GOT secret-4", 30)
        assert got(lines) == [f"secret-{i}" for i in range(5)]
