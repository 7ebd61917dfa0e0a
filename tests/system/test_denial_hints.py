"""What an operator with stock ROS 1 tools is told, and that it works: robot B's tools
refused, ``cryptoros denials`` on robot B names the command, the command pasted into
bash (``failglob``) grants it, and the tool works. Real rosmaster, a rospy talker on
robot A, Debian's rostopic and rosservice on robot B, interceptors over mutual TLS.

Robot B's grants share no name with robot A's: what B calls of A's node is allowed by
A's interceptor only through the token narrowed for A (a node's own logger service is no
grant of A's), and what A's node answers only through the token A shows B.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import time

import pytest

from cryptoros.lab.policy import policy_yaml
from tests.interceptor_harness import NODE, NODES, SYS_PY, denials, read_lines, robot_network, wait_registered
from tests.support import VENV_BIN, require, run, running

pytestmark = [pytest.mark.ros1]

S = "std_msgs/String"
POLICY = policy_yaml({"master": {}, "robot_a": {"publish": [("/talker_a", "/chatter", S)],
                                                "serve": [("/rospy_server", "/rospy_loggers", "roscpp/GetLoggers")]},
                      "robot_b": {"subscribe": [("/weather_listener", "/weather", S)]}, "robot_c": {}})


def through_run(net, *argv: str, timeout: float = 30) -> subprocess.CompletedProcess:
    """A stock tool on robot B through ``cryptoros run`` (its hook: one line per refusal)."""
    return run([str(VENV_BIN / "cryptoros"), "run", "--config", str(net.hosts["robot_b"].config), "--", *argv],
               env=net.ros_env("robot_b"), timeout=timeout)


def hints(net) -> list[str]:
    """The ``to allow:`` commands ``cryptoros denials`` shows on robot B."""
    shown = run([str(VENV_BIN / "cryptoros"), "denials", "--config", str(net.hosts["robot_b"].config)], timeout=20)
    assert shown.returncode == 0, shown.stderr
    return [line.split("to allow: ", 1)[1] for line in shown.stdout.splitlines() if "to allow: " in line]


def paste(net, hint: str) -> subprocess.CompletedProcess:
    """The hint as an operator pastes it: one line of bash, failglob set."""
    env = {"PATH": f"{VENV_BIN}:{os.environ.get('PATH', '/usr/bin:/bin')}", "CRYPTOROS_AUTHZ_DB": net.daemon.db}
    return run(["bash", "-O", "failglob", "-c", hint], env=env, timeout=60)


def until_ok(net, *argv: str, within: float) -> subprocess.CompletedProcess:
    """Run the tool again until it succeeds (a grant reaches the interceptors live)."""
    deadline = time.monotonic() + within
    while True:
        result = through_run(net, *argv)
        if result.returncode == 0:
            return result
        assert time.monotonic() < deadline, f"{argv} still fails: {result.stdout}{result.stderr}"
        time.sleep(0.5)


@contextlib.contextmanager
def talker_network(tmp_path):
    """Robot A's rospy talker (its own /talker_a/get_loggers too) behind the interceptors."""
    require("rostopic", "rosservice")
    with robot_network(tmp_path, policy=POLICY, start=("master", "robot_a", "robot_b")) as net, \
            running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "10", "120"],
                    env=net.ros_env("robot_a")) as pub:
        read_lines(pub, "READY", 20)
        wait_registered(net, "/talker_a")
        yield net
        assert pub.poll() is None  # the talker lived through it all


