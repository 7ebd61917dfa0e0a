"""What stock ROS 1 tools and libraries meet behind an interceptor, decided without a
network: refusals as ROS error triples, unreadable parameters answered as unset, the
measured default-readable parameters, the endpoints libraries serve under a node's own
name, node patterns, and denials aggregated for the log."""

from __future__ import annotations

import time

import pytest

from cryptoros.errors import PolicyDenied
from cryptoros.names import validate_node_name
from cryptoros.policy.infrastructure import ROS1_DEFAULT_PARAM_READS, ros1_allows, ros1_topic_param
from cryptoros.policy.hints import TOOL_NODES
from cryptoros.policy.ros1 import (
    OWN_TOKEN_REASONS,
    SEE_DENIALS,
    SHARED_TOOL_NAMES,
    SHOWN_REASONS,
    check_local_subscriber_header,
    check_master_call,
    check_publisher_header,
    check_service_client_header,
    check_service_server_header,
    check_subscriber_header,
    filter_param_reply,
    may_read_param,
    may_write_param,
    node_pattern,
    refusal_answer,
    refusal_text,
    refused_reason,
)
from cryptoros.grants import Grant, Grants, node_matches
from interceptor.denials import DenialTable
from tests.support import require, run

ROBOT = Grants([
    Grant(node="/talker", action="publish", name="/chatter", type="std_msgs/String"),
    Grant(node="/action_server", action="publish", name="/move_base/status", type="actionlib_msgs/GoalStatusArray"),
    Grant(node="/camera", action="publish", name="/image_raw", type="sensor_msgs/Image"),
    Grant(node="/roslaunch", action="write_param", name="/run_id", type="param"),
])


def master(method, *params, grants=ROBOT):
    check_master_call(method, params, manager="robot_b", grants=grants, owners={})


def refused(method, *params, grants=ROBOT) -> str:
    with pytest.raises(PolicyDenied) as info:
        master(method, *params, grants=grants)
    return info.value.reason


# ------------------------------------------------------------------ answers
def test_a_refusal_is_a_ros_error_triple_with_its_reason_code():
    assert refusal_answer("param_write_denied", "setParam", ("/n", "/x", 1)) == \
        [-1, "denied by cryptoros: param_write_denied", 0]
    assert refusal_answer("shutdown_dropped", "shutdown", ("/rosnode", "user request")) == \
        [-1, "denied by cryptoros: shutdown_dropped", 0]
    assert refusal_answer("not_granted", "registerPublisher", ("/n", "/t", "T", "http://x:1/"))[0] == -1


def test_a_reason_outside_the_shown_list_is_not_told():
    assert refusal_text("some_internal_reason") == "denied by cryptoros"
    assert refusal_text(None) == "denied by cryptoros"


@pytest.mark.parametrize("reason", sorted(OWN_TOKEN_REASONS))
def test_why_our_own_token_cannot_be_used_is_told_to_our_own_nodes_and_tools_only(reason):
    """A robot without a token (its manager removed, its certificate revoked...): its own
    tools say why; a peer calling in learns nothing of our token."""
    assert refusal_text(reason, own=True) == f"denied by cryptoros: {reason}"
    assert refusal_answer(reason, "getSystemState", ("/rosnode",), own=True) == \
        [-1, f"denied by cryptoros: {reason}", 0]
    assert refusal_text(reason) == "denied by cryptoros"
    assert refusal_answer(reason, "getSystemState", ("/rosnode",)) == [-1, "denied by cryptoros", 0]
    assert reason not in SHOWN_REASONS


@pytest.mark.parametrize("method, params, answer", [
    ("hasParam", ("/action_server", "/secret"), [1, "/secret", False]),
    ("hasParam", ("/ns/node", "rel"), [1, "/ns/rel", False]),  # resolved as rosmaster resolves it
    ("getParam", ("/n", "/secret"), [-1, "Parameter [/secret] is not set", 0]),
    ("searchParam", ("/n", "secret"), [-1, "Cannot find parameter [secret] in an upwards search", ""]),
    ("subscribeParam", ("/n", "http://127.0.0.1:1/", "/secret"), [1, "Subscribed to parameter [/secret]", {}]),
])
def test_a_probe_of_an_unreadable_parameter_is_answered_as_unset(method, params, answer):
    assert refusal_answer("param_read_denied", method, params) == answer


def test_a_found_but_unreadable_search_result_is_not_found():
    reply = filter_param_reply("searchParam", ("/talker", "secret"), [1, "Found [/secret]", "/secret"], grants=ROBOT)
    assert reply == [-1, "Cannot find parameter [secret] in an upwards search", ""]


