"""Learning mode's decisions and proposals, without processes: grants widened only while
a window lasts and only for whom it should, what is recorded, the proposal's smallest
grants, the unused grants, what a report may carry, and how the interceptor reports
(its AuthzClient answered by a stand-in for the server, no network)."""

from __future__ import annotations

import logging
import ssl
import time

import pytest
from prometheus_client import CollectorRegistry

from authz_server.learning import (MAX_OBSERVATION_ROWS, checked_observations, granted, known_types, propose,
                                   proposal_yaml, unused)
from authz_server.registry import GrantRow, ObservationRow
from cryptoros.errors import RegistryError
from cryptoros.learning import ANY_TYPES, LearningState, ObservationTable, Seen
from cryptoros.policy.ros1 import check_master_call, check_service_client_header
from cryptoros.grants import Grant, Grants
from interceptor.authz_client import AuthzClient, AuthzUnavailable
from interceptor.config import AuthzSettings
from interceptor.learning import Learner

NOW = 1_000_000.0
TALKER = Grant(node="/talker", action="publish", name="/chatter", type="std_msgs/String")


class Clock:
    def __init__(self) -> None:
        self.now = NOW

    def __call__(self) -> float:
        return self.now


def state(own: str = "robot_a", *, master: bool = False, learning: dict[str, float] | None = None):
    clock = Clock()
    s = LearningState(own, serves_everyone=master, clock=clock)
    s.windows = learning or {}
    return s, clock


def test_without_a_window_grants_answer_as_they_are_and_record_what_they_allowed():
    s, _ = state()
    grants = s.grants("robot_a", Grants([TALKER]))
    assert grants.allows("publish", "/talker", "/chatter", "std_msgs/String")
    assert not grants.allows("publish", "/talker", "/cmd_vel", "geometry_msgs/Twist")
    assert not grants.types_for("call", "/client", "/srv")
    assert [r["allowed"] for r in s.table.due(NOW)] == [True]
    assert s.table.learned() == []


def test_while_its_own_manager_learns_what_no_grant_covers_is_let_through_and_recorded():
    s, clock = state(learning={"robot_a": NOW + 60})
    grants = s.grants("robot_a", Grants())
    check_master_call("registerPublisher", ("/intruder", "/cmd_vel", "geometry_msgs/Twist", "http://x:1/"),
                      manager="robot_a", grants=grants, owners={})
    assert grants.types_for("call", "/client", "/srv") is ANY_TYPES
    assert check_service_client_header({"callerid": "/client", "service": "/srv", "md5sum": "*"}, grants=grants)
    assert grants.param_allows("write", "/conf", "/fleet/speed")
    learned = {(r["action"], r["node"], r["name"], r["type"]) for r in s.table.learned()}
    assert learned == {("publish", "/intruder", "/cmd_vel", "geometry_msgs/Twist"), ("call", "/client", "/srv", None),
                       ("write_param", "/conf", "/fleet/speed", None)}
    # a name another manager may hold is never widened: ownership is the registry's
    assert not grants.names_node_exactly("/intruder")
    # the window ends by itself
    clock.now = NOW + 61
    assert not grants.allows("publish", "/intruder", "/cmd_vel", "geometry_msgs/Twist")


def test_a_peer_is_widened_only_while_both_learn_or_at_the_masters_interceptor():
    s, _ = state(learning={"robot_b": NOW + 60})
    peer = s.grants("robot_b", Grants())
    assert not peer.allows("subscribe", "/listener", "/chatter", "std_msgs/String")  # we do not learn
    s.windows = {"robot_b": NOW + 60, "robot_a": NOW + 60}
    assert peer.allows("subscribe", "/listener", "/chatter", "std_msgs/String")
    assert s.table.learned() == []  # a peer's requests are its own interceptor's to record
    master, _ = state("master", master=True, learning={"robot_b": NOW + 60})
    assert master.grants("robot_b", Grants()).allows("publish", "/talker", "/chatter", "std_msgs/String")
    assert not master.grants("robot_c", Grants()).allows("publish", "/talker", "/chatter", "std_msgs/String")


