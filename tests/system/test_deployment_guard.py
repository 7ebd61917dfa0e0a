"""The product refuses an exposed deployment and makes the secure one easy, on separate
hosts (a network namespace per host, a stranger among them), as an operator and an
attacker would act:

- rosmaster started as plain ROS starts it (every address): the master's interceptor
  exits 1 with one line saying how to fix it, ``--check`` too; rosmaster started through
  ``cryptoros run`` (loopback): it serves; rosmaster restarted exposed while it runs:
  master streams are refused (``exposed_master``), nothing is replayed to it (a
  stranger reaching it sees no robot), ``cryptoros status`` warns; back on loopback,
  served again; ``allow_exposed_master = true`` serves with a warning in status;
- a rospy node started without ``ROS_IP`` on a robot: its registration is refused
  (``exposed_endpoint``) as one ROS error line naming the node, the port and the fix,
  and it is asked to shut down (its open port would take a stranger's calls);
  the same node through ``cryptoros run``, and a listener from a shell that sourced
  ``cryptoros env``, talk;
- one instance per configuration: a second start exits 1 naming the running pid and
  leaves the state file's bytes as they were.

Needs root (CI runs as root); without root it skips and says why.
"""

from __future__ import annotations

import contextlib
import shutil
import signal
import subprocess
import time
import xmlrpc.client

import pytest

from cryptoros.lab.network import clean_env, stop, tool, wait_port
from tests.interceptor_harness import (
    NODE,
    SYS_PY,
    got,
    reaches,
    read_lines,
    robot_network,
    run_on,
    separate_hosts,
    status_text,
)
from tests.ros1_flow import flow_policy, legit_flow
from tests.support import require, ros_package, running

#: an unmodified rospy listener that exits once asked to shut down (roslaunch respawns it)
SPINNING_LISTENER = """#!/usr/bin/python3
import rospy
from std_msgs.msg import String
rospy.init_node("listener")
rospy.Subscriber("/chatter", String, lambda _m: None)
rospy.spin()
"""

pytestmark = [pytest.mark.ros1]




