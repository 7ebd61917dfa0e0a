"""The command a denial shows after ``to allow:`` (:mod:`cryptoros.policy.hints`): a
stock tool's bundle, the type filled in where it is known, a placeholder explained
where it is not, and every argument quoted so that the line works pasted into a shell."""

from __future__ import annotations

import shlex
import subprocess

import pytest

from cryptoros.errors import PolicyDenied
from cryptoros.policy.hints import grant_hint, missing_grant_hint
from cryptoros.policy.ros1 import (
    check_local_subscriber_header,
    check_node_call,
    check_publisher_header,
    check_service_client_header,
    check_service_server_header,
    check_subscriber_header,
    node_pattern,
)
from cryptoros.grants import Grants
from interceptor.ros1.wire import header_hint
from tests.support import require

NOTHING = Grants([])
ROSTOPIC = "/rostopic_4711_1795791784006"


def refused(reason: str = "not_granted") -> PolicyDenied:
    return PolicyDenied(reason, "x")


def refusal(check, *args, **kwargs) -> PolicyDenied:
    with pytest.raises(PolicyDenied) as info:
        check(*args, **kwargs)
    return info.value


def command_part(hint: str) -> list[str]:
    """The arguments a shell gives the command (the note after ``#`` is a comment)."""
    return shlex.split(hint, comments=True)


def test_a_tools_node_is_pointed_at_its_bundle_with_the_tools_node_pattern():
    assert node_pattern("/rosparam-4711") == "/rosparam-*"
    assert node_pattern("/rostopic_4711_1795791784006") == "/rostopic_*"
    assert grant_hint(refused("param_write_denied"), "setParam", ("/rosparam-4711", "/x", 1), "robot_b") == \
        "cryptoros-authz grant-tools robot_b --param-ns /x"
    assert grant_hint(refused("param_read_denied"), "getParam", ("/rosparam-4711", "/x"), "robot_b") == \
        "cryptoros-authz grant-tools robot_b --param-ns /x --params-read-only"
    assert grant_hint(refused(), "registerPublisher", ("/play_1795791817872", "/clock", "rosgraph_msgs/Clock",
                                                       "http://127.0.0.1:1/"), "robot_b") == \
        "cryptoros-authz grant-tools robot_b --clock"
    assert grant_hint(refused(), "registerSubscriber", (ROSTOPIC, "/chatter", "std_msgs/String", "http://x:1/"),
                      "robot_b") == "cryptoros-authz grant-tools robot_b --topic /chatter:std_msgs/String"
    assert grant_hint(refused(), "registerPublisher", ("/play_1795791817872", "/scan", "sensor_msgs/LaserScan",
                                                       "http://x:1/"), "robot_b") == \
        "cryptoros-authz grant-tools robot_b --publish-topic /scan:sensor_msgs/LaserScan"
    assert grant_hint(refused("shutdown_dropped"), "shutdown", ("/rosnode", "x"), "robot_b") is None
    assert grant_hint(refused("param_write_denied"), "setParam", ("/n", "/x", 1), None) is None
    assert grant_hint(refused("param_read_denied"), "getParam", ("/prober", "/secret"), "robot_b") == \
        "cryptoros-authz grant robot_b read_param /prober /secret"


def test_roslaunchs_refusals_point_at_its_bundle():
    assert grant_hint(refused("param_write_denied"), "setParam", ("/roslaunch", "/run_id", "x"), "robot_b") == \
        "cryptoros-authz grant-tools robot_b --roslaunch"
    assert grant_hint(refused("param_write_denied"), "setParam", ("/roslaunch", "/roslaunch/uris/host_1", "x"),
                      "robot_b") == "cryptoros-authz grant-tools robot_b --roslaunch"
    assert grant_hint(refused("param_write_denied"), "setParam", ("/roslaunch", "/global_setting", 3), "robot_b") == \
        "cryptoros-authz grant-tools robot_b --roslaunch --launch-param-ns /global_setting"


def test_a_node_no_grant_names_is_told_what_grant_names_it():
    """/rosout and a node's own loggers are refused only to a node no grant names: the hint
    is the tool's bundle (or any grant) with its placeholders explained."""
    rosout = (ROSTOPIC, "/rosout", "rosgraph_msgs/Log", "http://x:1/")
    hint = grant_hint(refused(), "registerPublisher", rosout, "robot_b")
    assert hint.startswith("cryptoros-authz grant-tools robot_b --topic TOPIC:TYPE  # no grant names "
                           "/rostopic_*; TOPIC: the topic rostopic echo/hz/bw reads (rostopic pub: --publish-topic "
                           "TOPIC:TYPE), TYPE: its type (rostopic type TOPIC prints it)"), hint
    loggers = grant_hint(refused(), "registerService", (ROSTOPIC, ROSTOPIC + "/get_loggers", "rosrpc://x:1",
                                                        "http://x:1/"), "robot_b")
    assert loggers == hint
    service_tool = grant_hint(refused(), "registerPublisher", ("/rosservice_1_1795791784006",) + rosout[1:], "robot_b")
    assert command_part(service_tool) == ["cryptoros-authz", "grant-tools", "robot_b", "--service", "SERVICE:TYPE"]
    assert "show-manager" in service_tool
    other = grant_hint(refused(), "registerPublisher", ("/my_node",) + rosout[1:], "robot_b")
    assert command_part(other) == ["cryptoros-authz", "grant", "robot_b", "ACTION", "/my_node", "NAME", "TYPE"]
    assert "no grant names /my_node; ACTION: publish, subscribe, serve or call" in other


