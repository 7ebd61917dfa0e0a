"""The token a robot shows one peer (:meth:`cryptoros.grants.Grants.narrowed_to`): its
grants on names the peer holds a grant on, plus what a call or subscription of the
endpoints ROS serves under a node's own name (loggers, dynamic_reconfigure) needs at
either end; nothing about other names."""

from __future__ import annotations

from cryptoros.policy.ros1 import check_service_client_header, check_service_server_header
from cryptoros.grants import Grant, Grants

LOGGERS = "roscpp/GetLoggers"


def grants(*rows: tuple[str, str, str, str]) -> Grants:
    return Grants(Grant(node=n, action=a, name=x, type=t) for n, a, x, t in rows)


#: robot A: a talker and cameras by pattern; robot B: a listener and the rosservice tools
ROBOT_A = grants(("/talker", "publish", "/chatter", "std_msgs/String"),
                 ("/cam_*", "publish", "/image", "sensor_msgs/Image"),
                 ("/talker", "publish", "/secret", "std_msgs/String"))
ROBOT_B = grants(("/listener", "subscribe", "/chatter", "std_msgs/String"),
                 ("/rosservice", "call", "/talker/get_loggers", LOGGERS),
                 ("/rosservice_*", "call", "/talker/get_loggers", LOGGERS),
                 ("/rosservice", "call", "/cam_front/set_logger_level", "roscpp/SetLoggerLevel"),
                 ("/dr_client", "subscribe", "/talker/parameter_updates", "dynamic_reconfigure/Config"),
                 ("/rosservice", "call", "/elsewhere/get_loggers", LOGGERS),
                 ("/rosservice", "call", "/talker/get_loggers_x", LOGGERS),
                 ("/rosservice", "call", "/cam_front/get_loggers", "std_srvs/Empty"))


def test_a_call_of_a_named_nodes_logger_service_is_kept_for_the_robot_serving_it():
    shown_a = ROBOT_B.narrowed_to(ROBOT_A)  # what robot B shows robot A
    assert shown_a.allows("call", "/rosservice", "/talker/get_loggers", LOGGERS)
    assert shown_a.allows("call", "/rosservice_1_1795791784006", "/talker/get_loggers", LOGGERS)
    # a node robot A's grants name by a pattern
    assert shown_a.allows("call", "/rosservice", "/cam_front/set_logger_level", "roscpp/SetLoggerLevel")
    assert shown_a.allows("subscribe", "/dr_client", "/talker/parameter_updates", "dynamic_reconfigure/Config")
    # robot A learns nothing of calls of nodes its grants do not name, of other names, other types
    assert "/elsewhere/get_loggers" not in shown_a.names()
    assert "/talker/get_loggers_x" not in shown_a.names()
    assert not shown_a.types_for("call", "/rosservice", "/cam_front/get_loggers")
    # robot A judges robot B's call with it
    assert check_service_client_header({"callerid": "/rosservice", "service": "/talker/get_loggers", "md5sum": "*",
                                        "probe": "1"}, grants=shown_a) == {LOGGERS}


def test_the_serving_robot_shows_the_caller_its_nodes_own_service_and_nothing_else():
    shown_b = ROBOT_A.narrowed_to(ROBOT_B)  # what robot A shows robot B
    assert shown_b.allows("serve", "/talker", "/talker/get_loggers", LOGGERS)
    assert shown_b.allows("serve", "/cam_front", "/cam_front/set_logger_level", "roscpp/SetLoggerLevel")
    assert shown_b.allows("publish", "/talker", "/talker/parameter_updates", "dynamic_reconfigure/Config")
    assert shown_b.allows("publish", "/talker", "/chatter", "std_msgs/String")
    # nothing on names robot B holds no grant on: not /image, not /secret, not the pattern
    assert shown_b.names() == {"/chatter", "/talker/get_loggers", "/cam_front/set_logger_level",
                               "/talker/parameter_updates"}
    assert not shown_b.names_node("/cam_back")
    check_service_server_header({"callerid": "/talker", "type": LOGGERS}, service="/talker/get_loggers",
                                server_grants=shown_b, client_types=frozenset({LOGGERS}))


def test_nothing_is_kept_for_a_peer_whose_grants_name_no_such_node():
    stranger = grants(("/other", "subscribe", "/weather", "std_msgs/String"))
    assert len(ROBOT_B.narrowed_to(stranger)) == 0
    assert len(ROBOT_A.narrowed_to(stranger)) == 0
    assert len(stranger.narrowed_to(ROBOT_B)) == 0
