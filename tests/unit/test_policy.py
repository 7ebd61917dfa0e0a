"""The policy decision, request by request: what is allowed, and why the rest is not."""

from __future__ import annotations

import pytest

from cryptoros.errors import PolicyDenied
from cryptoros.policy.ros1 import (
    check_master_call,
    check_node_call,
    check_publisher_header,
    check_service_client_header,
    check_service_server_header,
    check_subscriber_header,
)
from cryptoros.grants import Grant, Grants

STRING = "std_msgs/String"
MD5 = "992ce8a1687cec8c8bd883ec73ca41d1"
ALICE = Grants(
    [
        Grant(node="/talker", action="publish", name="/chatter", type=STRING),
        Grant(node="/listener", action="subscribe", name="/chatter", type=STRING),
        Grant(node="/adder", action="serve", name="/add_two_ints", type="rospy_tutorials/AddTwoInts"),
        Grant(node="/client", action="call", name="/add_two_ints", type="rospy_tutorials/AddTwoInts"),
    ]
)
OWNERS = {"/talker": "alice", "/victim": "bob"}


def master(method, *params, manager="alice", grants=ALICE, infrastructure=True):
    return check_master_call(
        method, params, manager=manager, grants=grants, owners=OWNERS, infrastructure=infrastructure
    )


def denied(fn, *args, **kw) -> str:
    with pytest.raises(PolicyDenied) as info:
        fn(*args, **kw)
    return info.value.reason


API = "cryptoros://127.0.0.2:11400/x/1"


def test_granted_registrations_pass():
    master("registerPublisher", "/talker", "/chatter", STRING, API)
    master("registerSubscriber", "/listener", "/chatter", STRING, API)
    master("registerService", "/adder", "/add_two_ints", "rosrpc://x", API)
    master("unregisterPublisher", "/talker", "/chatter", API)


@pytest.mark.parametrize(
    ("method", "params", "reason"),
    [
        ("registerPublisher", ("/talker", "/cmd_vel", "geometry_msgs/Twist", API), "not_granted"),
        ("registerPublisher", ("/talker", "/chatter", "std_msgs/Int32", API), "not_granted"),
        ("registerPublisher", ("/listener", "/chatter", STRING, API), "not_granted"),
        ("registerSubscriber", ("/talker", "/chatter", STRING, API), "not_granted"),
        ("registerService", ("/talker", "/add_two_ints", "rosrpc://x", API), "not_granted"),
        ("registerPublisher", ("/victim", "/chatter", STRING, API), "name_taken"),
        ("unregisterPublisher", ("/victim", "/chatter", API), "name_taken"),
        ("unregisterSubscriber", ("/stranger", "/chatter", API), "not_its_node"),  # no grant would allow it
        ("shutdown", ("/evil", "bye"), "shutdown_dropped"),
        ("setParam", ("/talker", "/use_sim_time", True), "param_write_denied"),
        ("deleteParam", ("/talker", "/robot_description"), "param_write_denied"),
        ("launchMissiles", ("/talker",), "method_not_allowed"),
        ("registerPublisher", (), "malformed"),
        ("registerPublisher", ("not a name", "/chatter", STRING, API), "malformed"),
        ("registerPublisher", ("/talker", 42, STRING, API), "malformed"),
    ],
)
def test_master_calls_denied_with_reason(method, params, reason):
    assert denied(master, method, *params) == reason


def test_read_only_and_own_params_pass():
    for method in ("getSystemState", "lookupNode", "getTopicTypes", "getUri"):
        master(method, "/anyone", "/x")
    master("setParam", "/talker", "/talker/rate", 10)
    master("getParam", "/talker", "/talker/rate")
    master("getParam", "/anyone", "/use_sim_time")
    assert denied(master, "getParam", "/anyone", "/x") == "param_read_denied"


