"""Stock tools: Debian's own rostopic, rosparam, rosservice and rosnode run on
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

import re
import subprocess
import sys
import time

import pytest

from cryptoros.lab.policy import policy_yaml
from cryptoros.policy.ros1 import SEE_DENIALS
from tests.interceptor_harness import NODE, NODES, SYS_PY, denials, read_lines, robot_network, wait_registered
from tests.support import VENV_BIN, require, ros_package, run, running

pytestmark = [pytest.mark.ros1]

S = "std_msgs/String"
LOGGERS = ("/rospy_server", "/rospy_loggers", "roscpp/GetLoggers")


def policy(robot_b: dict | None = None) -> str:
    """Robot A's talker and logger service, robot B's listener (plus ``robot_b``'s grants)."""
    grants_b = {"subscribe": [("/rospy_listener", "/chatter", S)]}
    for action, rows in (robot_b or {}).items():
        grants_b[action] = grants_b.get(action, []) + rows
    return policy_yaml({"master": {}, "robot_a": {"publish": [("/talker_a", "/chatter", S)], "serve": [LOGGERS]},
                        "robot_b": grants_b, "robot_c": {}})


#: robot B holds no '*' grant: only its own listener's, and whatever grant-tools adds.
POLICY = policy()

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
    require("rostopic", "rosparam", "rosnode", "rosservice", "rosbag", "rosmsg", "rossrv")
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
        assert "ERROR: Unable to determine type of service [/rospy_loggers]." in denied_call.stderr, denied_call
        # rosservice type (and info) probe the service (a probe tells its type): the call grant
        denied_type = tool(net, "rosservice", "type", "/rospy_loggers", timeout=10)
        assert denied_type.returncode != 0 and "Unknown service [/rospy_loggers]" in denied_type.stderr, denied_type
        # the refused TCPROS header is logged with the grant that would allow it
        assert "not_granted: /rosservice may not call /rospy_loggers (to allow: cryptoros-authz grant-tools robot_b " \
               "--service /rospy_loggers:TYPE  # TYPE: the service's type" in denials(net, "robot_b"), denials(net, "robot_b")

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
        service_type = tool(net, "rosservice", "type", "/rospy_loggers")
        assert service_type.returncode == 0 and service_type.stdout.strip() == "roscpp/GetLoggers", service_type

        nodes = tool(net, "rosnode", "list")
        assert nodes.returncode == 0 and "/talker_a" in nodes.stdout.split(), nodes
        info = tool(net, "rosnode", "info", "/talker_a")
        assert info.returncode == 0 and "/chatter" in info.stdout, info
        ping = tool(net, "rosnode", "ping", "-c", "1", "/talker_a")
        assert ping.returncode == 0 and "reply from" in ping.stdout, ping

        # --- the rest of the tools of the table in docs/stock-tools.md
        topics = tool(net, "rostopic", "list")
        assert topics.returncode == 0 and "/chatter" in topics.stdout.split(), topics
        topic_info = tool(net, "rostopic", "info", "/chatter")
        assert topic_info.returncode == 0 and "/talker_a" in topic_info.stdout, topic_info
        hz = tool(net, "rostopic", "hz", "-w", "5", "/chatter", timeout=8)  # runs until stopped
        assert "average rate" in hz.stdout, hz
        assert net.cli("grant", "robot_b", "publish", "/rostopic_*", "/tool_topic", "std_msgs/String").returncode == 0
        published = until_ok(net, "rostopic", "pub", "-1", "/tool_topic", "std_msgs/String", "hi", within=20, timeout=30)
        assert published.returncode == 0, published
        services = tool(net, "rosservice", "list")
        assert services.returncode == 0 and "/talker_a/get_loggers" in services.stdout.split(), services
        delete = tool(net, "rosparam", "delete", "/x")
        assert delete.returncode == 0 and tool(net, "rosparam", "get", "/x").returncode != 0, delete
        for offline in (("rosmsg", "show", "std_msgs/String"), ("rossrv", "show", "roscpp/GetLoggers")):
            shown = tool(net, *offline)
            assert shown.returncode == 0 and shown.stdout.strip(), shown

        # --- --remove takes the bundle away again (live)
        removed = net.cli(*GRANT_TOOLS, "--remove")
        assert removed.returncode == 0 and "removed: robot_b /rosparam-* write_param /" in removed.stdout
        deadline = time.monotonic() + 15
        while tool(net, "rosparam", "set", "/y", "2").returncode == 0:
            assert time.monotonic() < deadline, "rosparam set still works after grant-tools --remove"
            time.sleep(0.5)
        assert pub.poll() is None  # (the service server lives 30 s only)


# ---------------------------------------------------------------------------------------
# Refusals read like ROS errors, what libraries read is readable, roslaunch and
# rosbag play with their bundles, actionlib, and quiet, useful denial logs.

#: robot B's own nodes: a prober, two launched nodes, an action server and its client.
POLICY_LIBS = policy({
    "subscribe": [
        ("/prober", "/chatter", "std_msgs/String"),
        ("/action_server", "/move_base/goal", "move_base_msgs/MoveBaseActionGoal"),
        ("/action_server", "/move_base/cancel", "actionlib_msgs/GoalID"),
        ("/action_client", "/move_base/status", "actionlib_msgs/GoalStatusArray"),
        ("/action_client", "/move_base/feedback", "move_base_msgs/MoveBaseActionFeedback"),
        ("/action_client", "/move_base/result", "move_base_msgs/MoveBaseActionResult"),
        ("/dr_server", "/chatter", "std_msgs/String"),
        ("/dr_client", "/dr_server/parameter_descriptions", "dynamic_reconfigure/ConfigDescription"),
        ("/dr_client", "/dr_server/parameter_updates", "dynamic_reconfigure/Config"),
    ],
    "call": [
        ("/dr_client", "/dr_server/set_parameters", "dynamic_reconfigure/Reconfigure"),
    ],
    "publish": [
        ("/launch_talker", "/launched", "std_msgs/String"),
        ("/launch_other", "/chatter_other", "std_msgs/String"),
        ("/action_server", "/move_base/status", "actionlib_msgs/GoalStatusArray"),
        ("/action_server", "/move_base/feedback", "move_base_msgs/MoveBaseActionFeedback"),
        ("/action_server", "/move_base/result", "move_base_msgs/MoveBaseActionResult"),
        ("/action_client", "/move_base/goal", "move_base_msgs/MoveBaseActionGoal"),
        ("/action_client", "/move_base/cancel", "actionlib_msgs/GoalID"),
    ],
})

LIBS = str(NODES / "stock_libs.py")

LAUNCH = """\
<launch>
  <node name="launch_talker" pkg="crtest" type="stock_libs.py" args="launched" output="screen">
    <param name="rate" value="10.0"/>
    <rosparam param="gains">{p: 1.0, i: 0.1}</rosparam>
    <remap from="chatter" to="/launched"/>
  </node>
  <node name="launch_other" pkg="crtest" type="stock_libs.py" args="launched" output="screen">
    <remap from="chatter" to="/chatter_other"/>
  </node>
</launch>
"""


def _one_error_line(result: subprocess.CompletedProcess) -> str:
    """A tool's refusal: non-zero exit, no traceback, no XML-RPC fault; the error line."""
    assert result.returncode != 0, result.stdout + result.stderr
    out = result.stdout + result.stderr
    assert "Traceback" not in out and "Fault" not in out, out
    errors = [line for line in out.splitlines() if "ERROR" in line or "denied by cryptoros" in line]
    assert errors, out
    return errors[0]


def _set_on_master(net, key: str, value) -> None:
    import xmlrpc.client

    code, msg, _ = xmlrpc.client.ServerProxy(net.rosmaster_uri).setParam("/test", key, value)
    assert code == 1, msg


def test_refusals_read_like_ros_errors_and_unreadable_parameters_like_unset_ones(tmp_path):
    """No grant-tools: each stock tool refused says so in one line (rosparam get/delete,
    roslaunch below), a probe of an unreadable parameter is answered as unset, a node's
    own logging adds no denial, a refusal repeated at 5 Hz for 10 s adds at most two
    DENY lines, and ``cryptoros denials`` shows it with the grant that would allow it."""
    require("rosparam", "rosnode")
    with robot_network(tmp_path, policy=POLICY_LIBS, start=("master", "robot_a", "robot_b")) as net, \
            running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "10", "120"],
                    env=net.ros_env("robot_a")) as pub:
        read_lines(pub, "READY", 20)
        wait_registered(net, "/talker_a")
        _set_on_master(net, "/secret", "hidden")

        # --- a node probing a parameter it may not read: as if unset, never a crash
        with running([SYS_PY, LIBS, "probe", "prober", "/secret", "10"], env=net.ros_env("robot_b")) as prober:
            lines = [line.strip() for line in read_lines(prober, "DONE", 60)]
        assert "PROBE False unset-default" in lines, lines
        log = denials(net, "robot_b")
        secret = [line for line in log.splitlines() if "/secret" in line]
        assert 1 <= len(secret) <= 2 * 2, log  # hasParam and getParam: at most two lines each
        for noise in ("/rosout_disable_topics_generation", "/tcp_keepalive", "/enable_statistics", "/use_sim_time"):
            assert noise not in log, log
        assert "to allow: cryptoros-authz grant robot_b read_param /prober /secret" in log, log

        shown = run([sys.executable, "-m", "cryptoros.cli", "denials", "--config", str(net.hosts["robot_b"].config)], timeout=20)
        assert shown.returncode == 0, shown.stderr
        assert "to allow: cryptoros-authz grant robot_b read_param /prober /secret" in shown.stdout, shown.stdout
        counts = [int(line.split("x", 1)[0]) for line in shown.stdout.splitlines() if "/secret" in line and "x  " in line]
        assert counts and max(counts) >= 20, shown.stdout  # every probe counted

        # --- stock tools: one line, the reason code, no traceback
        got = tool(net, "rosparam", "get", "/secret")
        assert _one_error_line(got) == "ERROR: Parameter [/secret] is not set", got  # as if unset
        deleted = tool(net, "rosparam", "delete", "/secret")
        assert _one_error_line(deleted) == f"ERROR: denied by cryptoros: param_write_denied {SEE_DENIALS}", deleted
        # ros_comm 1.15's rosparam set catches no master error (a plain rosmaster's neither):
        # its last line is the refusal, never an XML-RPC fault
        refused = tool(net, "rosparam", "set", "/secret", "changed")
        assert refused.returncode != 0 and "Fault" not in refused.stderr, refused
        assert refused.stderr.strip().splitlines()[-1].endswith(f"denied by cryptoros: param_write_denied {SEE_DENIALS}"), \
            refused
        # ... which is why nodes and tools run through cryptoros run (or cryptoros env): its
        # hook prints such an uncaught refusal as one line
        through_run = run([str(VENV_BIN / "cryptoros"), "run", "--config", str(net.hosts["robot_b"].config), "--",
                           "rosparam", "set", "/secret", "changed"], env=net.ros_env("robot_b"), timeout=20)
        assert through_run.returncode == 1 and _one_error_line(through_run) == \
            f"ERROR: denied by cryptoros: param_write_denied {SEE_DENIALS}", through_run

        # --- rosnode kill: the shutdown is refused with an error, the node lives
        import xmlrpc.client

        code, _, relay = xmlrpc.client.ServerProxy(net.hosts["robot_b"].master_uri).lookupNode("/rosnode", "/talker_a")
        assert code == 1
        assert xmlrpc.client.ServerProxy(relay).shutdown("/rosnode", "user request") == \
            [-1, "denied by cryptoros: shutdown_dropped", 0]
        plain = tool(net, "rosnode", "kill", "/talker_a")  # ros_comm prints "killed" whatever the answer
        assert "killed" in plain.stdout, plain
        # through cryptoros run (its hook wraps rosnode's kill_nodes): the refusal and a failure
        killed = run([str(VENV_BIN / "cryptoros"), "run", "--config", str(net.hosts["robot_b"].config), "--",
                      "rosnode", "kill", "/talker_a"], env=net.ros_env("robot_b"), timeout=20)
        assert killed.returncode == 1 and "killed" not in killed.stdout, killed
        assert "ERROR: denied by cryptoros: shutdown_dropped" in killed.stderr.splitlines(), killed
        assert "ERROR: Failed to kill:" in killed.stderr and "Traceback" not in killed.stderr, killed
        ping = tool(net, "rosnode", "ping", "-c", "1", "/talker_a")
        assert ping.returncode == 0 and pub.poll() is None, ping

        # --- rostopic: rospy logs a refused registration as [FATAL] and goes on (pub said it
        # published, exit 0; echo waited); through cryptoros run the refusal ends it in one line
        for argv in (["pub", "-1", "/chatter", "std_msgs/String", "data: x"], ["echo", "-n", "1", "/chatter"]):
            refused = run([str(VENV_BIN / "cryptoros"), "run", "--config", str(net.hosts["robot_b"].config), "--",
                           "rostopic", *argv], env=net.ros_env("robot_b"), timeout=30)
            lines = [line for line in (refused.stdout + refused.stderr).splitlines() if line.strip()]
            assert refused.returncode == 1 and len(lines) == 1, refused
            # rostopic's node is named by no grant of robot B: its first registration, of ROS's own
            # /rosout or its own logger service (which comes first varies), is refused
            assert len(lines) == 1 and re.fullmatch(r"ERROR: unable to register (publication \[/rosout\]|service "
                                                    r"\[/rostopic_\d+_\d+/get_loggers\]) with master: denied by "
                                                    r"cryptoros: not_granted " + re.escape(SEE_DENIALS), lines[0]), refused


