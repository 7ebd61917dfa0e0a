"""The interceptor's ROS 2 role with real Jazzy rclpy nodes on separate domains.

Robot A (domain a), robot B (domain b), robot C (domain c), each behind its own
``cryptoros-interceptor`` (role ``ros2``); unmodified rclpy talkers, listeners, a
service server and a client as subprocesses (tests/ros2_nodes). The only way between
domains is the interceptors (see tests/test_ros2_support.py for the policy).
"""

from __future__ import annotations

import time

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


@pytest.mark.parametrize("kind", ["twist", "scan", "image"])
def test_message_types_arrive_intact_and_in_order(network, kind):
    topic = {"twist": "/twist", "scan": "/scan", "image": "/image"}[kind]
    with network.node("robot_b", "listener.py", kind, topic, "25") as sub:
        sub.until("READY", 20)
        with network.node("robot_a", "talker.py", kind, topic, "100000", "20"):
            lines = collect(sub, 30, 25)
    seqs = got(lines)
    assert not [line for line in lines if line.startswith("BAD")], "a message arrived altered"
    assert seqs == list(range(seqs[0], seqs[0] + 30)), "messages lost or reordered"


def test_service_call_across_robots(network):
    with network.node("robot_a", "server.py", "/set_flag", "flag_server") as server:
        server.until("READY", 20)
        with network.node("robot_b", "client.py", "/set_flag", "3", "25") as client:
            lines = client.until("RESULT True flag set to True by flag_server", 30)[-1:]
            lines += client.until("RESULT True flag set to False by flag_server", 10)[-1:]
        calls = server.until(None, 0.5)
    assert lines == ["RESULT True flag set to True by flag_server", "RESULT True flag set to False by flag_server"]
    assert "CALLED True" in calls or calls == []  # the server printed its calls (some may already be read)


def test_latched_message_reaches_a_late_subscriber_with_transient_local(network):
    with network.node("robot_a", "talker.py", "string", "/latched", "1", "10", "--latched"):
        time.sleep(4)  # robot A's interceptor finds the topic and forwards the one message
        with network.node("robot_b", "listener.py", "string", "/latched", "10", "--latched") as sub:
            lines = sub.until("GOT 0", 12)
    assert got(lines) == [0]


def test_two_robots_bridging_the_same_topic_do_not_loop(network):
    with network.node("robot_a", "listener.py", "string", "/both", "30", "--node", "watcher") as a_sub:
        a_sub.until("READY", 20)
        with network.node("robot_a", "talker.py", "string", "/both", "100000", "20"), \
                network.node("robot_b", "talker.py", "string", "/both", "100000", "20", "--node", "talker_b",
                             "--offset", "1000000"):
            deadline = time.monotonic() + 25
            lines: list[str] = []
            while time.monotonic() < deadline:
                lines += a_sub.until(None, 1)
                seqs = got(lines)
                if sum(s >= 1000000 for s in seqs) >= 30:
                    break
            lines += a_sub.until(None, 2)
    seqs = got(lines)
    remote = [s for s in seqs if s >= 1000000]
    local = [s for s in seqs if s < 1000000]
    assert len(remote) >= 30, "robot B's messages did not reach robot A"
    assert local, "robot A's own talker was not heard"
    duplicates = sorted({s for s in seqs if seqs.count(s) > 1})
    assert duplicates == [], f"messages came back around the loop: {duplicates[:10]}"