def _rosmaster(net, port: int, *, through_cryptoros_run: bool) -> subprocess.Popen:
    """rosmaster on the master host: as plain ROS starts it, or through ``cryptoros run``."""
    cmd = [shutil.which("rosmaster"), "--core", "-p", str(port)]
    if through_cryptoros_run:
        cmd = [tool("cryptoros"), "run", "--config", str(net.hosts["master"].config), "--", *cmd]
    proc = subprocess.Popen(net.argv("master", cmd), env=clean_env(ROS_HOME=str(net.workdir)),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    net.procs.append(proc)
    with net.inside("master"):
        wait_port("127.0.0.1", port, 15, proc, "rosmaster")
    return proc


def _lab_rosmaster(net) -> subprocess.Popen:
    return next(p for p in net.procs if "--core" in p.args and p.poll() is None)




def _wait_log(net, host: str, needle: str, timeout: float = 15) -> None:
    deadline = time.monotonic() + timeout
    while needle not in net.hosts[host].logs():
        assert time.monotonic() < deadline, f"no {needle!r} in {host}'s log within {timeout} s:\n" + net.hosts[host].logs()
        time.sleep(0.1)


def _wait_rosmaster_holds(net, node: str, timeout: float = 20) -> None:
    deadline = time.monotonic() + timeout
    while True:
        with net.inside("master"):
            with contextlib.suppress(OSError):
                if node in str(xmlrpc.client.ServerProxy(net.rosmaster_uri).getSystemState("/t")):
                    return
        assert time.monotonic() < deadline, f"rosmaster does not hold {node}"
        time.sleep(0.2)




def test_the_masters_interceptor_refuses_a_rosmaster_other_hosts_reach(tmp_path):
    separate_hosts()
    require("rosmaster")
    with robot_network(tmp_path, start=(), netns=True) as net:
        stranger = net.add_host("stranger")  # its own namespace: what inside("stranger") reaches
        port = int(net.rosmaster_uri.rstrip("/").rsplit(":", 1)[1])
        master = net.hosts["master"]
        stop(_lab_rosmaster(net))
        exposed = _rosmaster(net, port, through_cryptoros_run=False)  # the runbook's old line
        assert reaches(net, "stranger", master.address, port)  # what the check is about

        for args in ([], ["--check"]):
            result = run_on(net, "master", [tool("cryptoros-interceptor"), "--config", str(master.config), *args])
            lines = result.stderr.strip().splitlines()
            assert result.returncode == 1 and len(lines) == 1, result
            assert f"listens on 0.0.0.0 port {port}" in lines[0] and "ROS_IP=127.0.0.1" in lines[0]
            assert f"cryptoros run --config {master.config} -- rosmaster --core -p {port}" in lines[0]
            assert "Traceback" not in result.stderr
        assert not (tmp_path / "master.state").exists() or not list((tmp_path / "master.state").glob("*.json"))

        # the fix the line gives: rosmaster through cryptoros run, on loopback only
        stop(exposed)
        private = _rosmaster(net, port, through_cryptoros_run=True)
        assert not reaches(net, "stranger", master.address, port)
        check = run_on(net, "master", [tool("cryptoros-interceptor"), "--config", str(master.config), "--check"])
        assert "rosmaster" not in check.stderr, check
        net.start("master")
        net.start("robot_a")
        net.start("robot_b")
        with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "120"],
                     env=net.ros_env("robot_a")) as pub:
            read_lines(pub, "READY", 20)
            _wait_rosmaster_holds(net, "/talker_a")

            with net.inside("robot_b"):  # a tunnel to the master's interceptor, kept for the next call
                assert xmlrpc.client.ServerProxy(net.hosts["robot_b"].master_uri).getSystemState("/probe")[0] == 1
            # rosmaster restarted exposed while everything runs
            stop(private)
            exposed = _rosmaster(net, port, through_cryptoros_run=False)
            _wait_log(net, "master", "master streams refused (exposed_master)")
            with net.inside("robot_b"):
                code, message, _ = xmlrpc.client.ServerProxy(net.hosts["robot_b"].master_uri).getSystemState("/probe")
            # robot B's own tools read why (a README deployment audit: only "denied by cryptoros")
            assert code != 1 and message == "denied by cryptoros: exposed_master", message
            assert "exposed_master" in net.hosts["master"].logs().split("master streams refused", 1)[1]
            status = status_text(net, "master")
            assert "warning   master streams refused (exposed_master)" in status, status
            # not healthy while it refuses: status exits 1 with the reason, /healthz 503
            result = run_on(net, "master", [tool("cryptoros"), "status", "--config", str(master.config)])
            assert result.returncode == 1 and "exposed_master" in result.stdout.splitlines()[0], result
            # the stranger reaches this rosmaster, but it holds no robot: nothing was replayed to it
            with net.inside("stranger"):
                state = xmlrpc.client.ServerProxy(f"http://{master.address}:{port}/").getSystemState("/stranger")
            assert "/talker_a" not in str(state), state
            assert "registrations replayed" not in net.hosts["master"].logs()

            # the operator overrides: served, with a warning in every status
            master.config.write_text("allow_exposed_master = true\n" + master.config.read_text())
            master.proc.send_signal(signal.SIGHUP)
            _wait_log(net, "master", "registrations replayed")
            status = status_text(net, "master")
            assert "warning   allow_exposed_master = true, served anyway" in status, status

            # fixed: rosmaster back on loopback, override gone; served, replayed, no warning
            master.config.write_text(master.config.read_text().replace("allow_exposed_master = true\n", ""))
            master.proc.send_signal(signal.SIGHUP)
            stop(exposed)
            _rosmaster(net, port, through_cryptoros_run=True)
            _wait_log(net, "master", "answers on loopback only now")
            _wait_rosmaster_holds(net, "/talker_a")  # replayed to the new rosmaster
            assert "warning" not in status_text(net, "master")
            assert run_on(net, "master", [tool("cryptoros"), "status", "--config", str(master.config)]).returncode == 0
            assert not reaches(net, "stranger", master.address, port)
        assert stranger.address  # the stranger's host was there all along


