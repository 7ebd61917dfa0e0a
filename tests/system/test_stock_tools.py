"""Issue 13, stock tools: Debian's own rostopic, rosparam, rosservice and rosnode run on
robot B's host against robot B's interceptor, with real rosmaster behind the
master's interceptor and a rospy talker (and service) on robot A.

Refused first (robot B holds no grant for the tools' anonymous node names), then
``cryptoros-authz grant-tools robot_b ...`` (no SIGHUP, no restart) and they work:
``rostopic echo -n 1 /chatter`` receives robot A's talker, ``rosparam set /x 1`` then
``rosparam get /x``, ``rosservice call``, ``rosnode list`` and ``rosnode info``, and
``rosbag record`` (which subscribes with type ``*``) records robot A's talker.
``grant-tools --remove`` takes them away again.
"""

from __future__ import annotations

import subprocess
import time

import pytest

from tests.interceptor_harness import NODE, NODES, SYS_PY, read_lines, robot_network, wait_registered
from tests.support import require, run, running

pytestmark = [pytest.mark.ros1]

#: robot B holds no '*' grant: only its own listener's, and whatever grant-tools adds.
POLICY = """\
version: 1
managers:
- name: master
  fingerprint_sha256: {master}
- name: robot_a
  fingerprint_sha256: {robot_a}
  grants:
    publish:
    - {{node: /talker_a, topic: /chatter, type: std_msgs/String}}
    serve:
    - {{node: /rospy_server, service: /rospy_loggers, type: roscpp/GetLoggers}}
- name: robot_b
  fingerprint_sha256: {robot_b}
  grants:
    subscribe:
    - {{node: /rospy_listener, topic: /chatter, type: std_msgs/String}}
- name: robot_c
  fingerprint_sha256: {robot_c}
"""

GRANT_TOOLS = ("grant-tools", "robot_b", "--topic", "/chatter:std_msgs/String",
               "--service", "/rospy_loggers:roscpp/GetLoggers", "--param-ns", "/")


def tool(net, *argv: str, timeout: float = 20) -> subprocess.CompletedProcess:
    """A stock tool on robot B's host; a tool still waiting at ``timeout`` counts as rc 124."""
    try:
        return run(list(argv), env=net.ros_env("robot_b"), timeout=timeout)
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout.decode(errors="replace") if isinstance(exc.stdout, bytes) else exc.stdout or ""
        return subprocess.CompletedProcess(argv, 124, out, "")


def until_ok(net, *argv: str, within: float, timeout: float = 15) -> subprocess.CompletedProcess:
    """Run the tool again until it succeeds (a grant reaches the interceptors live)."""
    deadline = time.monotonic() + within
    while True:
        result = tool(net, *argv, timeout=timeout)
        if result.returncode == 0:
            return result
        assert time.monotonic() < deadline, f"{argv} still fails: {result.stdout}{result.stderr}"
        time.sleep(0.5)


def test_stock_tools_refused_without_grant_tools_and_working_with_it(tmp_path):
    require("rostopic", "rosparam", "rosnode", "rosservice", "rosbag")
    with robot_network(tmp_path, policy=POLICY, start=("master", "robot_a", "robot_b")) as net, \
            running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "10", "120"],
                    env=net.ros_env("robot_a")) as pub, \
            running([SYS_PY, str(NODES / "services.py"), "serve"], env=net.ros_env("robot_a")) as server:
        read_lines(pub, "READY", 20)
        read_lines(server, "READY", 20)
        wait_registered(net, "/talker_a")
        wait_registered(net, "/rospy_server")

        # --- refused: no grant names the tools' anonymous nodes
        denied_set = tool(net, "rosparam", "set", "/x", "1")
        assert denied_set.returncode != 0, denied_set.stdout
        denied_echo = tool(net, "rostopic", "echo", "-n", "1", "/chatter", timeout=8)
        assert "data:" not in denied_echo.stdout and denied_echo.returncode != 0
        denied_call = tool(net, "rosservice", "call", "/rospy_loggers", timeout=10)
        assert denied_call.returncode != 0 and "loggers" not in denied_call.stdout

        # --- grant-tools: printed, idempotent, live (no SIGHUP)
        granted = net.cli(*GRANT_TOOLS)
        assert granted.returncode == 0, granted.stderr
        assert "granted: robot_b /rostopic_* subscribe /chatter std_msgs/String" in granted.stdout
        assert "granted: robot_b /rosparam-* write_param /" in granted.stdout
        again = net.cli(*GRANT_TOOLS)
        assert again.returncode == 0 and "0 grant(s) added" in again.stdout and "already granted" in again.stdout

        until_ok(net, "rosparam", "set", "/x", "1", within=15)
        got = tool(net, "rosparam", "get", "/x")
        assert got.returncode == 0 and got.stdout.strip() == "1", got
        listed = tool(net, "rosparam", "list")
        assert listed.returncode == 0 and "/x" in listed.stdout.split(), listed

        echo = tool(net, "rostopic", "echo", "-n", "1", "/chatter", timeout=30)
        assert echo.returncode == 0 and 'data: "secret-' in echo.stdout, echo

        # rosbag record subscribes with type '*': judged by the type really published
        bag = tmp_path / "chatter.bag"
        recorded = tool(net, "rosbag", "record", "-O", str(bag), "--duration=3", "/chatter", timeout=30)
        assert recorded.returncode == 0, recorded.stdout + recorded.stderr
        from rosbags.rosbag1 import Reader

        with Reader(bag) as reader:
            topics = {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
        assert topics.get("/chatter", ("", 0))[0] == "std_msgs/msg/String" and topics["/chatter"][1] >= 10, topics

        call = until_ok(net, "rosservice", "call", "/rospy_loggers", within=10, timeout=20)
        assert "rospy.server" in call.stdout, call.stdout

        nodes = tool(net, "rosnode", "list")
        assert nodes.returncode == 0 and "/talker_a" in nodes.stdout.split(), nodes
        info = tool(net, "rosnode", "info", "/talker_a")
        assert info.returncode == 0 and "/chatter" in info.stdout, info

        # --- --remove takes the bundle away again (live)
        removed = net.cli(*GRANT_TOOLS, "--remove")
        assert removed.returncode == 0 and "removed: robot_b /rosparam-* write_param /" in removed.stdout
        deadline = time.monotonic() + 15
        while tool(net, "rosparam", "set", "/y", "2").returncode == 0:
            assert time.monotonic() < deadline, "rosparam set still works after grant-tools --remove"
            time.sleep(0.5)
        assert pub.poll() is None and server.poll() is None
