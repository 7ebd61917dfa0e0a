"""The lab's policy builder writes what the registry imports, grants and patterns intact."""

from __future__ import annotations

import yaml

from authz_server.registry import parse_policy
from cryptoros.lab.policy import policy_yaml

MANAGERS = {
    "master": {},
    "robot_a": {"publish": [("/talker", "/chatter", "std_msgs/String"), ("/churn_*", "/churn", "std_msgs/String")],
                "serve": [("/adder", "/add_two_ints", "rospy_tutorials/AddTwoInts")],
                "read_param": [("*", "/robot_a", None)]},
    "robot_b": {"subscribe": [("*", "/chatter", "std_msgs/String")],
                "call": [("/client", "/add_two_ints", "rospy_tutorials/AddTwoInts")]},
}
FINGERPRINTS = {"master": "aa" * 32, "robot_a": "bb" * 32, "robot_b": "cc" * 32}


def granted(wanted) -> set[tuple]:
    return {(m.name, g.action, g.node, g.name) for m in wanted.values() for g in m.grants}


def test_the_template_and_the_filled_policy_are_the_same_registry_policy():
    template = policy_yaml(MANAGERS)
    assert "fingerprint_sha256: {robot_a}" in template  # lab_network fills it with str.format
    for text in (template.format(**FINGERPRINTS), policy_yaml(MANAGERS, fingerprints=FINGERPRINTS)):
        wanted = parse_policy(yaml.safe_load(text))
        assert {m.name: m.fingerprint for m in wanted.values()} == FINGERPRINTS
        assert granted(wanted) == {
            ("robot_a", "publish", "/talker", "/chatter"), ("robot_a", "publish", "/churn_*", "/churn"),
            ("robot_a", "serve", "/adder", "/add_two_ints"), ("robot_a", "read_param", "*", "/robot_a"),
            ("robot_b", "subscribe", "*", "/chatter"), ("robot_b", "call", "/client", "/add_two_ints"),
        }
