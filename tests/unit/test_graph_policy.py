"""The pure half of ``policy from-graph``: a ROS 1 graph (as a master reports it) to the
draft policy and its warnings. The live half runs against a real rosmaster in
tests/system/test_policy_from_graph.py."""

from __future__ import annotations

import pytest

from authz_server.graph_policy import Graph, ManagerMap, draft_policy
from authz_server.registry import parse_policy
from cryptoros.errors import RegistryError


def graph(**kw) -> Graph:
    base = dict(publishers={}, subscribers={}, services={}, topic_types={}, service_types={}, node_uris={},
                param_names=[])
    base.update(kw)
    return Graph(**base)


def grants_of(draft) -> dict[str, set[tuple]]:
    return {name: {(g.action, g.node, g.name, g.type) for g in w.grants}
            for name, w in parse_policy(draft.doc).items()}


def test_the_first_matching_entry_names_the_manager_by_node_or_by_host():
    m = ManagerMap.parse(["/robot_a/*=robot_a", "@10.0.0.3=robot_b", "/*=fallback"])
    assert m.manager_for("/robot_a/driver", "10.0.0.3") == "robot_a"
    assert m.manager_for("/driver", "10.0.0.3") == "robot_b"
    assert m.manager_for("/driver", "10.0.0.4") == "fallback"
    assert m.managers == ("robot_a", "robot_b", "fallback")
    for bad in (["/a"], ["=robot_a"], ["/a="], ["/a=not a name"]):
        with pytest.raises(RegistryError):
            ManagerMap.parse(bad)
    with pytest.raises(RegistryError, match="at least one"):
        ManagerMap.parse([])


def test_a_graph_becomes_exact_grants_and_ros_infrastructure_is_left_out():
    g = graph(
        publishers={"/scan": ["/robot_a/laser"], "/rosout": ["/robot_a/laser", "/robot_b/nav"]},
        subscribers={"/scan": ["/robot_b/nav"]},
        services={"/robot_a/laser/get_loggers": ["/robot_a/laser"], "/robot_a/laser/set_logger_level": ["/robot_a/laser"],
                  "/calibrate": ["/robot_a/laser"]},
        topic_types={"/scan": "sensor_msgs/LaserScan", "/rosout": "rosgraph_msgs/Log"},
        service_types={"/calibrate": "std_srvs/Trigger", "/robot_a/laser/get_loggers": "roscpp/GetLoggers",
                       "/robot_a/laser/set_logger_level": "roscpp/SetLoggerLevel"},
        node_uris={"/robot_a/laser": "http://10.0.0.2:4100/", "/robot_b/nav": "http://10.0.0.3:4200/"},
        param_names=["/robot_a/laser/rate", "/robot_a/laser/frame/id", "/rosdistro", "/robot_description"],
    )
    draft = draft_policy(g, ManagerMap.parse(["/robot_a/*=robot_a", "@10.0.0.3=robot_b"]))
    assert grants_of(draft) == {
        "robot_a": {("publish", "/robot_a/laser", "/scan", "sensor_msgs/LaserScan"),
                    ("serve", "/robot_a/laser", "/calibrate", "std_srvs/Trigger"),
                    ("read_param", "/robot_a/laser", "/robot_a/laser", "param")},
        "robot_b": {("subscribe", "/robot_b/nav", "/scan", "sensor_msgs/LaserScan")},
    }
    assert draft.infrastructure == 4  # two /rosout publications, two logger services
    assert [w.split(":")[0] for w in draft.warnings] == ["ROS 1 does not register service clients",
                                                          "1 parameter(s) outside any mapped node's private namespace are not granted (add read_param grants by hand)"]
    assert draft.warnings[1].endswith("/robot_description")
    assert draft.doc["managers"][0]["fingerprint_sha256"] is None


def test_what_a_grant_cannot_hold_is_a_warning_never_a_grant():
    g = graph(
        publishers={"/cmd": ["/teleop", "/rostopic_4242_1700000000000", "/stray"], "/any": ["/teleop"]},
        subscribers={"/cmd": ["/base"]},
        services={"/reset": ["/base"]},
        topic_types={"/cmd": "geometry_msgs/Twist", "/any": "*"},
        service_types={"/reset": None},
        param_names=["/base/a/b", "/base/x"],
    )
    draft = draft_policy(g, ManagerMap.parse(["/teleop=m", "/base=m", "/rostopic_*=m"]), param_access="write_param")
    assert grants_of(draft) == {"m": {("publish", "/teleop", "/cmd", "geometry_msgs/Twist"),
                                      ("subscribe", "/base", "/cmd", "geometry_msgs/Twist"),
                                      ("write_param", "/base", "/base", "param")}}
    text = "\n".join(draft.warnings)
    assert "node /stray matches no --manager-map entry: granted nothing" in text
    assert "node /rostopic_4242_1700000000000 has an anonymous name" in text
    assert "topic /any has no known type: publish not granted to /teleop" in text
    assert "service /reset: its type probe failed: serve not granted to /base" in text


def test_a_stable_name_ending_in_numbers_is_drafted_and_an_anonymous_one_is_not():
    """Policy audit: any name ending in ``_N_N`` or ``-N`` was taken for an anonymous one
    and granted nothing (``/arm_1_2``); only what ROS makes anew each run is."""
    stable = ["/arm_1_2", "/lidar_2048", "/robot_1001"]
    anonymous = ["/rostopic_4242_1700000000000", "/rosparam-42", "/record_1795791784006123456"]
    g = graph(publishers={"/t": stable + anonymous}, topic_types={"/t": "std_msgs/String"})
    draft = draft_policy(g, ManagerMap.parse(["*=m"]))
    assert {n for _a, n, _name, _t in grants_of(draft)["m"]} == set(stable)
    text = "\n".join(draft.warnings)
    assert all(f"node {n} has an anonymous name" in text for n in anonymous), text


def test_a_key_belongs_to_the_node_with_the_longest_matching_name():
    g = graph(publishers={"/t": ["/a", "/a/b"]}, topic_types={"/t": "std_msgs/String"},
              param_names=["/a/b/rate", "/a/c"])
    draft = draft_policy(g, ManagerMap.parse(["*=m"]))
    params = {(a, n, ns) for a, n, ns, _t in grants_of(draft)["m"] if a == "read_param"}
    assert params == {("read_param", "/a/b", "/a/b"), ("read_param", "/a", "/a")}