def test_another_robots_nodes_logger_service_is_called_once_the_hint_is_pasted(tmp_path):
    """Robot B holds no grant on any name of robot A: the call grant survives the token
    narrowed for robot A, and robot A's node's own service the token A shows B."""
    with talker_network(tmp_path) as net:
        refused = through_run(net, "rosservice", "call", "/talker_a/get_loggers")
        assert refused.returncode != 0 and "rospy" not in refused.stdout, refused
        # its probe refused, said as such (rosservice alone: "Unable to determine type")
        assert refused.stderr.splitlines() == ["ERROR: service [/talker_a/get_loggers]: denied by cryptoros "
                                               "(cryptoros denials says what to grant)"], refused
        typed = through_run(net, "rosservice", "type", "/talker_a/get_loggers")
        assert typed.returncode != 0 and typed.stderr.splitlines() == refused.stderr.splitlines(), typed
        loggers = "cryptoros-authz grant-tools robot_b --service /talker_a/get_loggers:roscpp/GetLoggers"
        assert loggers in hints(net), hints(net)
        pasted = paste(net, loggers)
        assert pasted.returncode == 0 and "granted: robot_b /rosservice call /talker_a/get_loggers" in pasted.stdout, \
            pasted
        called = until_ok(net, "rosservice", "call", "/talker_a/get_loggers", within=20)
        assert "rospy" in called.stdout, called
        assert "/talker_a/get_loggers" not in denials(net, "robot_a"), denials(net, "robot_a")


def test_each_hint_pasted_allows_what_was_refused(tmp_path):
    """A tool no grant names, then a topic (its type known) and a service (its type a
    placeholder saying where it is found)."""
    with talker_network(tmp_path) as net:

        # --- a tool no grant names: its first registration (/rosout) is refused; the refusal
        # points at cryptoros denials, which names the bundle with its placeholders explained
        echo = through_run(net, "rostopic", "echo", "-n", "1", "/chatter")
        lines = [line for line in (echo.stdout + echo.stderr).splitlines() if line.strip()]
        assert echo.returncode == 1 and len(lines) == 1 and lines[0].startswith("ERROR: unable to register ") and \
            lines[0].endswith("with master: denied by cryptoros: not_granted (cryptoros denials says what to grant)"), echo
        assert "[/rosout]" in lines[0] or "/get_loggers]" in lines[0], echo  # ROS's own: its log topic or loggers
        assert any(h.startswith("cryptoros-authz grant-tools robot_b --topic TOPIC:TYPE  # no grant names /rostopic_*; "
                                "TOPIC: the topic rostopic echo/hz/bw reads") for h in hints(net)), hints(net)

        # --- the operator fills in the placeholders for another topic: rostopic's node is named,
        # its subscription of /chatter refused with the type it asked for in the hint
        assert net.cli("grant-tools", "robot_b", "--topic", "/weather:std_msgs/String").returncode == 0
        deadline = time.monotonic() + 20
        while "[/chatter]" not in (refused := through_run(net, "rostopic", "echo", "-n", "1", "/chatter")).stderr:
            assert time.monotonic() < deadline, refused
            time.sleep(0.5)
        assert refused.returncode == 1 and "unable to register subscription [/chatter]" in refused.stderr, refused
        topic = "cryptoros-authz grant-tools robot_b --topic /chatter:std_msgs/String"
        assert topic in hints(net), hints(net)
        assert paste(net, topic).returncode == 0
        echoed = until_ok(net, "rostopic", "echo", "-n", "1", "/chatter", within=20)
        assert 'data: "secret-' in echoed.stdout, echoed

        # --- a service whose type no refusal tells: a placeholder, and where the type is
        with running([SYS_PY, str(NODES / "services.py"), "serve"], env=net.ros_env("robot_a")) as server:
            read_lines(server, "READY", 20)
            wait_registered(net, "/rospy_server")
            unknown = through_run(net, "rosservice", "call", "/rospy_loggers")
            assert unknown.returncode != 0, unknown
            placeholder = "cryptoros-authz grant-tools robot_b --service /rospy_loggers:TYPE  # TYPE: the service's " \
                          "type, the one its server is granted (cryptoros-authz show-manager SERVER_ROBOT lists it)"
            assert placeholder in hints(net), hints(net)
            shown = net.cli("show-manager", "robot_a")
            served = [line.split() for line in shown.stdout.splitlines() if "/rospy_loggers" in line]
            assert served and served[0][0] == "serve", shown.stdout
            filled = placeholder.split("  #")[0].replace("TYPE", served[0][-1])
            assert paste(net, filled).returncode == 0
            called = until_ok(net, "rosservice", "call", "/rospy_loggers", within=20)
            assert "rospy" in called.stdout, called
