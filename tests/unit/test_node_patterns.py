"""Node-name patterns in grants (``/rostopic_*``): validated in cryptoros/names.py,
matched by the one function :func:`cryptoros.grants.node_matches` that every
:class:`Grants` method uses, so every interceptor decides a pattern the same way."""

from __future__ import annotations

import pytest

from cryptoros.errors import PolicyDenied, RegistryError, TokenError
from cryptoros.names import validate_node_name
from cryptoros.policy.ros1 import check_master_call, check_subscriber_header
from cryptoros.grants import Grant, Grants, node_matches

STRING = "std_msgs/String"
MD5 = "992ce8a1687cec8c8bd883ec73ca41d1"
API = "cryptoros://127.0.0.2:11400/x/1"


@pytest.mark.parametrize("name", ["*", "/talker", "/robot1/scan", "/rostopic_*", "/rosparam-*", "/robot1/*", "/r*"])
def test_valid_node_names_and_patterns(name):
    assert validate_node_name(name) == name


@pytest.mark.parametrize("name", ["/*", "**", "/a*b*", "/a*b", "rostopic_*", "/1*", "/a//*", "/a b*", "*/x",
                                  "/ros*/*", "/talker-", "/a-b", "", "/" + "a" * 300 + "*"])
def test_invalid_node_names_and_patterns(name):
    with pytest.raises(RegistryError):
        validate_node_name(name)


@pytest.mark.parametrize(("granted", "node", "expected"), [
    ("*", "/anything", True),
    ("/talker", "/talker", True),
    ("/talker", "/talker2", False),           # an exact name never matches a longer one
    ("/talker", "/talker/sub", False),
    ("/talker", "/talke", False),
    ("/rostopic_*", "/rostopic_4242_1700000000000", True),
    ("/rostopic_*", "/rostopic_", False),     # the * stands for at least one character
    ("/rostopic_*", "/rostopic", False),
    ("/rostopic_*", "/rostopicx_1", False),
    ("/rostopic_*", "/other/rostopic_1", False),
    ("/rosparam-*", "/rosparam-4242", True),
    ("/rosparam-*", "/rosparam_4242", False),
    ("/robot1/*", "/robot1/planner", True),
    ("/robot1/*", "/robot1/a/b", True),       # ``/`` included: a namespace prefix
    ("/robot1/*", "/robot10/planner", False),
    ("/robot1/*", "/robot1", False),
])
def test_node_matches(granted, node, expected):
    assert node_matches(granted, node) is expected


TOOLS = Grants([
    Grant(node="/rostopic_*", action="subscribe", name="/chatter", type=STRING),
    Grant(node="/rosparam-*", action="write_param", name="/", type="param"),
    Grant(node="/rosservice", action="call", name="/add", type="rospy_tutorials/AddTwoInts"),
    Grant(node="/talker", action="publish", name="/chatter", type=STRING),
])


def test_every_grants_method_uses_the_pattern():
    anon = "/rostopic_77_1700000000000"
    assert TOOLS.allows("subscribe", anon, "/chatter", STRING)
    assert not TOOLS.allows("subscribe", "/rostopic", "/chatter", STRING)
    assert not TOOLS.allows("publish", anon, "/chatter", STRING)
    assert TOOLS.types_for("subscribe", anon, "/chatter") == {STRING}
    assert TOOLS.types_for("subscribe", "/rosparam-1", "/chatter") == frozenset()
    assert TOOLS.param_allows("write", "/rosparam-4242", "/x")
    assert TOOLS.param_allows("read", "/rosparam-4242", "/a/b")
    assert not TOOLS.param_allows("read", "/rosparam_4242", "/x")
    assert TOOLS.param_namespaces("/rosparam-9") == {"/"}
    assert TOOLS.names_node(anon) and TOOLS.names_node("/rosparam-1") and TOOLS.names_node("/rosservice")
    assert not TOOLS.names_node("/rosservice_1") and not TOOLS.names_node("/talker2")
    # exact grants keep working next to patterns
    assert TOOLS.allows("publish", "/talker", "/chatter", STRING)
    assert TOOLS.types_for("call", "/rosservice", "/add") == {"rospy_tutorials/AddTwoInts"}


def test_patterns_survive_the_token_claim_and_narrowing():
    again = Grants.from_claim(TOOLS.to_claim())
    assert again == TOOLS
    narrowed = again.narrowed_to(Grants([Grant(node="/l", action="publish", name="/chatter", type=STRING)]))
    assert narrowed.allows("subscribe", "/rostopic_1_2", "/chatter", STRING)
    with pytest.raises(TokenError) as info:
        Grants.from_claim({"/a*b*": {"subscribe": [["/chatter", STRING]]}})
    assert info.value.reason == "malformed"


def test_master_role_lets_a_pattern_register_matching_names_only():
    anon = "/rostopic_77_1700000000000"
    check_master_call("registerSubscriber", (anon, "/chatter", STRING, API), manager="bob", grants=TOOLS,
                      owners={})
    check_master_call("unregisterSubscriber", (anon, "/chatter", API), manager="bob", grants=TOOLS,
                      owners={anon: "bob"})
    # a name matching the pattern that another manager registered first stays theirs
    with pytest.raises(PolicyDenied) as taken:
        check_master_call("registerSubscriber", (anon, "/chatter", STRING, API), manager="bob", grants=TOOLS,
                          owners={anon: "alice"})
    assert taken.value.reason == "name_taken"
    # the pattern's anonymous nodes get rospy's infrastructure (/rosout) like any own node
    check_master_call("registerPublisher", (anon, "/rosout", "rosgraph_msgs/Log", API), manager="bob", grants=TOOLS,
                      owners={})
    with pytest.raises(PolicyDenied):
        check_master_call("registerPublisher", ("/rostopic", "/rosout", "rosgraph_msgs/Log", API), manager="bob",
                          grants=TOOLS, owners={})
    # rosparam's caller /rosparam-<pid> writes a global parameter under its write_param grant
    check_master_call("setParam", ("/rosparam-4242", "/x", 1), manager="bob", grants=TOOLS, owners={})
    with pytest.raises(PolicyDenied) as refused:
        check_master_call("setParam", ("/rostopic_1_2", "/x", 1), manager="bob", grants=TOOLS, owners={})
    assert refused.value.reason == "param_write_denied"


def test_subscriber_header_of_an_anonymous_tool():
    header = {"callerid": "/rostopic_5_6", "topic": "/chatter", "type": STRING, "md5sum": MD5}
    check_subscriber_header(header, grants=TOOLS, published_type=STRING, published_md5=MD5)
    with pytest.raises(PolicyDenied):
        check_subscriber_header({**header, "callerid": "/rostopic"}, grants=TOOLS, published_type=STRING,
                                published_md5=MD5)
