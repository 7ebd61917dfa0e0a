"""``cryptoros-authz policy from-graph`` against a real rosmaster and real rospy nodes.

A plain ROS 1 graph (no cryptoros yet): a talker, a listener, a service server, a
node no --manager-map entry names, parameters private and shared. The draft holds
exactly that graph's nodes, topics, types and served service (found by the TCPROS
probe, as ``rosservice type`` does), each node under its mapped manager; what it
cannot show is a warning. Imported with ``cryptoros-authz import`` it exports back
unchanged, and with certificates added it is the policy of a robot network behind
interceptors where the same nodes run and the unmapped one is refused.
"""

from __future__ import annotations

import contextlib
import time
import xmlrpc.client
from pathlib import Path

import pytest
import yaml

from tests.authz_support import authz, ok
from tests.interceptor_harness import NODE, NODES, SYS_PY, denials, got, read_lines, robot_network, wait_registered
from tests.support import free_port, require, run, running, script, wait_for_port

pytestmark = [pytest.mark.ros1]

MAP = ["--manager-map", "/talker_a=robot_a", "--manager-map", "/rospy_server=robot_a",
       "--manager-map", "/rospy_l*=robot_b"]

EXPECTED = {"version": 1, "managers": [
    {"name": "robot_a", "fingerprint_sha256": None, "enabled": True, "grants": {
        "publish": [{"node": "/talker_a", "topic": "/chatter", "type": "std_msgs/String"}],
        "serve": [{"node": "/rospy_server", "service": "/rospy_loggers", "type": "roscpp/GetLoggers"}],
        "read_param": [{"node": "/talker_a", "namespace": "/talker_a"}],
    }},
    {"name": "robot_b", "fingerprint_sha256": None, "enabled": True, "grants": {
        "subscribe": [{"node": "/rospy_listener", "topic": "/chatter", "type": "std_msgs/String"}],
    }},
]}


def ros_env(tmp_path: Path, master_uri: str) -> dict[str, str]:
    import os

    return {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "ROS_MASTER_URI": master_uri, "ROS_IP": "127.0.0.1",
            "ROS_HOME": str(tmp_path), "PYTHONUNBUFFERED": "1"}


def wait_nodes(master_uri: str, nodes: set[str], timeout: float = 40) -> None:
    deadline = time.monotonic() + timeout
    master = xmlrpc.client.ServerProxy(master_uri)
    while True:
        state = master.getSystemState("/test")[2]
        seen = {n for section in state for _name, ns in section for n in ns}
        services = {name for name, _ns in state[2]}
        if nodes <= seen and "/rospy_loggers" in services:
            return
        assert time.monotonic() < deadline, f"never registered: {nodes - seen}"
        time.sleep(0.1)


@contextlib.contextmanager
def plain_graph(tmp_path: Path):
    """rosmaster and the nodes, no cryptoros anywhere."""
    rosmaster = require("rosmaster")["rosmaster"]
    port = free_port()
    uri = f"http://127.0.0.1:{port}"
    env = ros_env(tmp_path, uri)
    with running([rosmaster, "--core", "-p", str(port)], env=env) as master:
        wait_for_port("127.0.0.1", port, 20, master)
        proxy = xmlrpc.client.ServerProxy(uri)
        proxy.setParam("/test", "/talker_a/rate", 5)
        proxy.setParam("/test", "/talker_a/frame/id", "base")
        proxy.setParam("/test", "/robot_description", "<robot/>")
        with running([SYS_PY, NODE, "sub", "/rospy_listener", "/chatter", "60"], env=env), \
                running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "5", "1"], env=env), \
                running([SYS_PY, NODE, "sub", "/stray", "/other", "60"], env=env), \
                running([SYS_PY, str(NODES / "services.py"), "serve"], env=env):
            wait_nodes(uri, {"/rospy_listener", "/talker_a", "/stray", "/rospy_server"})
            yield uri


