"""Issue 11, findings 1 and 4: parameter calls bind names and read secrets; against real
rosmaster, rospy and Debian's rosparam behind real interceptors.

The insider is robot B (valid certificate, subscribe grants on /chatter, no parameter
grants); robot A runs the talker and owns ``/robot_a``; an operator's
``/secrets/db_password`` sits in rosmaster. Around each attack robot A's ``/flow``
keeps reaching robot C (tests/ros1_flow.py): never silent 5 s during it, back within
5 s after.
"""

from __future__ import annotations

import json
import time
import urllib.request
import xmlrpc.client

import pytest

from tests.interceptor_harness import (
    NODE,
    SYS_PY,
    robot_network,
    rogue_preamble,
    rogue_tls,
    rogue_xmlrpc,
    separate_hosts,
    token_of,
    wait_registered,
)
from tests.support import require, run, running, until
from tests.interceptor_harness import got, master_state, nodes_in_state, read_lines
from tests.ros1_flow import flow_policy, legit_flow

pytestmark = [pytest.mark.ros1]


@pytest.fixture(scope="module")
def network(tmp_path_factory):
    # rosmaster's answers read up to 2 MiB (default 64 MiB): the multicall test's four reads are over it together
    with robot_network(tmp_path_factory.mktemp("params"), start=("master", "robot_a", "robot_b", "robot_c"),
                       policy=flow_policy(), netns=separate_hosts(),
                       extra={"master": f"[limits]\nmax_master_reply = {2 << 20}\n"}) as net:
        with net.inside("master"):
            master = xmlrpc.client.ServerProxy(net.rosmaster_uri)
            master.setParam("/operator", "/robot_a/api_key", "A-KEY-123")
            master.setParam("/operator", "/secrets/db_password", "hunter2")
            master.setParam("/operator", "/shared/map_size", 42)
        yield net


@pytest.fixture(scope="module")
def flow(network):
    """Robot A's /flow to robot C's listener: two honest robots, through the master the
    insider's parameter calls go to."""
    with legit_flow(network, "robot_a", "robot_c") as running_flow:
        yield running_flow


def test_subscribe_param_cannot_rebind_another_robots_node(network, flow):
    with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "40"], env=network.ros_env("robot_a")) as pub:
        read_lines(pub, "READY", 20)
        wait_registered(network, "/talker_a")
        local_b = xmlrpc.client.ServerProxy(network.hosts["robot_b"].master_uri)
        # on the insider's own local master port, and by hand over a master stream
        with flow.held(), network.inside("robot_b"):
            # (a key every node may read: an unreadable one would be answered as unset, unforwarded)
            assert local_b.subscribeParam("/talker_a", "http://127.0.0.1:9/", "/use_sim_time")[0] == -1
        b = network.hosts["robot_b"]
        m = network.hosts["master"]
        with flow.held(), rogue_tls(m.address, m.public_port, ca=network.pki.ca_cert, cert=network.pki.pki.cert_path_for("robot_b"),
                       key=network.pki.pki.key_path_for("robot_b")) as s:
            assert rogue_preamble(s, token_of(network, "robot_b"), "master").ok
            reply = rogue_xmlrpc(s, "subscribeParam", "/talker_a", f"cryptoros://{b.address}:{b.public_port}/x/1", "/x")
        assert reply.value[0] == -1
        # /talker still publishes: a new subscriber receives
        with running([SYS_PY, NODE, "sub", "/rospy_listener", "/chatter", "30"], env=network.ros_env("robot_b")) as sub:
            read_lines(sub, "READY", 20)
            assert got(read_lines(sub, "GOT", 20))
        assert "/talker_a" in nodes_in_state(master_state(network))
        assert pub.poll() is None
    log = network.hosts["master"].logs() + network.hosts["robot_b"].logs()
    assert "name_taken" in log or "is not one of its nodes" in log


def test_parameter_reads_are_narrowed_to_what_the_caller_may_read(network, flow):
    with flow.held(), network.inside("robot_b"):
        _narrowed_reads(network)
    log = network.hosts["robot_b"].logs()
    assert "param_read_denied" in log and "param_write_denied" in log