def test_actionlib_and_dynamic_reconfigure_behind_interceptors(tmp_path):
    """actionlib reads <action>/status_frequency (has_param: an error would raise in
    start()) and its queue-size parameters; both readable, the goal succeeds. A
    dynamic_reconfigure server needs no grant for its own endpoints (set_parameters,
    parameter_descriptions, parameter_updates); its client, the call and subscriptions."""
    missing_action = run([SYS_PY, "-c", "import actionlib, move_base_msgs.msg, dynamic_reconfigure"], timeout=30)
    if missing_action.returncode != 0:
        require("python3-actionlib (apt: python3-actionlib python3-move-base-msgs)-not-installed")
    with robot_network(tmp_path, policy=POLICY_LIBS, start=("master", "robot_b")) as net, \
            running([SYS_PY, LIBS, "action_server"], env=net.ros_env("robot_b")) as server:
        read_lines(server, "READY", 30)
        with running([SYS_PY, LIBS, "action_client"], env=net.ros_env("robot_b")) as client:
            lines = [line.strip() for line in read_lines(client, "RESULT", 60)]
        assert "RESULT 3" in lines, lines  # GoalStatus.SUCCEEDED
        assert "status_frequency" not in denials(net, "robot_b")
        with running([SYS_PY, LIBS, "dr_server"], env=net.ros_env("robot_b")) as dr_server:
            read_lines(dr_server, "READY", 30)
            with running([SYS_PY, LIBS, "dr_client"], env=net.ros_env("robot_b")) as dr_client:
                lines = [line.strip() for line in read_lines(dr_client, "SET", 60)]
        assert "SET 7" in lines, lines
        assert "DENY" not in denials(net, "robot_b"), denials(net, "robot_b")