# ------------------------------------------------------------------ default reads
@pytest.mark.parametrize("key", ["/use_sim_time", "/rosout_disable_topics_generation", "/tcp_keepalive",
                                 "/enable_statistics", "/statistics_window_max_size", "/run_id",
                                 "/actionlib_server_pub_queue_size", "/actionlib_client_sub_queue_size"])
def test_what_the_libraries_read_is_readable_by_any_own_node(key):
    assert key in ROS1_DEFAULT_PARAM_READS
    assert may_read_param(ROBOT, "/talker", key)
    master("getParam", "/talker", key)
    master("hasParam", "/talker", key)


def test_a_default_readable_parameter_is_not_writable():
    assert not may_write_param(ROBOT, "/talker", "/use_sim_time")
    assert refused("setParam", "/talker", "/use_sim_time", True) == "param_write_denied"


def test_an_action_servers_and_an_image_publishers_own_topic_parameters_are_readable():
    assert ros1_topic_param("/move_base/status_frequency") == ("/move_base/status", "status_frequency")
    assert may_read_param(ROBOT, "/action_server", "/move_base/status_frequency")
    assert may_read_param(ROBOT, "/action_server", "/move_base/status_list_timeout")
    assert may_read_param(ROBOT, "/camera", "/image_raw/disable_pub_plugins")
    # not by a node that does not publish that topic
    assert not may_read_param(ROBOT, "/talker", "/move_base/status_frequency")
    assert not may_read_param(ROBOT, "/talker", "/image_raw/disable_pub_plugins")


def test_the_private_namespace_of_a_node_the_manager_names_exactly_is_its_own():
    # roslaunch (caller /roslaunch) sets a launched node's <param>; a nodelet manager reads its nodelet's
    assert may_write_param(ROBOT, "/roslaunch", "/talker/rate")
    assert may_read_param(ROBOT, "/camera", "/talker/rate")
    # not a node of another manager, and not for a caller the manager's grants do not name
    assert not may_write_param(ROBOT, "/roslaunch", "/other_robots_node/rate")
    assert not may_write_param(ROBOT, "/stranger", "/talker/rate")


def test_the_names_every_robots_tools_use_have_no_private_namespace_and_cannot_be_registered():
    """/roslaunch and /rosservice are in every robot's tool bundle: naming them exactly
    gives no node their namespace (robot A's /roslaunch/uris/* were written by any node
    of robot B), and no node may register under them (robot B's /roslaunch locked every
    other robot's roslaunch out of the master)."""
    bundle = Grants([*ROBOT, Grant(node="/rosservice", action="call", name="/add", type="srv/Add"),
                     Grant(node="/rosparam-*", action="read_param", name="/robot_b", type="param")])
    for node in ("/talker", "/camera", "/rosparam-42", "/roslaunch", "/rosservice"):
        for key in ("/roslaunch/uris/host_10_0_0_1__41000", "/rosservice/x"):
            assert not may_write_param(bundle, node, key), (node, key)
            assert not may_read_param(bundle, node, key), (node, key)
    # the write_param grant of grant-tools --roslaunch opens /roslaunch to roslaunch
    launch = Grants([*bundle, Grant(node="/roslaunch", action="write_param", name="/roslaunch", type="param")])
    assert may_write_param(launch, "/roslaunch", "/roslaunch/uris/host_10_0_0_1__41000")
    assert not may_write_param(launch, "/talker", "/roslaunch/uris/host_10_0_0_1__41000")
    for method, params in (("registerSubscriber", ("/roslaunch", "/chatter", "std_msgs/String", "http://h:1/")),
                           ("registerPublisher", ("/rosservice", "/chatter", "std_msgs/String", "http://h:1/")),
                           ("registerService", ("/roslaunch", "/add", "rosrpc://h:2", "http://h:1/")),
                           ("subscribeParam", ("/roslaunch", "http://h:1/", "/run_id"))):
        with pytest.raises(PolicyDenied) as info:
            check_master_call(method, params, manager="robot_b", grants=launch, owners={})
        assert info.value.reason == "name_taken" and "every robot" in info.value.detail, method
    # roslaunch's own calls go on
    check_master_call("getParam", ("/roslaunch", "/run_id"), manager="robot_b", grants=launch, owners={})
    check_master_call("setParam", ("/roslaunch", "/roslaunch/uris/host_a__1", "http://a:1/"), manager="robot_b",
                      grants=launch, owners={})
    check_master_call("setParam", ("/roslaunch", "/talker/rate", 5), manager="robot_b", grants=launch, owners={})