def test_the_draft_is_exactly_the_graph_and_round_trips_through_import(tmp_path):
    with plain_graph(tmp_path) as uri:
        draft = tmp_path / "draft.yaml"
        r = run([script("cryptoros-authz"), "policy", "from-graph", "--master-uri", uri, *MAP, "-o", str(draft)],
                timeout=60)
    assert r.returncode == 0, r.stderr
    text = draft.read_text()
    assert text.startswith(f"# draft policy from the ROS 1 graph at {uri}")
    assert yaml.safe_load(text) == EXPECTED
    warnings = [line for line in r.stderr.splitlines() if line.startswith("cryptoros-authz: warning: ")]
    assert any("node /stray matches no --manager-map entry: granted nothing" in w for w in warnings), r.stderr
    assert any("grant 'call' by hand" in w and "/rospy_loggers [roscpp/GetLoggers]" in w for w in warnings)
    assert any("not granted" in w and "/robot_description" in w for w in warnings)
    assert not any("/rosdistro" in w or "/run_id" in w for w in warnings)  # every node may read those
    # docs/policy.md quotes this line
    assert r.stderr.splitlines()[-1] == ("cryptoros-authz: drafted 4 grant(s) for 2 manager(s) from 4 node(s); 9 left "
                                         "out that ROS has without a grant (/rosout, logger services); 3 warning(s)")
    assert len(warnings) == 3
    # import, export: the same document
    db = f"sqlite:///{tmp_path / 'registry.db'}"
    assert "managers added 2, managers removed 0, managers changed 0, grants added 4" in ok(
        authz("import", str(draft), db=db))
    assert yaml.safe_load(ok(authz("export", db=db))) == EXPECTED


def test_a_master_that_does_not_answer_is_one_error_line(tmp_path):
    port = free_port()
    r = run([script("cryptoros-authz"), "policy", "from-graph", "--master-uri", f"http://127.0.0.1:{port}",
             "--manager-map", "/*=robot_a", "--timeout", "2"], timeout=30)
    assert r.returncode == 2
    assert r.stderr.strip().startswith(f"cryptoros-authz: error: cannot read the graph from http://127.0.0.1:{port}")
    assert len(r.stderr.strip().splitlines()) == 1 and r.stdout == ""
    r = run([script("cryptoros-authz"), "policy", "from-graph", "--master-uri", "http://127.0.0.1:1",
             "--manager-map", "/talker=not a manager"], timeout=30)
    assert r.returncode == 2 and "invalid manager name 'not a manager'" in r.stderr


def test_the_draft_with_certificates_runs_that_graph_behind_interceptors(tmp_path):
    with plain_graph(tmp_path) as uri:
        r = run([script("cryptoros-authz"), "policy", "from-graph", "--master-uri", uri, *MAP], timeout=60)
    assert r.returncode == 0, r.stderr
    doc = yaml.safe_load(r.stdout)
    # the operator adds certificates (the network's own, by placeholder) and the master's manager
    for manager in doc["managers"]:
        manager["fingerprint_sha256"] = "{" + manager["name"] + "}"
    doc["managers"].insert(0, {"name": "master", "fingerprint_sha256": "{master}"})
    policy = yaml.safe_dump(doc, sort_keys=False)
    with robot_network(tmp_path / "net", policy=policy) as network:
        with running([SYS_PY, NODE, "sub", "/rospy_listener", "/chatter", "60"], env=network.ros_env("robot_b")) \
                as listener:
            read_lines(listener, "READY", 30)
            with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "5", "1"],
                         env=network.ros_env("robot_a")):
                assert got(read_lines(listener, "GOT secret-2", 40))[-1] == "secret-2"
        with running([SYS_PY, str(NODES / "services.py"), "serve"], env=network.ros_env("robot_a")) as server:
            read_lines(server, "READY", 30)
            wait_registered(network, "/rospy_server")
        with running([SYS_PY, NODE, "sub", "/stray", "/other", "60"], env=network.ros_env("robot_b")):
            deadline = time.monotonic() + 30
            while "/stray" not in denials(network, "robot_b"):
                assert time.monotonic() < deadline, denials(network, "robot_b")
                time.sleep(0.2)


def test_a_master_answering_garbage_is_one_error_line():
    import threading
    from xmlrpc.server import SimpleXMLRPCServer

    server = SimpleXMLRPCServer(("127.0.0.1", 0), logRequests=False, allow_none=True)
    server.register_function(lambda caller: [1, "", [[["/t", [7]]], [], []]], "getSystemState")
    server.register_function(lambda caller: [1, "", "not a list"], "getTopicTypes")
    server.register_function(lambda caller: [1, "", []], "getParamNames")
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        uri = f"http://127.0.0.1:{server.server_address[1]}"
        r = run([script("cryptoros-authz"), "policy", "from-graph", "--master-uri", uri, "--manager-map", "*=m"],
                timeout=30)
    finally:
        server.shutdown()
        server.server_close()
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.strip() == f"cryptoros-authz: error: {uri} did not answer as a ROS master: expected a string, got int"
