"""Learning mode on ROS 1, as an operator uses it: a robot graph with no grants at all
runs while its managers learn, the proposal is reviewed and applied, learning ends, and
the same graph then runs with zero denials for a minute; a node that was not there while
learning is refused; no proposal holds a wildcard.

The graph, on two robots behind their interceptors (separate network-namespace hosts):
robot A runs a talker (/chatter), a service server (/robot_loggers) and a node that
writes and reads a parameter; robot B runs a listener and a client of the service, and a
launch file (roslaunch, a global and a private <param>, a publisher and a subscriber of
/odom). Eight nodes counting roslaunch; every one an unmodified rospy process.
"""

from __future__ import annotations

import contextlib
import json
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from cryptoros.lab.policy import policy_yaml
from tests.authz_support import ok
from tests.interceptor_harness import (
    SYS_PY,
    denials,
    read_lines,
    robot_network,
    separate_hosts,
)
from tests.support import require, ros_package, running, until

pytestmark = [pytest.mark.ros1]

GRAPH = str(Path(__file__).parents[1] / "ros1_nodes" / "graph_node.py")
#: managers and certificates only: not one grant
POLICY = policy_yaml({"master": {}, "robot_a": {}, "robot_b": {}, "robot_c": {}})
LAUNCH = """<launch>
  <param name="/fleet/mode" value="explore"/>
  <node name="odom_pub" pkg="crlearn" type="graph_node.py" args="talker /odom_pub /odom">
    <param name="rate" value="5"/>
  </node>
  <node name="odom_sub" pkg="crlearn" type="graph_node.py" args="listener /odom_sub /odom" output="screen"/>
</launch>
"""
#: the enforced graph runs this long with no denial anywhere (seconds)
CLEAN_RUN = 60.0


def status(net, host: str) -> dict:
    with net.inside(host):
        with urllib.request.urlopen(f"http://127.0.0.1:{net.hosts[host].metrics_port}/status", timeout=5) as reply:
            return json.loads(reply.read())


def cli_ok(net, *args: str) -> str:
    return ok(net.cli(*args))


def policy_denials(net, host: str) -> list[str]:
    """``host``'s denials but rosmaster's ``shutdown`` of a node name registered again
    (the first run's nodes were killed without unregistering; the call is always dropped)."""
    return [line for line in denials(net, host).splitlines() if "shutdown_dropped" not in line]


class Graph:
    """The eight nodes, started in a with block; each node's output lines by name."""

    def __init__(self, net, workdir: Path) -> None:
        self.net, self.workdir, self.procs = net, workdir, {}

    @contextlib.contextmanager
    def running(self):
        net = self.net
        pkgs = self.workdir / "pkgs"
        ros_package(pkgs, "crlearn", {"graph_node.py": Path(GRAPH).read_text()})
        (self.workdir / "odom.launch").write_text(LAUNCH)
        nodes = {
            "talker": ("robot_a", [SYS_PY, GRAPH, "talker", "/talker", "/chatter"]),
            "server": ("robot_a", [SYS_PY, GRAPH, "server", "/server", "/robot_loggers"]),
            "configurator": ("robot_a", [SYS_PY, GRAPH, "params", "/configurator", "/fleet/speed"]),
            "listener": ("robot_b", [SYS_PY, GRAPH, "listener", "/listener", "/chatter"]),
            "client": ("robot_b", [SYS_PY, GRAPH, "client", "/client", "/robot_loggers"]),
            "launch": ("robot_b", ["roslaunch", str(self.workdir / "odom.launch")]),
        }
        with contextlib.ExitStack() as stack:
            for name, (host, argv) in nodes.items():
                env = {**net.ros_env(host), "ROS_PACKAGE_PATH": str(pkgs)}
                self.procs[name] = stack.enter_context(running(argv, env=env))
            yield self

    def wait(self, name: str, text: str, timeout: float = 60) -> list[str]:
        return read_lines(self.procs[name], text, timeout)

    def working(self, timeout: float = 60) -> None:
        """Until every flow of the graph was seen working once."""
        self.wait("listener", "GOT n ", timeout)
        self.wait("client", "ANSWER 1", timeout)
        self.wait("configurator", "PARAM 3", timeout)
        self.wait("launch", "GOT n ", timeout)  # /odom_sub, printing to roslaunch's screen