def test_a_refusal_is_told_from_any_other_ros_error():
    assert refused_reason([-1, "denied by cryptoros: name_taken", 0]) == "name_taken"
    assert refused_reason([-1, f"denied by cryptoros: not_granted {SEE_DENIALS}", 0]) == "not_granted"
    for other in ([-1, "denied by cryptoros", 0], [-1, "denied by cryptoros: made_up", 0], [1, "ok", 0],
                  [-1, "node is not registered", 0], "denied by cryptoros: name_taken", None, [0, 5, 0]):
        assert refused_reason(other) is None, other


def test_the_shared_tool_names_are_the_exact_names_of_the_tool_bundles():
    assert {n for n in TOOL_NODES.values() if "*" not in n} == SHARED_TOOL_NAMES


# ------------------------------------------------------------------ own-name endpoints
@pytest.mark.parametrize("action, name, type_name", [
    ("serve", "/cam/set_parameters", "dynamic_reconfigure/Reconfigure"),
    ("publish", "/cam/parameter_descriptions", "dynamic_reconfigure/ConfigDescription"),
    ("publish", "/cam/parameter_updates", "dynamic_reconfigure/Config"),
    ("serve", "/cam/load_nodelet", "nodelet/NodeletLoad"),
    ("serve", "/cam/pause_playback", "std_srvs/SetBool"),
    ("serve", "/cam/get_loggers", "roscpp/GetLoggers"),
])
def test_endpoints_libraries_serve_under_the_nodes_own_name_are_infrastructure(action, name, type_name):
    assert ros1_allows(action, "/cam", name, type_name)
    assert not ros1_allows(action, "/other", name, type_name)  # only under its own name
    assert not ros1_allows(action, "/cam", name, "std_msgs/String")  # only with the library's type


def _two_runs_of_roslib_anonymous_name(base: str) -> tuple[str, str]:
    """``rosgraph.names.anonymous_name`` as roslaunch's ``$(anon ...)`` calls it, in two
    processes of Debian's Python, where ros_comm is (two runs: another pid, another random number)."""
    require("roslaunch")
    code = f"import rosgraph.names; print(rosgraph.names.anonymous_name({base!r}))"
    names = [run(["/usr/bin/python3", "-c", code], timeout=30, check=True).stdout.strip() for _ in range(2)]
    return "/" + names[0], "/" + names[1]


def _rospy_anonymous(base: str, pid: int, at: float) -> str:
    return "%s_%s_%s" % (base, pid, int(at * 1000))  # rospy.client.init_node(anonymous=True)


def _roscpp_anonymous(base: str, at_ns: int) -> str:
    return "%s_%d" % (base, at_ns)  # roscpp this_node.cpp, AnonymousName: snprintf("_%llu", WallTime toNSec)


@pytest.mark.parametrize("runs", [
    (_rospy_anonymous("/rostopic", 4711, 1_795_791_784.006), _rospy_anonymous("/rostopic", 12, 1_795_791_999.5)),
    (_rospy_anonymous("/rosservice", 4194303, 1_700_000_000.0), _rospy_anonymous("/rosservice", 7, 1_795_000_000.0)),
    (_rospy_anonymous("/robot1/cam_1", 4711, 1_795_791_784.0), _rospy_anonymous("/robot1/cam_1", 99, 1_795_791_790.0)),
    (_roscpp_anonymous("/record", 1_795_791_784_006_123_456), _roscpp_anonymous("/record", 1_795_791_790_000_000_001)),
    (_roscpp_anonymous("/robot1/play", time.time_ns()), _roscpp_anonymous("/robot1/play", time.time_ns() + 10**9)),
    ("/rosparam-4711", "/rosparam-12"),
    ("/robot1/rosparam-4194303", "/robot1/rosparam-1"),
    "roslib",
])
def test_an_anonymous_name_learned_as_a_pattern_matches_the_next_runs_name(runs):
    first, second = _two_runs_of_roslib_anonymous_name("cam_1") if runs == "roslib" else runs
    assert first != second
    pattern = node_pattern(first)
    assert pattern != first and pattern == node_pattern(second), (first, second, pattern)
    assert node_matches(pattern, second)
    validate_node_name(pattern)