def test_the_masters_status_says_when_rosmaster_does_not_answer(tmp_path):
    """Deployment audit: rosmaster bound where the interceptor could not reach it (only
    ``[::1]``) left every robot call failing while the master's status said ok."""
    separate_hosts()
    require("rosmaster")
    with robot_network(tmp_path, netns=True) as net:
        master = net.hosts["master"]
        port = int(net.rosmaster_uri.rstrip("/").rsplit(":", 1)[1])
        status = [tool("cryptoros"), "status", "--config", str(master.config)]
        assert run_on(net, "master", status).returncode == 0
        stop(_lab_rosmaster(net))
        deadline = time.monotonic() + 20
        while (result := run_on(net, "master", status)).returncode == 0:
            assert time.monotonic() < deadline, "the master's status still said ok 20 s after rosmaster stopped"
            time.sleep(0.5)
        first = result.stdout.splitlines()[0]
        assert result.returncode == 1 and "master_down" in first and f"127.0.0.1:{port}" in first, result
        _rosmaster(net, port, through_cryptoros_run=True)
        deadline = time.monotonic() + 20
        while run_on(net, "master", status).returncode != 0:
            assert time.monotonic() < deadline, "the master's status did not say ok again after rosmaster came back"
            time.sleep(0.5)


def test_a_node_other_hosts_reach_is_refused_and_the_same_node_through_cryptoros_run_works(tmp_path):
    separate_hosts()
    with robot_network(tmp_path, netns=True) as net:
        exposed_env = net.ros_env("robot_a")
        del exposed_env["ROS_IP"]  # as a node's shell is by default: rospy binds every address
        # a stock tool as an operator starts it: refused, and asked to shut down (a refused
        # rospy subscriber keeps running, its port open to a stranger's publisherUpdate)
        echo = [SYS_PY, shutil.which("rostopic"), "echo", "/chatter", "__name:=echo_exposed"]
        with running(echo, env=exposed_env) as exposed:
            lines = read_lines(exposed, None, 30)  # until it exits
            try:
                exposed.wait(5)
            except subprocess.TimeoutExpired:
                raise AssertionError("the exposed node still runs after 30 s:\n" + "".join(lines)) from None
        refusals = [line for line in lines if "exposed_endpoint" in line]
        assert refusals, lines
        assert "denied by cryptoros: exposed_endpoint: node /echo_exposed's XML-RPC API listens on 0.0.0.0 port" in \
            refusals[0] and "ROS_IP=127.0.0.1" in refusals[0] and "Traceback" not in "".join(lines)
        assert "DENY local-master from local node: exposed_endpoint" in net.hosts["robot_a"].logs()
        _wait_log(net, "robot_a", "node /echo_exposed listens where other hosts reach it")
        assert "/echo_exposed listens where other hosts reach it (port" in net.hosts["robot_a"].logs() and \
            "could not be asked" not in net.hosts["robot_a"].logs()

        config_a, config_b = net.hosts["robot_a"].config, net.hosts["robot_b"].config
        home = {"ROS_HOME": str(net.workdir / "ros_home"), "PYTHONUNBUFFERED": "1"}
        listener = net.argv("robot_b", ["bash", "-c", f'eval "$({tool("cryptoros")} env --config {config_b})" && '
                                                      f"exec {SYS_PY} {NODE} sub /rospy_listener /chatter 60"])
        talker = net.argv("robot_a", [tool("cryptoros"), "run", "--config", str(config_a), "--",
                                      SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "30"])
        with running(listener, env=clean_env(ROS_IP="10.9.9.9", ROS_HOSTNAME="robot-b", **home)) as sub, \
                running(talker, env=clean_env(ROS_HOSTNAME="robot-a", **home)) as pub:
            read_lines(sub, "READY", 30)
            read_lines(pub, "READY", 30)
            assert got(read_lines(sub, "GOT", 30)), "no message through cryptoros run / cryptoros env"
        assert net.hosts["robot_a"].logs().count("exposed_endpoint") == \
            net.hosts["robot_a"].logs().count("DENY local-master from local node: exposed_endpoint")