def test_a_graph_learned_applied_and_enforced_runs_with_no_denial(tmp_path):
    require("rosmaster", "roslaunch")
    with robot_network(tmp_path, policy=POLICY, start=("master", "robot_a", "robot_b"),
                       netns=separate_hosts()) as net:
        graph = Graph(net, tmp_path)
        # ------------------------------------------------------------ learning
        for robot in ("robot_a", "robot_b"):
            out = cli_ok(net, "learn", "start", robot, "--for", "10m")
            assert "LEARNING" in out, out
        for robot in ("robot_a", "robot_b"):
            until(lambda robot=robot: status(net, robot).get("learning"), 20, f"{robot} says LEARNING in status")
        started = time.monotonic()
        with graph.running():
            graph.working()
            learned_in = time.monotonic() - started

            def proposal(robot: str, wanted: tuple[str, ...]) -> str:
                text = cli_ok(net, "learn", "propose", robot)
                return text if all(w in text for w in wanted) else ""

            want_a = ("'/talker', topic: '/chatter', type: 'std_msgs/String'",
                      "'/server', service: '/robot_loggers', type: 'roscpp/GetLoggers'",
                      "'/configurator', namespace: '/fleet/speed'")
            want_b = ("'/listener', topic: '/chatter', type: 'std_msgs/String'",
                      "'/client', service: '/robot_loggers', type: 'roscpp/GetLoggers'",
                      "'/odom_pub', topic: '/odom'", "'/odom_sub', topic: '/odom'",
                      "'/roslaunch', namespace: '/fleet/mode'", "'/roslaunch', namespace: '/odom_pub/rate'")
            proposal_a = until(lambda: proposal("robot_a", want_a), 60, "robot A's proposal")
            proposal_b = until(lambda: proposal("robot_b", want_b), 60, "robot B's proposal")
        assert "LEARNING" in net.hosts["robot_a"].logs(), "robot A's log never said LEARNING"
        for text in (proposal_a, proposal_b):
            grants = [line for line in text.splitlines() if line.lstrip().startswith("- {")]
            assert grants and not any("*" in line.split("#")[0] for line in grants), text
            assert "/rosout" not in text and "get_loggers" not in text, text  # ROS's own: no grant needed
        for robot in ("robot_a", "robot_b"):  # nor is it asked for on stderr
            notes = net.cli("learn", "propose", robot).stderr
            assert "get_loggers" not in notes and "set_logger_level" not in notes, notes
        print(f"learned in {learned_in:.1f} s; robot A {proposal_a.count('- {')} grants, "
              f"robot B {proposal_b.count('- {')} grants")
        for robot in ("robot_a", "robot_b"):
            applied = cli_ok(net, "learn", "apply", robot, "--yes")
            assert "grants added" in applied, applied
            cli_ok(net, "learn", "stop", robot)
        for robot in ("robot_a", "robot_b"):
            until(lambda robot=robot: not status(net, robot).get("learning"), 20, f"{robot} no longer LEARNING")
        cli_ok(net, "grant", "robot_a", "publish", "/talker", "/never", "std_msgs/String")  # for `unused`
        changes = cli_ok(net, "audit", "--changes")
        assert "learn apply robot_a" in changes and "learning" in changes, changes

        # ------------------------------------------------------------ enforced
        with graph.running():
            graph.working()
            before = {h: len(policy_denials(net, h)) for h in ("master", "robot_a", "robot_b")}
            clean_from = time.monotonic()
            seen = {name: [] for name in graph.procs}
            while time.monotonic() - clean_from < CLEAN_RUN:
                for name, proc in graph.procs.items():
                    seen[name] += read_lines(proc, None, 0.2)
            for name, lines in seen.items():
                assert not [line for line in lines if line.startswith("FAIL")], (name, lines[-5:])
                assert all(proc.poll() is None for proc in graph.procs.values()), f"a node of the graph ended: {name}"
            assert sum(line.startswith("GOT") for line in seen["listener"]) >= CLEAN_RUN * 5, seen["listener"][-5:]
            assert sum(line.startswith("ANSWER") for line in seen["client"]) >= CLEAN_RUN, seen["client"][-5:]
            for host, count in before.items():
                new = policy_denials(net, host)[count:]
                assert not new, f"{host} refused something the learned policy should allow: {new[:5]}"

            # least privilege kept: the grant nothing used is listed for removal, the used ones are not
            listed = cli_ok(net, "unused", "--since", "10m")
            assert "robot_a publish /talker /never std_msgs/String" in listed, listed
            assert "/chatter" not in listed and "/robot_loggers" not in listed and "/fleet" not in listed, listed

            # a node that was not there while learning is refused
            with running([SYS_PY, GRAPH, "talker", "/intruder", "/chatter"], env=net.ros_env("robot_a")) as intruder:
                read_lines(intruder, "READY", 30)
                until(lambda: "/intruder" in denials(net, "robot_a"), 30, "the intruder refused on robot A")
            assert "not_granted" in denials(net, "robot_a"), denials(net, "robot_a")


def test_learning_cannot_be_started_by_a_certificate_and_learned_rows_are_refused_when_not_learning(tmp_path):
    """The daemon has no endpoint that starts learning; a robot's interceptor (its valid
    certificate) reporting learned requests while its manager enforces gets them refused,
    and a malformed report is refused whole."""
    with robot_network(tmp_path, policy=POLICY, start=("master",), netns=separate_hosts()) as net:
        ctx, _token = net.client_of("robot_a")
        opener = urllib.request.build_opener(urllib.request.HTTPSHandler(context=ctx))

        def post(path: str, body: dict) -> tuple[int, dict]:
            request = urllib.request.Request(f"{net.authz_url}{path}", data=json.dumps(body).encode(),
                                             headers={"Content-Type": "application/json"})
            try:
                with net.inside("master"), opener.open(request, timeout=10) as reply:
                    return reply.status, json.loads(reply.read())
            except urllib.error.HTTPError as exc:
                body = exc.read()
                return exc.code, json.loads(body) if body.startswith(b"{") else {"text": body.decode()}

        for path in ("/learn", "/learning", "/learn/start", "/observations/start"):
            status_code, _ = post(path, {"manager": "robot_a", "for": 3600})
            assert status_code in (404, 405), (path, status_code)
        now = time.time()
        row = {"allowed": False, "action": "publish", "node": "/evil", "name": "/cmd_vel",
               "type": "geometry_msgs/Twist", "count": 1, "first": now, "last": now}
        code, answer = post("/observations", {"observations": [row]})
        assert (code, answer) == (200, {"accepted": 0, "refused": 1}), (code, answer)
        code, answer = post("/observations", {"observations": [{**row, "allowed": True}]})  # no grant allowed it
        assert (code, answer) == (200, {"accepted": 0, "refused": 1}), (code, answer)
        code, answer = post("/observations", {"observations": [{**row, "node": "not a node"}]})
        assert code == 400, (code, answer)
        learn_status = cli_ok(net, "learn", "status", "robot_a")
        assert "enforcing" in learn_status and "0 distinct requests recorded" in learn_status, learn_status