#: bob's nodes are any nodes (one ``*`` grant); he may read /robot_b and nothing else
BOB = Grants([Grant(node="*", action="subscribe", name="/chatter", type=STRING),
              Grant(node="*", action="read_param", name="/robot_b", type="param"),
              Grant(node="/rosparam-*", action="subscribe", name="/chatter", type=STRING)])


def bob(method, *params):
    return master(method, *params, manager="bob", grants=BOB)


def test_a_name_covered_only_by_the_wildcard_has_no_private_namespace():
    """Under ``*`` any name is the manager's, so a caller named after a global key, a
    namespace or another robot's parameter would own it as its "private namespace"."""
    for key in ("/fleet/mode", "/robot_description", "/talker/rate", "/fleet"):
        assert denied(bob, "setParam", key, key, 1) == "param_write_denied"
        assert denied(bob, "deleteParam", key, key) == "param_write_denied"
        assert denied(bob, "getParam", key, key) == "param_read_denied"
        assert denied(bob, "hasParam", key, "~") == "param_read_denied"
    bob("getParam", "/fleet/mode", "/robot_b/speed")  # what his grant says he may read
    bob("setParam", "/rosparam-42", "/rosparam-42/x", 1)  # a prefix pattern is the manager's own
    # an exact grant keeps it: alice's /talker writes its own rate
    master("setParam", "/talker", "/talker/rate", 10)


def test_a_parameter_call_in_the_name_of_another_managers_node_is_refused():
    """Reads too: the private namespace is the node's that holds the name."""
    pattern = Grants([Grant(node="/vic*", action="subscribe", name="/chatter", type=STRING)])
    for method, params in (("getParam", ("/victim", "/victim/secret")), ("hasParam", ("/victim", "~secret")),
                           ("getParamNames", ("/victim",)), ("searchParam", ("/victim", "secret")),
                           ("setParam", ("/victim", "/victim/secret", 1))):
        assert denied(master, method, *params, grants=pattern) == "name_taken", method
    master("getParam", "/vicar", "/vicar/secret", grants=pattern)  # its own (held by nobody else)


def test_subscribing_a_namespace_needs_all_of_it_readable():
    """rosmaster's paramUpdates after a subscribeParam carry every value set under the
    key, unpruned: a namespace readable only in part is refused (getParam's one answer
    is pruned instead)."""
    assert denied(bob, "subscribeParam", "/robot_b/x", API, "/") == "param_read_denied"
    assert denied(master, "subscribeParam", "/talker", API, "/") == "param_read_denied"
    master("getParam", "/talker", "/")  # allowed, the answer pruned (filter_param_reply)
    bob("subscribeParam", "/robot_b/x", API, "/robot_b")
    bob("subscribeParam", "/robot_b/x", API, "/robot_b/speed")
    master("subscribeParam", "/talker", API, "~rate")
    master("subscribeParam", "/talker", API, "/use_sim_time")


def test_rosout_and_logger_services_are_infrastructure():
    master("registerPublisher", "/talker", "/rosout", "rosgraph_msgs/Log", API)
    master("registerService", "/talker", "/talker/get_loggers", "rosrpc://x", API)
    assert denied(master, "registerService", "/talker", "/listener/get_loggers", "rosrpc://x", API) == "not_granted"
    assert denied(master, "registerPublisher", "/nobody", "/rosout", "rosgraph_msgs/Log", API) == "not_granted"
    assert (
        denied(master, "registerPublisher", "/talker", "/rosout", "rosgraph_msgs/Log", API, infrastructure=False)
        == "not_granted"
    )


def node(method, *params, peer_is_master=False, grants=ALICE):
    return check_node_call(
        method, params, grants=grants, peer_is_master=peer_is_master, topic_types={"/chatter": STRING}
    )