def _narrowed_reads(network):
    local_b = xmlrpc.client.ServerProxy(network.hosts["robot_b"].master_uri)
    code, _, tree = local_b.getParam("/rospy_listener", "/")
    assert code == 1
    assert "api_key" not in repr(tree) and "hunter2" not in repr(tree) and "secrets" not in tree
    assert local_b.getParam("/rospy_listener", "/secrets/db_password")[0] == -1
    assert local_b.getParam("/rospy_listener", "/robot_a")[0] == -1
    # a probe of what it may not read is answered as if unset (whether it is set is not told)
    assert local_b.hasParam("/rospy_listener", "/secrets/db_password") == [1, "/secrets/db_password", False]
    code, _, names = local_b.getParamNames("/rospy_listener")
    assert code == 1 and not [n for n in names if n.startswith(("/secrets", "/robot_a"))]
    assert local_b.searchParam("/rospy_listener", "secrets")[0] == -1
    assert local_b.subscribeParam("/rospy_listener", "http://127.0.0.1:9/", "/secrets") == \
        [1, "Subscribed to parameter [/secrets]", {}]
    # what every node may read, and its own private namespace
    assert local_b.getParam("/rospy_listener", "/rosdistro")[0] in (1, -1)  # set by roscore, not rosmaster --core
    assert local_b.setParam("/rospy_listener", "~rate", 5)[0] == 1
    assert local_b.getParam("/rospy_listener", "/rospy_listener/rate") == [1, "Parameter [/rospy_listener/rate]", 5]
    # writes outside the caller's namespace are refused with a ROS error, and nothing is written
    # (robot B's own node is pointed at cryptoros denials, where the grant is named)
    assert local_b.setParam("/rospy_listener", "/robot_a/api_key", "pwned") == \
        [-1, "denied by cryptoros: param_write_denied (cryptoros denials says what to grant)", 0]
    with network.inside("master"):
        master = xmlrpc.client.ServerProxy(network.rosmaster_uri)
        assert master.getParam("/operator", "/robot_a/api_key")[2] == "A-KEY-123"


def test_rosparam_set_get_and_list_work_with_a_grant(network, flow):
    require("rosparam")
    network.cli("grant", "robot_b", "write_param", "*", "/shared")
    env = network.ros_env("robot_b")
    deadline = time.monotonic() + 15
    while True:  # the grant reaches robot B's interceptor within seconds (no SIGHUP)
        result = run(["rosparam", "set", "/shared/speed", "3"], env=env, timeout=30)
        if result.returncode == 0:
            break
        assert time.monotonic() < deadline, result.stdout + result.stderr
        time.sleep(0.5)
    got_value = run(["rosparam", "get", "/shared/speed"], env=env, timeout=30)
    assert got_value.returncode == 0 and got_value.stdout.strip() == "3"
    listed = run(["rosparam", "list"], env=env, timeout=30)
    assert listed.returncode == 0 and "/shared/speed" in listed.stdout and "/secrets/db_password" not in listed.stdout
    with flow.held("a refused rosparam set"):
        denied = run(["rosparam", "set", "/secrets/db_password", "x"], env=env, timeout=30)
    assert denied.returncode != 0
    with network.inside("master"):
        assert xmlrpc.client.ServerProxy(network.rosmaster_uri).getParam("/o", "/secrets/db_password")[2] == "hunter2"


SET_PARAM_NODE = """
import sys, rospy
rospy.init_node("rospy_listener", disable_signals=True)
rospy.set_param("~rate", 5)
print("OWN_OK", flush=True)
try:
    rospy.set_param(sys.argv[1], "pwned")
    print("WROTE", flush=True)
except Exception as exc:
    print("REFUSED", type(exc).__name__, exc, flush=True)
"""


def test_a_denied_parameter_write_of_an_unmodified_rospy_node_writes_nothing_and_is_logged(network, flow):
    """A refused write is answered as rosmaster answers an error ([-1, "denied by
    cryptoros: param_write_denied", 0], never a fault, which tools print as a
    traceback). rospy's set_param ignores that answer, as it ignores any error of
    rosmaster's: nothing is written, and the interceptor's log names the grant."""
    with flow.held("a refused parameter write"):
        result = run([SYS_PY, "-c", SET_PARAM_NODE, "/robot_a/api_key"], env=network.ros_env("robot_b"), timeout=60)
    assert "OWN_OK" in result.stdout, result.stdout + result.stderr
    assert "Traceback" not in result.stdout + result.stderr
    assert "to allow: cryptoros-authz grant robot_b write_param /rospy_listener /robot_a/api_key" in \
        network.hosts["robot_b"].logs()
    with network.inside("master"):
        assert xmlrpc.client.ServerProxy(network.rosmaster_uri).getParam("/operator", "/robot_a/api_key")[2] == "A-KEY-123"