def test_the_observation_table_is_bounded_and_a_failed_report_is_due_again():
    table = ObservationTable(max_keys=2, used_every=300)
    for i in range(5):
        table.record(Seen(False, "publish", f"/n{i}", "/t", "std_msgs/String"), NOW)
    assert table.dropped == 3
    rows = table.due(NOW)
    assert len(rows) == 2 and table.due(NOW) == []
    table.unreport(rows)
    assert [r["count"] for r in table.due(NOW)] == [1, 1]
    used = Seen(True, "publish", "/n9", "/t", "std_msgs/String")
    table = ObservationTable(max_keys=4, used_every=300)
    table.record(used, NOW)
    assert len(table.due(NOW)) == 1
    table.record(used, NOW + 1)
    assert table.due(NOW + 1) == []  # a used key is reported again only after used_every
    assert len(table.due(NOW + 301)) == 1


def obs(action, node, name, type_=None, *, manager="robot_a", allowed=False, count=1, last=NOW):
    return ObservationRow(manager, allowed, action, node, name, type_, count, int(NOW) - 10, int(last))


def test_a_proposal_is_the_smallest_set_of_exact_grants():
    learned = [
        obs("publish", "/talker", "/chatter", "std_msgs/String", count=40),
        obs("publish", "/talker", "/rosout", "rosgraph_msgs/Log"),  # ROS's own: the node is named otherwise
        obs("serve", "/server", "/srv"),  # a registration tells no type...
        obs("serve", "/server", "/srv", "roscpp/GetLoggers"),  # ...its stream does
        obs("call", "/client", "/srv"),  # the type the server's side told
        obs("call", "/client", "/other"),  # nothing knows its type: reported, not guessed
        obs("subscribe", "/rostopic_4711_1795000000000", "/chatter", "std_msgs/String"),
        obs("write_param", "/roslaunch", "/roslaunch/uris/host_10_0_0_1__41234"),
        obs("write_param", "/conf", "/fleet/speed"),
        obs("read_param", "/conf", "/fleet/speed"),  # covered by its write
        obs("read_param", "/conf", "/fleet/mode"),
        obs("publish", "/held", "/held", "std_msgs/String"),  # granted already
    ]
    current = [GrantRow("publish", "/held", "/held", "std_msgs/String")]
    proposal = propose("robot_a", learned, current, known_types(learned, current))
    grants = {(p.grant.action, p.grant.node, p.grant.name, p.grant.type) for p in proposal.grants}
    assert grants == {
        ("publish", "/talker", "/chatter", "std_msgs/String"),
        ("serve", "/server", "/srv", "roscpp/GetLoggers"),
        ("call", "/client", "/srv", "roscpp/GetLoggers"),
        ("subscribe", "/rostopic_*", "/chatter", "std_msgs/String"),
        ("write_param", "/roslaunch", "/roslaunch/uris", "param"),
        ("write_param", "/conf", "/fleet/speed", "param"),
        ("read_param", "/conf", "/fleet/mode", "param"),
    }
    assert len(proposal.notes) == 1 and "/other" in proposal.notes[0]
    text = proposal_yaml(proposal)
    assert "seen 40 times" in text and "covers /rostopic_4711_1795000000000 /chatter" in text
    import yaml

    from authz_server.registry import parse_policy

    assert len(parse_policy(yaml.safe_load(text))["robot_a"].grants) == 7  # what `import --merge` reads


def test_a_proposal_keeps_names_that_end_in_a_number_exact():
    """Policy audit: a stable node name ending in ``_NNNN`` or ``-NNNN`` became a pattern
    (``/robot_1001`` -> ``/robot_*``) and a key whose last part did became its parent
    (``/fleet/zone_1234`` -> write_param ``/fleet``). Only what ROS makes anew each run
    (an anonymous node, roslaunch's server port) is widened."""
    learned = [
        obs("publish", "/robot_1001", "/robot_1001/odom", "nav_msgs/Odometry"),
        obs("publish", "/robot1/lidar_2048", "/robot1/points", "sensor_msgs/PointCloud2"),
        obs("subscribe", "/cam-0001", "/robot1/scan", "sensor_msgs/LaserScan"),
        obs("read_param", "/robot1/move_base", "/robot1/move_base/planner_2024"),
        obs("write_param", "/robot1/move_base", "/fleet/zone_1234"),
        obs("subscribe", "/rostopic_4711_1795791784006", "/robot1/scan", "sensor_msgs/LaserScan"),
        obs("subscribe", "/record_1795791784006123456", "/robot1/scan", "sensor_msgs/LaserScan"),
        obs("write_param", "/rosparam-12", "/robot1/mode"),
        obs("write_param", "/roslaunch", "/roslaunch/uris/host_robot1__38217"),
        obs("write_param", "/conf", "/fleet/seen/rostopic_4711_1795791784006"),
    ]
    proposal = propose("robot_a", learned, [], known_types(learned, []))
    assert {(p.grant.action, p.grant.node, p.grant.name) for p in proposal.grants} == {
        ("publish", "/robot_1001", "/robot_1001/odom"),
        ("publish", "/robot1/lidar_2048", "/robot1/points"),
        ("subscribe", "/cam-0001", "/robot1/scan"),
        ("read_param", "/robot1/move_base", "/robot1/move_base/planner_2024"),
        ("write_param", "/robot1/move_base", "/fleet/zone_1234"),
        ("subscribe", "/rostopic_*", "/robot1/scan"),
        ("subscribe", "/record_*", "/robot1/scan"),
        ("write_param", "/rosparam-*", "/robot1/mode"),
        ("write_param", "/roslaunch", "/roslaunch/uris"),
        ("write_param", "/conf", "/fleet/seen"),
    }