def test_node_calls():
    node("requestTopic", "/listener", "/chatter", [["TCPROS"]])
    node("getBusInfo", "/anyone")
    node("publisherUpdate", "/master", "/chatter", [], peer_is_master=True)
    assert denied(node, "publisherUpdate", "/evil", "/chatter", []) == "not_from_master"
    assert denied(node, "paramUpdate", "/evil", "/p", 1) == "not_from_master"
    assert denied(node, "shutdown", "/master", "bye", peer_is_master=True) == "shutdown_dropped"
    assert denied(node, "requestTopic", "/talker", "/chatter", [["TCPROS"]]) == "not_granted"
    assert denied(node, "requestTopic", "/listener", "/secret", [["TCPROS"]]) == "unknown_topic"
    assert denied(node, "system.listMethods") == "method_not_allowed"


def sub_header(**kw):
    h = {"callerid": "/listener", "topic": "/chatter", "type": STRING, "md5sum": MD5}
    h.update(kw)
    return h


def test_subscriber_header_checks():
    check_subscriber_header(sub_header(), grants=ALICE, published_type=STRING, published_md5=MD5)
    cases = {
        "type_mismatch": sub_header(type="std_msgs/Int32"),
        "md5_mismatch": sub_header(md5sum="0" * 32),
        "not_granted": sub_header(callerid="/talker"),
        "malformed": sub_header(topic=""),
    }
    for reason, header in cases.items():
        assert denied(check_subscriber_header, header, grants=ALICE, published_type=STRING, published_md5=MD5) == reason
    assert denied(check_subscriber_header, sub_header(type="*"), grants=ALICE, published_type=STRING,
                  published_md5=MD5) == "type_mismatch"
    assert denied(check_subscriber_header, sub_header(), grants=ALICE, published_type=None,
                  published_md5=None) == "unknown_topic"


def test_publisher_and_service_headers():
    check_publisher_header({"callerid": "/talker", "type": STRING, "md5sum": MD5}, grants=ALICE, topic="/chatter")
    assert denied(check_publisher_header, {"callerid": "/listener", "type": STRING}, grants=ALICE,
                  topic="/chatter") == "not_granted"
    types = check_service_client_header({"callerid": "/client", "service": "/add_two_ints", "md5sum": "*"},
                                        grants=ALICE)
    assert types == {"rospy_tutorials/AddTwoInts"}
    assert denied(check_service_client_header, {"callerid": "/talker", "service": "/add_two_ints", "md5sum": "x"},
                  grants=ALICE) == "not_granted"
    check_service_server_header({"callerid": "/adder", "type": "rospy_tutorials/AddTwoInts"},
                                service="/add_two_ints", server_grants=ALICE, client_types=types)
    assert denied(check_service_server_header, {"callerid": "/adder", "type": "std_srvs/Empty"},
                  service="/add_two_ints", server_grants=ALICE, client_types=types) == "type_mismatch"
    assert denied(check_service_server_header, {"callerid": "/talker", "type": "rospy_tutorials/AddTwoInts"},
                  service="/add_two_ints", server_grants=ALICE, client_types=types) == "not_granted"


def test_a_header_is_judged_for_one_purpose_only():
    """rospy answers a header that names a topic as a subscription, whatever else it
    holds: a service header naming a topic (checked as a granted call) read another
    topic's messages in an insider's run. Headers and replies carrying both kinds of
    field are refused, both ways."""
    call = {"callerid": "/client", "service": "/add_two_ints", "md5sum": "*"}
    assert denied(check_service_client_header, {**call, "topic": "/chatter", "type": STRING},
                  grants=ALICE) == "malformed"
    types = check_service_client_header(call, grants=ALICE)
    served = {"callerid": "/adder", "type": "rospy_tutorials/AddTwoInts"}
    for extra in ({"topic": "/chatter"}, {"latching": "0"}):
        assert denied(check_service_server_header, {**served, **extra}, service="/add_two_ints",
                      server_grants=ALICE, client_types=types) == "malformed"
    for extra in ({"service": "/add_two_ints"}, {"probe": "1"}, {"persistent": "1"}):
        assert denied(check_subscriber_header, sub_header(**extra), grants=ALICE, published_type=STRING,
                      published_md5=MD5) == "malformed"
    assert denied(check_publisher_header, {"callerid": "/talker", "type": STRING, "md5sum": MD5,
                                           "request_type": "x/Req"}, grants=ALICE, topic="/chatter") == "malformed"
    # what rospy and roscpp really send still passes
    check_subscriber_header(sub_header(tcp_nodelay="1", message_definition="string data"), grants=ALICE,
                            published_type=STRING, published_md5=MD5)
    check_service_client_header({**call, "persistent": "1"}, grants=ALICE)
    check_service_server_header({**served, "request_type": "r/Q", "response_type": "r/A", "md5sum": "x"},
                                service="/add_two_ints", server_grants=ALICE, client_types=types)