def test_a_node_on_the_master_host_registered_directly_and_reachable_is_shut_down(tmp_path):
    """Deployment audit: a tool run on the master host with ROS_IP on the host's network
    address registers with rosmaster directly, past every interceptor: nothing refused
    it, a stranger read its topic, and robots' subscribers of that topic were refused
    (``foreign_uri``). The master's interceptor now looks at each node rosmaster holds:
    this one is asked to shut down and named in the log; one on loopback is left alone."""
    separate_hosts()
    with robot_network(tmp_path, netns=True) as net:
        master = net.hosts["master"]
        echo = [SYS_PY, shutil.which("rostopic"), "echo", "/chatter"]
        private_env = net.ros_env(None)
        exposed_env = {**net.ros_env(None), "ROS_IP": master.address}
        with running([*echo, "__name:=mhost_private"], env=private_env) as private, \
                running([*echo, "__name:=mhost_exposed"], env=exposed_env) as exposed:
            _wait_rosmaster_holds(net, "/mhost_exposed")
            lines = read_lines(exposed, None, 30)  # until it exits
            try:
                exposed.wait(5)
            except subprocess.TimeoutExpired:
                raise AssertionError("the exposed node still runs after 30 s:\n" + "".join(lines)) from None
            assert "Traceback" not in "".join(lines), lines
            logs = master.logs()
            assert "DENY master-host node: exposed_endpoint: node /mhost_exposed's XML-RPC API listens on" in logs
            _wait_log(net, "master", "node /mhost_exposed listens where other hosts reach it (port")
            assert "could not be asked" not in master.logs()
            assert private.poll() is None and "mhost_private" not in master.logs()
        # re-audit: one that takes a robot's node name was skipped (the name was the robot's),
        # and rosmaster dropped the robot's registrations for it
        with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "120"],
                     env=net.ros_env("robot_a")) as pub:
            read_lines(pub, "READY", 20)
            _wait_rosmaster_holds(net, "/talker_a")
            impostor = [SYS_PY, shutil.which("rostopic"), "pub", "/chatter", "std_msgs/String", "impostor",
                        "-r", "5", "__name:=talker_a"]
            with running(impostor, env=exposed_env) as taken:
                lines = read_lines(taken, None, 30)
                try:
                    taken.wait(5)
                except subprocess.TimeoutExpired:
                    raise AssertionError("the impostor still runs after 30 s:\n" + "".join(lines)) from None
            _wait_log(net, "master", "/talker_a's name was taken here: ")
            _wait_rosmaster_holds(net, "/talker_a")  # the robot's registrations, made again
            with net.inside("master"):
                uri = xmlrpc.client.ServerProxy(net.rosmaster_uri).lookupNode("/t", "/talker_a")[2]
            assert uri.startswith("http://127.0.0.1:") and "/cryptoros/" in uri, uri  # the robot's relay again


def test_a_second_interceptor_with_the_same_config_exits_naming_the_first_and_changes_nothing(tmp_path):
    separate_hosts()
    with robot_network(tmp_path, start=("master", "robot_a"), policy=flow_policy(), netns=True) as net:
        host = net.hosts["robot_a"]
        state = tmp_path / "robot_a.state"  # the default state_dir: beside the configuration
        # robot A's /flow to robot C runs through the first instance all along
        with legit_flow(net, "robot_a", "robot_c") as flow, \
                running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "3", "20", "60"],
                        env=net.ros_env("robot_a")) as pub:
            read_lines(pub, "SENT", 30)
            saved = state / "robot_a.state.json"
            deadline = time.monotonic() + 10
            while not saved.exists():
                assert time.monotonic() < deadline, "no state file"
                time.sleep(0.1)
            before = saved.read_bytes(), saved.stat().st_mtime_ns
            assert oct(state.stat().st_mode & 0o777) == "0o700"
            with flow.held("the second starts"):
                for where in ("robot_a", "robot_b"):  # the same host, or another by mistake
                    second = run_on(net, where, [tool("cryptoros-interceptor"), "--config", str(host.config)])
                    lines = second.stderr.strip().splitlines()
                    assert second.returncode == 1 and len(lines) == 1, second
                    assert f"pid {host.proc.pid}" in lines[0] and "nothing was changed" in lines[0]
                    assert (saved.read_bytes(), saved.stat().st_mtime_ns) == before
            assert host.proc.poll() is None
        stop(host.proc)
        net.start("robot_a")  # the lock went with the process: a restart takes it
        assert (state / "robot_a.lock").read_text().strip() == str(host.proc.pid)