def test_a_proposal_never_asks_for_what_ros_does_on_a_nodes_behalf():
    """Policy audit: every node's logger services, registered without a type, came out as
    notes asking the operator to grant them by hand (``grant robot_a serve /lidar_2048
    /lidar_2048/get_loggers TYPE``), though they need no grant once the node is named."""
    learned = [
        obs("publish", "/lidar_2048", "/robot1/points", "sensor_msgs/PointCloud2"),
        obs("publish", "/lidar_2048", "/rosout", "rosgraph_msgs/Log"),
        obs("serve", "/lidar_2048", "/lidar_2048/get_loggers"),  # a registration tells no type
        obs("serve", "/lidar_2048", "/lidar_2048/set_logger_level"),
        obs("subscribe", "/rostopic_4711_1795791784006", "/robot1/points", "sensor_msgs/PointCloud2"),
        obs("serve", "/rostopic_4711_1795791784006", "/rostopic_4711_1795791784006/get_loggers"),
        # a node that does nothing else keeps them, with the library's types: they name it
        obs("serve", "/idle", "/idle/get_loggers"),
        obs("serve", "/idle", "/idle/set_logger_level"),
        # another service under a node's name is no library's: its type is still asked for
        obs("serve", "/lidar_2048", "/lidar_2048/calibrate"),
    ]
    proposal = propose("robot_a", learned, [], known_types(learned, []))
    assert len(proposal.notes) == 1 and "/lidar_2048/calibrate: type not seen" in proposal.notes[0], proposal.notes
    assert {(p.grant.action, p.grant.node, p.grant.name, p.grant.type) for p in proposal.grants} == {
        ("publish", "/lidar_2048", "/robot1/points", "sensor_msgs/PointCloud2"),
        ("subscribe", "/rostopic_*", "/robot1/points", "sensor_msgs/PointCloud2"),
        ("serve", "/idle", "/idle/get_loggers", "roscpp/GetLoggers"),
        ("serve", "/idle", "/idle/set_logger_level", "roscpp/SetLoggerLevel"),
    }


def test_unused_lists_the_grants_no_allowed_request_fell_under():
    grants = [GrantRow("publish", "/talker", "/chatter", "std_msgs/String"),
              GrantRow("subscribe", "*", "/chatter", "std_msgs/String"),
              GrantRow("write_param", "/conf", "/fleet", "param"),
              GrantRow("read_param", "/conf", "/other", "param")]
    used = [obs("publish", "/talker", "/chatter", "std_msgs/String", allowed=True),
            obs("subscribe", "/anyone", "/chatter", "std_msgs/String", allowed=True),
            obs("read_param", "/conf", "/fleet/speed", allowed=True)]
    assert unused(grants, used) == [GrantRow("read_param", "/conf", "/other", "param")]