@pytest.mark.timeout(180)
def test_node_apis_that_never_answer_do_not_hold_rosmasters_notifications_for_others(network, flow):
    """Insider audit: rosmaster sends publisherUpdate and paramUpdate from three worker
    threads. Robot B subscribes three of its nodes' own parameters with APIs that accept
    and never answer, and re-arms them with allowed writes twice a second: relayed
    straight, each notification held a worker for 30 s, and robot A's new subscriber
    never heard of its publisher (100 s). The master's interceptor now answers rosmaster
    at once and delivers per node API (interceptor/ros1/notices.py)."""
    import socket
    import threading

    held: list[socket.socket] = []
    servers: list[socket.socket] = []
    stop = threading.Event()
    nodes = ["/rospy_listener", "/victim", "/rospy_client"]  # named in robot B's grants (robot A's /victim idle)
    with network.inside("robot_b"):
        local_b = xmlrpc.client.ServerProxy(network.hosts["robot_b"].master_uri)
        for node in nodes:
            server = socket.create_server(("127.0.0.1", 0), backlog=64)
            servers.append(server)

            def hold(server=server) -> None:
                while not stop.is_set():
                    try:
                        held.append(server.accept()[0])  # read nothing, answer nothing
                    except OSError:
                        return

            threading.Thread(target=hold, daemon=True).start()
            assert local_b.subscribeParam(node, f"http://127.0.0.1:{server.getsockname()[1]}/", "~stall")[0] == 1

    def rearm() -> None:
        with network.inside("robot_b"):
            writer = xmlrpc.client.ServerProxy(network.hosts["robot_b"].master_uri)
            i = 0
            while not stop.wait(0.5):  # rosmaster does not notify the writer itself: a sibling writes
                for k, node in enumerate(nodes):
                    writer.setParam(nodes[k - 1], f"{node}/stall", i)
                i += 1

    network.cli("grant", "robot_a", "subscribe", "/notified_a", "/chatter", "std_msgs/String")
    attacker = threading.Thread(target=rearm, daemon=True)
    attacker.start()
    try:
        with flow.held():
            until(lambda: len(held) >= 3, 20, "robot B's three node APIs called")
            # robot A: a subscriber first, then its publisher: rosmaster tells the subscriber
            with running([SYS_PY, NODE, "sub", "/notified_a", "/chatter", "60"], env=network.ros_env("robot_a")) as sub:
                read_lines(sub, "READY", 20)
                with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "60"],
                             env=network.ros_env("robot_a")) as pub:
                    read_lines(pub, "READY", 20)
                    assert got(read_lines(sub, "GOT", 20)), "robot A's subscriber never heard of its publisher"
    finally:
        stop.set()
        attacker.join(10)
        network.cli("revoke", "robot_a", "subscribe", "/notified_a", "/chatter", "std_msgs/String")
        for sock in (*servers, *held):
            sock.close()
    with network.inside("master"):
        url = f"http://127.0.0.1:{network.hosts['master'].metrics_port}/status"
        with urllib.request.urlopen(url, timeout=5) as reply:
            notices = json.loads(reply.read())["ros1"]["notices"]
    assert notices["delivered"] >= 1 and notices["replaced"] >= 1, notices


def test_an_insiders_stored_values_cost_rosmaster_one_value_a_read_and_others_nothing(network, flow):
    """Insider audit: rosmaster builds a multicall's whole answer before the interceptor
    checks a byte of it (96 reads of the insider's own 3.6 MB took rosmaster to 716 MB),
    and its answers were read up to 1 MiB only, so 1.4 MB in the insider's own namespace
    made every honest robot's ``getParam('/')`` fail. Reads in a multicall now reach
    rosmaster one at a time, and its answers are read up to ``max_master_reply`` (2 MiB
    here) and then pruned."""
    from tests.ros1_flow import listener_name

    blob = "x" * 700_000
    m = network.hosts["master"]
    keys = ["/rospy_listener/blob1", "/rospy_listener/blob2"]
    with flow.held(), rogue_tls(m.address, m.public_port, ca=network.pki.ca_cert,
                                cert=network.pki.pki.cert_path_for("robot_b"),
                                key=network.pki.pki.key_path_for("robot_b")) as s:
        assert rogue_preamble(s, token_of(network, "robot_b"), "master").ok
        try:
            for key in keys:
                assert rogue_xmlrpc(s, "setParam", "/rospy_listener", key, blob).value[0] == 1
            # four reads: 2.8 MB together, over max_master_reply; 700 kB each
            calls = [{"methodName": "getParam", "params": ["/rospy_listener", keys[i % 2]]} for i in range(4)]
            calls.insert(2, {"methodName": "hasParam", "params": ["/rospy_listener", keys[0]]})
            answers = rogue_xmlrpc(s, "system.multicall", calls).value
            # names too: 8 lists of 3,000 long names, 2.5 MB together, each alone under the limit
            names = {f"n{i:04d}_" + "x" * 90: i for i in range(3000)}
            assert rogue_xmlrpc(s, "setParam", "/rospy_listener", "/rospy_listener/names", names).value[0] == 1
            keys.append("/rospy_listener/names")
            listed = rogue_xmlrpc(s, "system.multicall",
                                  [{"methodName": "getParamNames", "params": ["/rospy_listener"]}] * 8).value
            # an honest robot's read of the whole tree, pruned to what it may read
            with network.inside("robot_c"):
                local_c = xmlrpc.client.ServerProxy(network.hosts["robot_c"].master_uri)
                code, _, tree = local_c.getParam(listener_name("robot_c"), "/")
        finally:
            for key in keys:
                rogue_xmlrpc(s, "deleteParam", "/rospy_listener", key)
    assert [a[0][0] for a in answers] == [1] * 5, [repr(a)[:200] for a in answers]
    assert [a[0][2] for a in answers] == [blob, blob, True, blob, blob]
    assert all(a[0][0] == 1 and len(a[0][2]) > 3000 for a in listed), [repr(a)[:200] for a in listed]
    assert code == 1 and "rospy_listener" not in tree and "hunter2" not in repr(tree)