@pytest.mark.parametrize("node", [
    "/robot_1001", "/lidar_2048", "/robot1/lidar_2048", "/cam-0001", "/cam-2048", "/camera_1", "/arm_1_2",
    "/robot_1001_2002", "/sensor_20240101", "/rosparam-0042", "/rosparam-12345678", "/myrosparam-4711",
    "/robot1/driver", "/rosnode", "/rosservice", "/roslaunch",
])
def test_a_name_that_is_the_same_each_run_is_kept_exactly(node):
    """Policy audit: any name ending in a number of 4 digits or more became a pattern
    (``/robot_1001`` -> ``/robot_*``), granting every robot_N the learned robot's rights."""
    assert node_pattern(node) == node


# ------------------------------------------------------------------ aggregation
def test_a_node_refused_at_5_hz_for_10_s_adds_at_most_two_lines():
    table = DenialTable(interval=10.0)
    lines = []
    for i in range(50):  # 5 Hz for 10 s
        lines += table.record("master", "robot_b subscribeParam", "param_read_denied", "x may not read /y",
                              now=100.0 + i * 0.2, hint="cryptoros-authz grant robot_b read_param /x /y")
    assert 1 <= len(lines) <= 2, lines
    assert lines[0].startswith("DENY master from robot_b subscribeParam: x may not read /y")
    assert "to allow: cryptoros-authz grant robot_b read_param /x /y" in lines[0]
    later = table.record("master", "robot_b subscribeParam", "param_read_denied", "x may not read /y", now=111.0)
    assert len(later) == 1 and "in all" in later[0]
    [row] = table.table(now=112.0)
    assert row["count"] == 51 and row["grant"].endswith("read_param /x /y")


def test_distinct_refusals_are_each_logged_and_the_table_is_bounded():
    table = DenialTable(interval=10.0, max_keys=3)
    for n in range(5):
        assert len(table.record("master", "robot_b", "not_granted", f"/t{n}", now=1.0)) == 1
    assert [r["target"] for r in table.table(now=2.0)] == ["/t4", "/t3", "/t2"]


def test_refused_connections_from_many_sources_are_logged_within_a_budget_and_counted():
    """Stranger audit: unauthenticated refusals were aggregated per source and kind only,
    so 20 addresses sending 7 kinds of junk wrote 160-240 lines a minute. At most
    MAX_UNAUTHENTICATED_LINES every interval, all sources together, then one count."""
    from interceptor.denials import MAX_UNAUTHENTICATED_LINES

    table = DenialTable(interval=10.0)
    lines = []
    for second in range(10):
        for source in range(20):
            for kind in range(7):
                lines += table.record("tls", f"10.0.0.{source}", "tls_failed", f"junk {kind}", now=100.0 + second)
    assert len(lines) == MAX_UNAUTHENTICATED_LINES, len(lines)
    later = table.record("tls", "10.0.0.1", "tls_failed", "junk 0", now=111.0)
    assert later[0].startswith(f"DENY tls: {140 - MAX_UNAUTHENTICATED_LINES} more line(s) of refused connections "
                               "not logged in the last 11 s"), later
    assert later[1].startswith("DENY tls from 10.0.0.1: junk 0 (") and len(later) == 2, later
    assert len(table.table(now=112.0)) == 140  # every one counted in the table (cryptoros denials)
    # refusals of peers that showed a certificate are not held back
    assert all(len(table.record("master", f"robot_{n}", "not_granted", "/t", now=112.0)) == 1 for n in range(40))


def test_a_launched_nodes_parameters_are_not_writable_while_another_manager_holds_its_name():
    # robot_b's grants name /talker, but robot_a registered it: roslaunch of robot_b may not write it
    with pytest.raises(PolicyDenied) as info:
        check_master_call("setParam", ("/roslaunch", "/talker/rate", 5), manager="robot_b", grants=ROBOT,
                          owners={"/talker": "robot_a"})
    assert info.value.reason == "name_taken"
    check_master_call("setParam", ("/roslaunch", "/talker/rate", 5), manager="robot_b", grants=ROBOT,
                      owners={})


def test_our_own_tools_refused_for_a_grant_are_pointed_at_cryptoros_denials():
    """This host's own tools print the refusal as their error line: one refused for a
    grant says where the grant is named; a peer is told the code only."""
    assert refusal_text("not_granted", own=True) == "denied by cryptoros: not_granted (cryptoros denials says what to grant)"
    assert refusal_answer("param_write_denied", "setParam", ("/rosparam-1", "/x", 1), own=True) == \
        [-1, "denied by cryptoros: param_write_denied (cryptoros denials says what to grant)", 0]
    assert refusal_text("not_granted") == "denied by cryptoros: not_granted"
    assert refusal_text("shutdown_dropped", own=True) == "denied by cryptoros: shutdown_dropped"  # no grant allows it