def test_a_stream_refused_by_its_header_names_the_grant_of_the_side_that_lacks_it():
    """The subscriber's or client's manager for subscribe and call, the publisher's or
    server's for publish and serve; the type filled in where it is known."""
    probe = {"callerid": "/rosservice", "service": "/svc_a", "md5sum": "*", "probe": "1"}
    call = refusal(check_service_client_header, probe, grants=NOTHING)
    call_hint = header_hint(call, opener="robot_b", server="robot_a")
    # the /rosservice probe: the bundle (probe and /rosservice_*); its type is a placeholder with where to find it
    assert call_hint == "cryptoros-authz grant-tools robot_b --service /svc_a:TYPE  # TYPE: the service's type, " \
                        "the one its server is granted (cryptoros-authz show-manager SERVER_ROBOT lists it)"
    echo = {"callerid": ROSTOPIC, "topic": "/chatter", "type": "*", "md5sum": "*"}
    assert header_hint(refusal(check_local_subscriber_header, echo, grants=NOTHING), opener="robot_b",
                       server="robot_a") == "cryptoros-authz grant-tools robot_b --topic /chatter:TYPE  " \
                                            "# TYPE: the topic's type (rostopic type NAME prints it)"
    # at the publisher's interceptor: the type is the one published
    subscribed = refusal(check_subscriber_header, echo, grants=NOTHING, published_type="std_msgs/String",
                         published_md5=None)
    assert header_hint(subscribed, opener="robot_b", server="robot_a") == \
        "cryptoros-authz grant-tools robot_b --topic /chatter:std_msgs/String"
    published = refusal(check_publisher_header, {"callerid": "/talker_a", "type": "std_msgs/String"},
                        grants=NOTHING, topic="/chatter")
    assert header_hint(published, opener="robot_b", server="robot_a") == \
        "cryptoros-authz grant robot_a publish /talker_a /chatter std_msgs/String"
    served = refusal(check_service_server_header, {"callerid": "/srv", "type": "roscpp/GetLoggers"},
                     service="/svc_a", server_grants=NOTHING, client_types=frozenset({"roscpp/GetLoggers"}))
    assert header_hint(served, opener="robot_b", server="robot_a") == \
        "cryptoros-authz grant robot_a serve /srv /svc_a roscpp/GetLoggers"
    malformed = refusal(check_service_client_header, {"callerid": "/x"}, grants=NOTHING)
    assert header_hint(malformed, opener="robot_b", server="robot_a") is None
    assert header_hint(call, opener="robot_b", server=None) == call_hint
    assert header_hint(published, opener="robot_b", server=None) is None


@pytest.mark.parametrize(("service", "type_name"), [("/talker/get_loggers", "roscpp/GetLoggers"),
                                                     ("/cam/front/set_logger_level", "roscpp/SetLoggerLevel"),
                                                     ("/dr/set_parameters", "dynamic_reconfigure/Reconfigure")])
def test_a_call_of_a_nodes_own_service_names_its_type(service, type_name):
    probe = {"callerid": "/rosservice", "service": service, "md5sum": "*", "probe": "1"}
    assert missing_grant_hint(refusal(check_service_client_header, probe, grants=NOTHING), "robot_b") == \
        f"cryptoros-authz grant-tools robot_b --service {service}:{type_name}"
    client = dict(probe, callerid="/monitor")
    assert missing_grant_hint(refusal(check_service_client_header, client, grants=NOTHING), "robot_b") == \
        f"cryptoros-authz grant robot_b call /monitor {service} {type_name}"


def test_a_topic_request_names_the_type_published():
    denied = refusal(check_node_call, "requestTopic", ("/listener", "/chatter", [["TCPROS"]]), grants=NOTHING,
                     peer_is_master=False, topic_types={"/chatter": "std_msgs/String"})
    assert grant_hint(denied, "requestTopic", ("/listener", "/chatter", [["TCPROS"]]), "robot_b") == \
        "cryptoros-authz grant robot_b subscribe /listener /chatter std_msgs/String"


@pytest.mark.parametrize("shell", [["bash", "-O", "failglob", "-c"], ["zsh", "-c"]])
def test_a_hint_with_a_pattern_pastes_into_a_shell_as_one_argument_each(shell):
    """A node pattern is quoted: bash with failglob and zsh (a glob matching nothing is
    an error in both) pass ``/play_*`` and ``/record_*`` on as they are; a note after
    ``#`` is a comment."""
    require(shell[0])
    hints = [missing_grant_hint(PolicyDenied("not_granted", "x", missing=("call", "/play_1795791817872", "/s", None)),
                                "robot_b"),
             missing_grant_hint(PolicyDenied("not_granted", "x", missing=("publish", "/record_1795791817872", "/x",
                                                                          "std_msgs/String")), "robot_b"),
             grant_hint(refused(), "registerPublisher", ("/my_node", "/rosout", "rosgraph_msgs/Log", "h"), "robot_b")]
    assert "'/play_*'" in hints[0] and "'/record_*'" in hints[1], hints
    for hint in hints:
        argv = subprocess.run([*shell, f"printf '%s\\n' {hint.split(' ', 1)[1]}"], capture_output=True, text=True,
                              timeout=10)
        assert argv.returncode == 0, (hint, argv.stderr)
        assert argv.stdout.splitlines() == command_part(hint)[1:], hint