def test_roslaunch_and_rosbag_play_with_their_bundles(tmp_path):
    """roslaunch refused in one line without its bundle; with ``grant-tools --roslaunch``
    a two-node launch file with <param>, <rosparam> and remappings runs. rosbag play
    --clock with ``--publish-topic`` and ``--clock``; its pause_playback service is its own."""
    require("roslaunch", "rosbag")
    ros_package(tmp_path / "pkgs", "crtest", {"stock_libs.py": open(LIBS).read()})
    launch = tmp_path / "two.launch"
    launch.write_text(LAUNCH)
    bag = tmp_path / "clock.bag"
    run([SYS_PY, "-c", "import rosbag, rospy; from std_msgs.msg import String\n"
         f"with rosbag.Bag({str(bag)!r}, 'w') as b:\n"
         "    [b.write('/chatter', String(data='b%d' % i), rospy.Time(1 + i * 0.1)) for i in range(20)]"],
        timeout=30, check=True)
    with robot_network(tmp_path, policy=POLICY_LIBS, start=("master", "robot_b")) as net:
        env = {**net.ros_env("robot_b"), "ROS_PACKAGE_PATH": str(tmp_path / "pkgs")}

        def launch_it() -> subprocess.CompletedProcess:
            try:
                return run(["roslaunch", str(launch)], env=env, timeout=60)
            except subprocess.TimeoutExpired as exc:
                return subprocess.CompletedProcess([], 124, str(exc.stdout), str(exc.stderr))

        refused = launch_it()
        assert "denied by cryptoros: param_write_denied" in _one_error_line(refused), refused

        granted = net.cli("grant-tools", "robot_b", "--roslaunch",
                          "--publish-topic", "/chatter:std_msgs/String", "--clock", "--param-ns", "/robot_b")
        assert granted.returncode == 0, granted.stderr
        assert "granted: robot_b /roslaunch write_param /run_id" in granted.stdout
        assert "granted: robot_b /play_* publish /clock rosgraph_msgs/Clock" in granted.stdout
        deadline = time.monotonic() + 30
        while True:
            launched = launch_it()
            if "PARAM 10.0 [('i', 0.1), ('p', 1.0)] /launched" in launched.stdout:
                break
            assert time.monotonic() < deadline, launched.stdout + launched.stderr
            time.sleep(1)
        assert "PARAM None [] /chatter_other" in launched.stdout, launched.stdout
        assert "Traceback" not in launched.stdout + launched.stderr
        # /roslaunch is every robot's roslaunch: the bundle opens its namespace to roslaunch
        # alone (not to rosparam, which may write /robot_b now), and a node registering under
        # the name is refused (it would hold the name against every other robot's roslaunch)
        assert tool(net, "rosparam", "set", "/robot_b/x", "1").returncode == 0
        written = tool(net, "rosparam", "set", "/roslaunch/uris/host_evil__1", "http://evil:1/")
        assert written.returncode != 0 and "param_write_denied" in written.stderr.strip().splitlines()[-1], written
        squatter = run([SYS_PY, "-c", "import rospy; from std_msgs.msg import String\n"
                        "rospy.init_node('roslaunch'); rospy.Subscriber('/chatter', String); rospy.sleep(1.0)"],
                       env=env, timeout=30)
        assert "Traceback" not in squatter.stdout + squatter.stderr, squatter.stderr
        assert "unable to register publication [/rosout] with master: denied by cryptoros: name_taken" in \
            squatter.stderr, squatter.stderr
        refused = [line for line in denials(net, "robot_b").splitlines() if "name_taken" in line]
        assert refused and "no node may register it" in refused[0], denials(net, "robot_b")

        played = tool(net, "rosbag", "play", "--clock", "-q", str(bag), timeout=60)
        assert played.returncode == 0, played.stdout + played.stderr
        log = denials(net, "robot_b")
        assert "/clock" not in log and "pause_playback" not in log, log