@pytest.mark.parametrize("row", [
    {"allowed": "yes"}, {"action": "shutdown"}, {"node": "no slash"}, {"node": "*"}, {"node": "/rosparam-*"},
    {"node": "/rosparam--1 x"}, {"name": "bad name!"}, {"type": "not a type"},
    {"count": 0}, {"count": True}, {"first": NOW - 3 * 86400}, {"first": NOW + 5, "last": NOW},
    {"action": "read_param", "type": "std_msgs/String"}, {"extra": 1},
])
def test_a_report_with_any_bad_row_is_refused_whole(row):
    good = {"allowed": False, "action": "publish", "node": "/n", "name": "/t", "type": "std_msgs/String",
            "count": 1, "first": NOW, "last": NOW}
    assert checked_observations({"observations": [good]}, now=NOW)[0]["node"] == "/n"
    with pytest.raises(RegistryError):
        checked_observations({"observations": [good, {**good, **row}]}, now=NOW)
    with pytest.raises(RegistryError):
        checked_observations({"observations": [good] * (MAX_OBSERVATION_ROWS + 1)}, now=NOW)


@pytest.mark.parametrize("node", ["/rosparam-10865", "/rostopic_123_1700000000000", "/robot1/cam-driver", "/talker"])
def test_a_reported_node_is_a_caller_id_as_the_interceptor_records_it(node):
    """Stock tools run as ``/rosparam-<pid>``: the interceptor accepts that caller ID
    (and grant-tools grants ``/rosparam-*``), so the server takes a report of it."""
    row = {"allowed": True, "action": "read_param", "node": node, "name": "/fleet", "type": None,
           "count": 1, "first": NOW, "last": NOW}
    assert checked_observations({"observations": [row]}, now=NOW)[0]["node"] == node
    assert granted(Grants([Grant(node="/rosparam-*", action="read_param", name="/", type="param")]),
                   {**row, "node": "/rosparam-10865"})


class _Server:
    """``POST /observations`` as the authorization server answers it: a report with a
    malformed row refused whole (HTTP 400), every row of a good one kept."""

    def __init__(self) -> None:
        self.kept: list[dict] = []
        self.posts = 0

    async def answer(self, method: str, path: str, *, json: dict, **_kw):
        assert (method, path) == ("POST", "/observations")
        self.posts += 1
        try:
            rows = checked_observations(json, now=time.time())
        except RegistryError as exc:
            return 400, {"error": "invalid_request", "error_description": str(exc)}, {}
        self.kept += rows
        return 200, {"accepted": len(rows), "refused": 0}, {}


def learner_reporting_to(server: _Server):
    """A Learner whose AuthzClient's requests are answered by ``server`` (no network)."""
    client = AuthzClient(AuthzSettings(url="https://authz.invalid:8443"), ssl.create_default_context())
    client._json = server.answer
    return Learner("robot_a", serves_everyone=False, authz=client, registry=CollectorRegistry())


async def test_stock_tools_rows_are_reported_and_not_queued_again():
    server = _Server()
    learner = learner_reporting_to(server)
    now = time.time()
    for node in ("/rosparam-10865", "/talker", "/rostopic_4711_1700000000000"):
        learner.state.table.record(Seen(True, "read_param", node, "/fleet/speed", None), now)
    await learner.report()
    assert sorted(r["node"] for r in server.kept) == ["/rosparam-10865", "/rostopic_4711_1700000000000", "/talker"]
    assert learner.reported == 3 and learner.refused == 0
    assert learner.state.table.due(now + 3600) == []  # nothing put back


async def test_a_row_the_server_refuses_as_malformed_is_dropped_and_the_others_still_reported(caplog):
    """One malformed row (here a name the server's rules refuse) does not hold back the
    rest forever: the refused report is halved until that row stands alone; it is
    dropped with one warning, the others are kept by the server, nothing is due again."""
    server = _Server()
    learner = learner_reporting_to(server)
    now = time.time()
    good = [Seen(False, "publish", f"/n{i}", "/chatter", "std_msgs/String") for i in range(9)]
    bad = Seen(False, "publish", "/n_bad", "/not-a-topic", "std_msgs/String")
    for seen in [*good[:4], bad, *good[4:]]:
        learner.state.table.record(seen, now)
    with caplog.at_level(logging.WARNING, logger="interceptor.learning"):
        await learner.report()
    assert sorted(r["node"] for r in server.kept) == sorted(s.node for s in good)
    assert learner.reported == 9 and learner.refused == 1
    assert learner.state.table.due(now + 1) == []
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "/not-a-topic" in warnings[0] and "dropped" in warnings[0], warnings
    posts = server.posts
    await learner.report()  # nothing left to send
    assert server.posts == posts