def test_a_refusal_reply_is_never_taken_for_a_granted_stream():
    """A server's ``error`` header (with or without other fields) does not pass the
    reply checks: the interceptor passes the refusal on and relays nothing after it."""
    for header in ({"error": "md5 mismatch"}, {"error": "x", "callerid": "/listener", "type": STRING}):
        assert denied(check_publisher_header, header, grants=ALICE, topic="/chatter") in ("malformed", "not_granted")
    assert denied(check_publisher_header, {"error": "no"}, grants=ALICE, topic="/chatter") == "malformed"
    assert denied(check_service_server_header, {"error": "no"}, service="/add_two_ints", server_grants=ALICE,
                  client_types=frozenset({"rospy_tutorials/AddTwoInts"})) == "malformed"


# ------------------------------------------------------------------ subscribers of any type (rosbag record)


def test_a_subscriber_of_any_type_needs_a_subscribe_grant_on_the_topic_and_gets_only_a_granted_type():
    from cryptoros.policy.ros1 import ANY_TYPE, check_local_subscriber_header, check_subscribed_type

    master("registerSubscriber", "/listener", "/chatter", ANY_TYPE, API)  # granted /chatter with some type
    assert denied(master, "registerSubscriber", "/talker", "/chatter", ANY_TYPE, API) == "not_granted"
    assert denied(master, "registerSubscriber", "/listener", "/secret", ANY_TYPE, API) == "not_granted"
    # leaving the subscriber's host, then once the publisher answered with its type
    wildcard = {"callerid": "/listener", "topic": "/chatter", "type": ANY_TYPE, "md5sum": ANY_TYPE}
    check_local_subscriber_header(wildcard, grants=ALICE)
    assert denied(check_local_subscriber_header, {**wildcard, "callerid": "/talker"}, grants=ALICE) == "not_granted"
    check_subscribed_type(wildcard, STRING, grants=ALICE)
    assert denied(check_subscribed_type, wildcard, "std_msgs/Int32", grants=ALICE) == "not_granted"
    check_subscribed_type({**wildcard, "type": STRING}, "std_msgs/Int32", grants=ALICE)  # checked before, not here
    # at the publisher's host: judged as a subscriber of the type really published
    check_subscriber_header(wildcard, grants=ALICE, published_type=STRING, published_md5=MD5)
    assert denied(check_subscriber_header, wildcard, grants=ALICE, published_type="std_msgs/Int32",
                  published_md5="x") == "not_granted"
    assert denied(check_subscriber_header, {**wildcard, "md5sum": "0" * 32}, grants=ALICE, published_type=STRING,
                  published_md5=MD5) == "type_mismatch"  # '*' type with a real md5sum is not a wildcard


def test_the_owners_a_decision_consults_are_the_callers_and_those_of_the_nodes_a_written_key_names():
    from cryptoros.policy.ros1 import named_nodes

    assert named_nodes("registerPublisher", ("/talker", "/chatter", "std_msgs/String", "http://x:1/")) == ("/talker",)
    assert named_nodes("setParam", ("/roslaunch", "/talker/rate", 5)) == ("/roslaunch", "/talker", "/talker/rate")
    assert named_nodes("setParam", ("/roslaunch", "bad key!", 5)) == ("/roslaunch",)
    assert named_nodes("getPid", ()) == ()