def test_what_stock_libraries_read_is_on_the_default_list(tmp_path, roscpp_talker):
    """Measured again, with no interceptor: rospy, roscpp, roslaunch, rosbag and actionlib
    run against a recording proxy in front of rosmaster. Every parameter a node reads
    outside its own names is on the one default list (or is a parameter of a topic it
    publishes), and what roslaunch writes is its own keys (the --roslaunch bundle) or the
    launched nodes' own."""
    import json

    from cryptoros.lab.processes import free_port, wait_port
    from cryptoros.policy.infrastructure import ROS1_DEFAULT_PARAM_READS, ros1_topic_param
    from cryptoros.policy.ros1 import resolve_param_key

    require("rosmaster", "roslaunch", "rosbag")
    if run([SYS_PY, "-c", "import actionlib, move_base_msgs.msg"], timeout=30).returncode != 0:
        require("python3-actionlib-and-python3-move-base-msgs")
    master_port, port = free_port(), free_port()
    out = tmp_path / "reads.jsonl"
    env = {"ROS_MASTER_URI": f"http://127.0.0.1:{port}/", "ROS_IP": "127.0.0.1", "ROS_HOME": str(tmp_path),
           "PATH": "/usr/bin:/bin", "ROS_PACKAGE_PATH": str(tmp_path / "pkgs")}
    ros_package(tmp_path / "pkgs", "crtest", {"stock_libs.py": open(LIBS).read()})
    (tmp_path / "two.launch").write_text(LAUNCH)
    with running(["rosmaster", "--core", "-p", str(master_port)], env=env), \
            running([SYS_PY, str(NODES / "param_recorder.py"), f"http://127.0.0.1:{master_port}/", str(port), str(out)],
                    env=env) as recorder:
        read_lines(recorder, "READY", 20)
        wait_port("127.0.0.1", master_port, 20)
        with running([SYS_PY, LIBS, "probe", "prober", "/prober/x", "3"], env=env) as prober:  # logs at 5 Hz
            read_lines(prober, "DONE", 60)
        with running([roscpp_talker, "/chatter", "1"], env=env) as cpp:
            read_lines(cpp, None, 3)
        with running([SYS_PY, LIBS, "action_server"], env=env) as server:
            read_lines(server, "READY", 30)
            with running([SYS_PY, LIBS, "action_client"], env=env) as client:
                assert "RESULT 3" in [line.strip() for line in read_lines(client, "RESULT", 60)]
        launched = run(["roslaunch", str(tmp_path / "two.launch")], env=env, timeout=60)
        assert "PARAM 10.0" in launched.stdout, launched.stdout + launched.stderr
        bag = tmp_path / "rec.bag"
        assert run(["rosbag", "record", "-O", str(bag), "--duration=1", "/chatter"], env=env, timeout=60).returncode == 0
        assert run(["rosbag", "play", "--clock", "-q", str(bag)], env=env, timeout=60).returncode == 0
    calls = [json.loads(line) for line in out.read_text().splitlines()]
    callers = {caller.split("_")[0] for _m, caller, _k in calls}
    assert {"/prober", "/roscpp", "/action", "/roslaunch", "/record", "/play", "/launch"} <= callers, callers
    own_names = {"/launch_talker", "/launch_other"}  # the launched nodes, named by the manager's grants
    outside = set()
    for method, caller, key in calls:
        if method in ("getParamNames",):
            continue
        key = "/" + key if method == "searchParam" and not key.startswith("/") else resolve_param_key(key, caller)
        if key == caller or key.startswith(caller + "/"):
            continue  # its own private namespace
        if method in ("setParam", "deleteParam"):
            assert caller == "/roslaunch", (method, caller, key)
            assert key.split("/")[1] in ("run_id", "roslaunch", "rosdistro", "rosversion") or \
                "/" + key.split("/")[1] in own_names, key
            continue
        outside.add(key)
    assert {"/rosout_disable_topics_generation", "/use_sim_time", "/tcp_keepalive"} <= outside, outside
    assert not [k for k in outside if k not in ROS1_DEFAULT_PARAM_READS and ros1_topic_param(k) is None], outside