def test_the_embedded_master_binds_loopback_and_refuses_another_address_without_the_unsafe_flag():
    from cryptoros.exposure import read_listeners
    from cryptoros.lab.netns import NetnsLab

    separate_hosts()
    with NetnsLab() as lab:
        host = lab.add_host("m")
        refused = subprocess.run(host.argv([tool("cryptoros"), "master", "--host", "0.0.0.0", "--port", "11311"]),
                                 capture_output=True, text=True, timeout=60)
        lines = refused.stderr.strip().splitlines()
        assert refused.returncode == 1 and len(lines) == 1 and "--unsafe-expose" in lines[0], refused
        proc = subprocess.Popen(host.argv([tool("cryptoros"), "master", "--port", "11311"]),
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            with host.inside():
                wait_port("127.0.0.1", 11311, 20, proc, "cryptoros master")
                assert {str(one.address) for one in read_listeners(11311)} == {"127.0.0.1"}
        finally:
            stop(proc)


def test_a_node_respawned_exposed_is_shut_down_at_once_each_time_and_named_in_status(tmp_path):
    """Stranger audit: a launch file's ``respawn="true"`` started a refused exposed node
    (``__ip:=0.0.0.0``) again each time it was asked to shut down; a stranger reached it
    half of the time and fed it messages, and status said ok. From its second start the
    node is asked to shut down at once, and ``cryptoros status`` names it; on the master
    host each respawned process is asked too."""
    require("roslaunch")
    separate_hosts()
    with robot_network(tmp_path, netns=True) as net:
        assert net.cli("grant-tools", "robot_a", "--roslaunch").returncode == 0
        launch = tmp_path / "respawn.launch"
        # a rospy node that runs on when refused, until asked to shut down (rostopic, through
        # cryptoros run, ends itself at a refused registration, before it could be asked)
        ros_package(tmp_path / "pkgs", "crguard", {"listener.py": SPINNING_LISTENER})
        launch.write_text('<launch>\n  <node pkg="crguard" type="listener.py" name="echo_respawn" '
                          'args="__ip:=0.0.0.0" respawn="true"/>\n</launch>\n')
        config = net.hosts["robot_a"].config
        roslaunch = net.argv("robot_a", [tool("cryptoros"), "run", "--config", str(config), "--", "roslaunch",
                                         str(launch)])
        home = {"ROS_HOME": str(net.workdir / "ros_home"), "PYTHONUNBUFFERED": "1",
                "ROS_PACKAGE_PATH": str(tmp_path / "pkgs")}
        with running(roslaunch, env=clean_env(PATH="/usr/bin:/bin", **home)):  # the nodes on Debian's Python
            deadline = time.monotonic() + 60
            while net.hosts["robot_a"].logs().count("node /echo_respawn listens where other hosts reach it") < 4:
                assert time.monotonic() < deadline, net.hosts["robot_a"].logs()[-3000:]
                time.sleep(0.2)
            status = status_text(net, "robot_a")
            # read while roslaunch runs: the process it started last is killed with it, maybe
            # before it could be asked (seen under load)
            logs = net.hosts["robot_a"].logs()
        assert "nodes started again and again where other hosts reach them" in status and "/echo_respawn (" in status, \
            status
        assert "could not be asked" not in logs
        # on the master host, where nodes register with rosmaster directly: the respawned
        # process (same name, a new port) was never asked, and stayed reachable
        master = net.hosts["master"]
        launch.write_text('<launch>\n  <node pkg="rostopic" type="rostopic" name="echo_mhost" '
                          f'args="echo /chatter __ip:={master.address}" respawn="true"/>\n</launch>\n')
        with running(net.argv("master", ["roslaunch", str(launch)]), env={**net.ros_env(None), "PATH": "/usr/bin:/bin"}):
            deadline = time.monotonic() + 60
            while master.logs().count("node /echo_mhost listens where other hosts reach it") < 3:
                assert time.monotonic() < deadline, master.logs()[-3000:]
                time.sleep(0.2)
            logs = master.logs()
        assert "could not be asked" not in logs
