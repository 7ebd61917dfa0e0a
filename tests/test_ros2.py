"""The interceptor's ROS 2 role with real Jazzy rclpy nodes on separate domains.

Robot A (domain a), robot B (domain b), robot C (domain c), each behind its own
``cryptoros-interceptor`` (role ``ros2``); unmodified rclpy talkers, listeners, a
service server and a client as subprocesses (tests/ros2_nodes). The only way between
domains is the interceptors (see tests/test_ros2_support.py for the policy).
"""

from __future__ import annotations

import pytest

from tests.test_ros2_support import collect, got, ros2_network


@pytest.fixture(scope="module")
def network(tmp_path_factory):
    with ros2_network(tmp_path_factory.mktemp("ros2")) as net:
        yield net


def test_talker_on_a_reaches_listener_on_b_through_the_interceptors(network):
    with network.node("robot_b", "listener.py", "string", "/chatter", "25") as sub:
        sub.until("READY", 20)
        with network.node("robot_a", "talker.py", "string", "/chatter", "100000", "20"):
            lines = collect(sub, 40, 25)
    seqs = got(lines)
    assert not [line for line in lines if line.startswith("BAD")]
    assert seqs == list(range(seqs[0], seqs[0] + 40)), "messages lost or reordered"


def test_topic_not_granted_to_the_sender_never_leaves_robot_a(network):
    with network.node("robot_b", "listener.py", "string", "/secret", "8") as sub:
        sub.until("READY", 20)
        with network.node("robot_a", "talker.py", "string", "/secret", "100000", "20"):
            lines = sub.until(None, 7)
    assert got(lines) == []
    assert "not_granted" in network.robots["robot_a"].denials()
    assert "/secret" in network.robots["robot_a"].denials()


def test_robot_whose_manager_may_not_subscribe_receives_nothing(network):
    with network.node("robot_c", "listener.py", "string", "/chatter", "8") as c_sub, \
            network.node("robot_b", "listener.py", "string", "/chatter", "8") as b_sub:
        c_sub.until("READY", 20)
        b_sub.until("READY", 20)
        with network.node("robot_a", "talker.py", "string", "/chatter", "100000", "20"):
            b_lines = collect(b_sub, 20, 20)
            c_lines = c_sub.until(None, 2)
    assert got(b_lines)
    assert got(c_lines) == []
    assert "robot_c may not subscribe /chatter" in network.robots["robot_a"].denials()