async def test_a_report_the_server_cannot_take_now_is_kept_for_the_next():
    server = _Server()
    learner = learner_reporting_to(server)

    async def down(*_args, **_kw):
        raise AuthzUnavailable("connection refused")

    learner._authz._json = down
    now = time.time()
    learner.state.table.record(Seen(False, "publish", "/n", "/chatter", "std_msgs/String"), now)
    await learner.report()
    assert [r["node"] for r in learner.state.table.due(now + 1)] == ["/n"]


def test_a_used_row_is_kept_only_under_a_grant_the_manager_holds():
    grants = Grants([TALKER, Grant(node="/conf", action="write_param", name="/fleet", type="param")])
    row = {"action": "publish", "node": "/talker", "name": "/chatter", "type": "std_msgs/String"}
    assert granted(grants, row)
    assert not granted(grants, {**row, "name": "/cmd_vel"}) and not granted(grants, {**row, "type": None})
    assert granted(grants, {"action": "read_param", "node": "/conf", "name": "/fleet/speed", "type": None})
    assert not granted(grants, {"action": "write_param", "node": "/other", "name": "/fleet/speed", "type": None})


def test_the_masters_interceptor_never_widens_a_learner_over_another_managers_parameters():
    """A learning robot may read and write, without a grant, what it or other learning
    managers set; never a value a manager that enforces set (its secrets stay its own)."""
    from cryptoros.policy.ros1 import filter_param_reply

    s, _ = state("master", master=True, learning={"robot_b": NOW + 60})
    owners = {"/robot_a/secret": {"robot_a"}, "/fleet/speed": {"robot_b"}, "/": {"robot_a", "robot_b"},
              "/robot_a": {"robot_a"}, "/fleet": {"robot_b"}}
    s.param_owners = lambda key: frozenset(owners.get(key, ()))
    learner = s.grants("robot_b", Grants())
    assert learner.param_allows("read", "/n", "/fleet/speed") and learner.param_allows("write", "/n", "/new/key")
    assert not learner.param_allows("read", "/n", "/robot_a/secret")
    assert not learner.param_allows("write", "/n", "/robot_a/secret")
    tree = {"robot_a": {"secret": "s3cr3t"}, "fleet": {"speed": 3}}
    reply = filter_param_reply("getParam", ("/n", "/"), [1, "", tree], grants=learner)
    assert reply[2] == {"fleet": {"speed": 3}}  # robot A's value pruned from the learner's read
    s.windows = {"robot_b": NOW + 60, "robot_a": NOW + 60}  # both learn: both are let through
    assert learner.param_allows("read", "/n", "/robot_a/secret")


def test_parameter_owners_are_those_of_the_key_what_lies_below_it_and_a_value_above_it():
    from interceptor.param_quota import ParamQuota

    quota = ParamQuota(100, 1 << 20)
    quota.set("robot_a", "/robot_a/secret", "s")
    quota.set("robot_b", "/fleet", {"speed": 3})
    assert quota.owners("/robot_a/secret") == {"robot_a"}
    assert quota.owners("/") == {"robot_a", "robot_b"}
    assert quota.owners("/fleet/speed") == {"robot_b"}  # inside a value robot B set
    assert quota.owners("/nothing/here") == frozenset()


async def test_an_outage_is_logged_once_not_at_every_report(caplog):
    """ROS 2 audit: "observations not reported yet" was logged every 5 s through an
    authorization server outage. Once when reports start failing, once when they work again."""
    from cryptoros.errors import TokenError

    class Down:
        fail = 3

        async def post_observations(self, batch):
            if self.fail:
                self.fail -= 1
                raise TokenError("no_token", "this interceptor holds no valid access token")
            return {"accepted": len(batch)}

    learner = Learner("robot_a", serves_everyone=False, authz=Down(), registry=CollectorRegistry())
    now = time.time()
    learner.state.table.record(Seen(True, "publish", "/talker", "/chatter", "std_msgs/String"), now)
    caplog.set_level(logging.INFO, logger="interceptor.learning")
    for _ in range(4):
        learner.state.table.record(Seen(True, "publish", "/talker", "/chatter", "std_msgs/String"), now + 3600)
        await learner.report()
    said = [r.getMessage() for r in caplog.records]
    assert sum("observations not reported yet" in m for m in said) == 1, said
    assert sum("observations reported again" in m for m in said) == 1, said
    assert learner.reported >= 1
