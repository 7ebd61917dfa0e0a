"""ROS 1: grants take effect for running nodes both ways, and
restarts never break the graph. Real rosmaster, rospy nodes, interceptors and authz
daemon; grants changed only with ``cryptoros-authz grant/revoke``; no node is restarted.
Every wait is bounded and ends on something observed (a message received, a line
logged, a registration listed), never on a sleep.
"""

from __future__ import annotations

import subprocess
import time

import pytest

from tests.interceptor_harness import NODE, NODES, SYS_PY, got, read_lines, robot_network, wait_registered
from cryptoros.lab.network import tool
from tests.support import on_host, running

pytestmark = [pytest.mark.ros1]


@pytest.fixture(scope="module")
def network(tmp_path_factory):
    # robot A's dead node stays listed (its interceptor does not clean it up) for the
    # dead-node test below, as when a robot's interceptor is down
    with robot_network(tmp_path_factory.mktemp("graph"), start=("master", "robot_a", "robot_b"),
                       limits={"dead_node_check": 0}) as net:
        yield net


def wait_logged(network, host: str, text: str, timeout: float = 15) -> None:
    logs = network.hosts[host].logs
    deadline = time.monotonic() + timeout
    while text not in logs():
        assert time.monotonic() < deadline, f"{host} never logged {text!r}:\n" + logs()[-3000:]
        time.sleep(0.1)


def first_message_within(proc, seconds: float, since: float | None = None) -> float:
    """Seconds from ``since`` (now) until the node printed its next GOT line (fails
    past ``seconds`` from now)."""
    started = time.monotonic() if since is None else since
    assert got(read_lines(proc, "GOT", seconds)), f"nothing received within {seconds} s"
    return time.monotonic() - started


def test_a_subscriber_running_before_its_grant_receives_once_it_is_granted(network):
    """robot B's listener starts with no grant (its registerSubscriber is refused); the
    grant is added: it receives robot A's talker, the listener never restarted."""
    with running([SYS_PY, NODE, "pub", "/talker_a", "/secret", "100000", "20", "90"],
                 env=network.ros_env("robot_a")) as pub, \
            running([SYS_PY, NODE, "sub", "/listener_early", "/secret", "90"], env=network.ros_env("robot_b")) as sub:
        read_lines(pub, "READY", 20)
        read_lines(sub, "READY", 20)
        wait_registered(network, "/talker_a")
        wait_logged(network, "robot_b", "/listener_early may not subscribe")  # refused: no grant yet
        granted = time.monotonic()
        network.cli("grant", "robot_b", "subscribe", "/listener_early", "/secret", "std_msgs/String")
        took = first_message_within(sub, 15, since=granted)
        print(f"subscriber before its grant: first message {took:.2f} s after `grant`")
        assert sub.poll() is None


def test_a_publisher_running_before_its_grant_reaches_its_subscriber_once_granted(network):
    """robot A's talker starts with no publish grant; robot B's listener (granted) waits;
    the grant is added: rosmaster learns the publication and the listener receives."""
    with running([SYS_PY, NODE, "sub", "/rospy_listener", "/chatter", "90"], env=network.ros_env("robot_b")) as sub, \
            running([SYS_PY, NODE, "pub", "/talker_early", "/chatter", "100000", "20", "90"],
                    env=network.ros_env("robot_a")) as pub:
        read_lines(sub, "READY", 20)
        read_lines(pub, "READY", 20)
        wait_registered(network, "/rospy_listener")
        granted = time.monotonic()
        network.cli("grant", "robot_a", "publish", "/talker_early", "/chatter", "std_msgs/String")
        took = first_message_within(sub, 15, since=granted)
        print(f"publisher before its grant: first message {took:.2f} s after `grant`")
        assert pub.poll() is None


def pause_before_the_grant(network, pause: str, cutter: str, cuts: int, sub) -> None:
    """Between a revoke and the grant given back: ``none``, ``half_a_second`` (as a script
    does it), or ``after_the_cut``: until ``cutter`` logged one more ``grant_removed`` than
    ``cuts``, and a second of the listener's lines (what was in flight) is read."""
    if pause == "half_a_second":
        time.sleep(0.5)
    elif pause == "after_the_cut":
        deadline = time.monotonic() + 15
        while network.hosts[cutter].logs().count("grant_removed") == cuts:
            assert time.monotonic() < deadline, f"{cutter} never cut the stream the removed grant covered"
            time.sleep(0.1)
        read_lines(sub, None, 1.0)


@pytest.mark.parametrize("pause", ["none", "half_a_second", "after_the_cut"])
def test_a_grant_removed_and_added_back_reaches_the_running_subscriber_within_10_s(network, pause):
    """Robot B's subscribe grant removed, then given back at once, half a second later or
    once its stream was cut and stayed silent: the running listener receives again. Robot B counts no refusal
    of its own against robot A for the stream either side cut (a day-2 audit: `DENY relay
    ... connection closed in the middle of a header` after a grant given back at once)."""
    network.cli("grant", "robot_b", "subscribe", "/listener_back", "/secret", "std_msgs/String")
    with running([SYS_PY, NODE, "pub", "/talker_a", "/secret", "100000", "20", "120"],
                 env=network.ros_env("robot_a")) as pub, \
            running([SYS_PY, NODE, "sub", "/listener_back", "/secret", "120"], env=network.ros_env("robot_b")) as sub:
        read_lines(pub, "READY", 20)
        read_lines(sub, "READY", 20)
        first_message_within(sub, 20)
        cuts, seen_b = network.hosts["robot_a"].logs().count("grant_removed"), len(network.hosts["robot_b"].logs())
        network.cli("revoke", "robot_b", "subscribe", "/listener_back", "/secret")
        pause_before_the_grant(network, pause, "robot_a", cuts, sub)
        if pause == "after_the_cut":
            assert not got(read_lines(sub, None, 1.0)), "still receiving after the grant was removed"
        granted = time.monotonic()
        network.cli("grant", "robot_b", "subscribe", "/listener_back", "/secret", "std_msgs/String")
        took = first_message_within(sub, 10, since=granted)
        print(f"grant removed and added back ({pause}): first message {took:.2f} s after `grant`")
        read_lines(sub, None, 1.0)  # a second of flow: robot B's interceptor has logged what it would
        assert sub.poll() is None and pub.poll() is None
    log_b = network.hosts["robot_b"].logs()[seen_b:]
    assert "DENY relay" not in log_b, log_b[-3000:]


def test_a_second_process_under_a_nodes_name_shuts_the_first_down_as_rosmaster_does(network):
    """Day-2 audit: ``rostopic echo ... __name:=listener`` beside a running ``/listener``
    left the first process running and deaf (rosmaster dropped its registrations; its
    ``shutdown`` call to it is never forwarded) with nothing said. As in plain ROS, the
    first process is told to shut down, with rosmaster's words."""
    network.cli("grant", "robot_b", "subscribe", "/listener_twice", "/twice", "std_msgs/String")
    argv = [SYS_PY, NODE, "sub", "/listener_twice", "/twice", "60"]
    with running(argv, env=network.ros_env("robot_b")) as first:
        read_lines(first, "READY", 20)
        wait_registered(network, "/listener_twice")
        with running(argv, env=network.ros_env("robot_b")) as second:
            read_lines(second, "READY", 20)
            lines = read_lines(first, "shutdown request", 15)
            assert "[/listener_twice] Reason: new node registered with same name" in lines[-1], lines
            assert second.poll() is None
        wait_logged(network, "robot_b", "its previous process")


def test_a_dead_node_of_another_robot_looks_unreachable_to_rosnode_ping(network):
    """Day-2 audit: ``rosnode ping`` of robot A's node killed without unregistering got
    ``[-1, "cryptoros: no answer ..."]`` through robot B's relay; rosnode raised it past
    its handlers (``ERROR: remote call failed``), and ``rosnode cleanup`` stopped there on
    every robot. The relay now resets the tool's connection, as a dead node's port does."""
    network.cli("grant", "robot_a", "subscribe", "/stale_one", "/stale_topic", "std_msgs/String")
    with running([SYS_PY, NODE, "sub", "/stale_one", "/stale_topic", "60"], env=network.ros_env("robot_a")) as stale:
        read_lines(stale, "READY", 20)
        wait_registered(network, "/stale_one")
        stale.kill()  # no unregistration: rosmaster still lists it
        stale.wait(10)
    env = {**network.ros_env("robot_b"), "PATH": "/usr/bin:/bin"}
    ping = subprocess.run(on_host(["rosnode", "ping", "-c", "1", "/stale_one"], env), env=env, capture_output=True,
                          text=True, timeout=60)
    assert "connection to [/stale_one] failed" in ping.stderr, ping
    assert "remote call failed" not in ping.stderr + ping.stdout and "Traceback" not in ping.stderr, ping
    # rosnode cleanup through cryptoros run: robot A's node may not be purged by robot B
    # (one line), and the cleanup goes on to its end
    cleanup = subprocess.run(on_host([tool("cryptoros"), "run", "--config", str(network.hosts["robot_b"].config), "--",
                                      "rosnode", "cleanup"], env), env=env, input="y\n", capture_output=True,
                             text=True, timeout=60)
    assert " * /stale_one" in cleanup.stdout and cleanup.stdout.rstrip().endswith("done"), cleanup
    # no grant of robot B's could allow it: the line points at none (a day-2 audit: "not_granted
    # (cryptoros denials says what to grant)")
    assert any(line in ("ERROR: /stale_one: denied by cryptoros: not_its_node",
                        "ERROR: /stale_one: denied by cryptoros: name_taken") for line in cleanup.stderr.splitlines()), \
        cleanup
    assert "Traceback" not in cleanup.stderr, cleanup


@pytest.mark.parametrize("pause", ["none", "half_a_second", "after_the_cut"])
def test_a_publish_grant_removed_and_added_back_reaches_the_running_subscriber_within_10_s(network, pause):
    """The publisher's side: robot B cuts the stream when robot A's publish grant goes;
    when it comes back, robot A makes the running talker's registration again and
    rosmaster tells the listener, which receives again. Given back with no pause, half a
    second after the revoke, or a second after the cut: then the listener's retry, refused, is followed by rospy's
    check, which drops the publisher (robot B tells it the publishers again on robot A's
    next token; without that, the listener stayed deaf in every run)."""
    # a topic robot A's grants name only here: robot B's token, narrowed to robot A's names,
    # loses its subscription with robot A's grant
    network.cli("grant", "robot_b", "subscribe", "/listener_pb", "/pub_back", "std_msgs/String")
    network.cli("grant", "robot_a", "publish", "/talker_back", "/pub_back", "std_msgs/String")
    with running([SYS_PY, NODE, "sub", "/listener_pb", "/pub_back", "120"], env=network.ros_env("robot_b")) as sub, \
            running([SYS_PY, NODE, "pub", "/talker_back", "/pub_back", "100000", "20", "120"],
                    env=network.ros_env("robot_a")) as pub:
        read_lines(sub, "READY", 20)
        read_lines(pub, "READY", 20)
        first_message_within(sub, 20)
        cuts = network.hosts["robot_b"].logs().count("grant_removed")
        seen_a, seen_b = len(network.hosts["robot_a"].logs()), len(network.hosts["robot_b"].logs())
        network.cli("revoke", "robot_a", "publish", "/talker_back", "/pub_back")
        pause_before_the_grant(network, pause, "robot_b", cuts, sub)
        granted = time.monotonic()
        network.cli("grant", "robot_a", "publish", "/talker_back", "/pub_back", "std_msgs/String")
        took = first_message_within(sub, 10, since=granted)
        print(f"publish grant removed and added back ({pause}): first message {took:.2f} s after `grant`")
        assert sub.poll() is None and pub.poll() is None
    # robot B's subscription, asked for while robot A's grant was gone, is refused as robot
    # A's: the token robot B shows is narrowed to names robot A holds, and lost it with
    # robot A's grant (a day-2 audit: "/listener_pb may not subscribe", with a grant to add)
    log_a = network.hosts["robot_a"].logs()[seen_a:]
    assert "may not subscribe /pub_back" not in log_a, log_a[-3000:]
    # nor does robot B count a refusal of its own against robot A for a stream either side cut
    log_b = network.hosts["robot_b"].logs()[seen_b:]
    assert "DENY relay" not in log_b, log_b[-3000:]


def test_a_registration_waiting_for_its_grant_is_kept_across_its_interceptors_restart(tmp_path):
    """robot B's listener is refused (no grant); robot B's interceptor stops, the grant is
    added meanwhile, and it starts again from its state directory: it makes the waiting
    registration, and the listener (never restarted) receives."""
    with robot_network(tmp_path, extra={"robot_b": f'state_dir = "{tmp_path / "state"}"'}) as net, \
            running([SYS_PY, NODE, "pub", "/talker_a", "/secret", "100000", "20", "90"],
                    env=net.ros_env("robot_a")) as pub, \
            running([SYS_PY, NODE, "sub", "/listener_wait", "/secret", "90"], env=net.ros_env("robot_b")) as sub:
        read_lines(pub, "READY", 20)
        read_lines(sub, "READY", 20)
        wait_logged(net, "robot_b", "/listener_wait may not subscribe")
        net.stop("robot_b")
        net.cli("grant", "robot_b", "subscribe", "/listener_wait", "/secret", "std_msgs/String")
        net.start("robot_b")
        took = first_message_within(sub, 15)
        print(f"a registration kept across a restart: first message {took:.2f} s after the restart")
        assert sub.poll() is None


@pytest.mark.parametrize("state", ["kept", "lost"])
def test_after_its_interceptors_restart_a_grant_given_back_reaches_a_running_subscriber_and_a_node_dead_meanwhile_is_cleaned_up(
        tmp_path, state):
    """A README deployment audit (day-2): robot B's interceptor restarted (the runbook's
    step) while its listener ran, and another listener was killed while it was down.
    Then the running listener's subscribe grant is removed and given back once its
    stream was cut: it receives again within 10 s (it stayed silent for minutes: the
    restarted interceptor had forgotten the registrations its nodes made before, so the
    grant given back made none of them again); and the node that died meanwhile has its
    registrations withdrawn by the dead-node check, as if it had died with the
    interceptor up (it stayed in rosnode list for good). With its state directory
    ``kept`` (the default one, beside the configuration) or ``lost`` (removed while it
    was down: what it knows is taken back from rosmaster)."""
    import shutil

    from interceptor.config import default_state_dir

    with robot_network(tmp_path, limits={"dead_node_check": 1}) as net, \
            running([SYS_PY, NODE, "pub", "/talker_a", "/secret", "100000", "20", "120"],
                    env=net.ros_env("robot_a")) as pub, \
            running([SYS_PY, NODE, "sub", "/listener_back", "/secret", "120"], env=net.ros_env("robot_b")) as sub, \
            running([SYS_PY, NODE, "sub", "/listener_dies", "/secret", "120"], env=net.ros_env("robot_b")) as dies:
        net.cli("grant", "robot_b", "subscribe", "/listener_back", "/secret", "std_msgs/String")
        net.cli("grant", "robot_b", "subscribe", "/listener_dies", "/secret", "std_msgs/String")
        for proc in (pub, sub, dies):
            read_lines(proc, "READY", 20)
        first_message_within(sub, 20)
        net.stop("robot_b")
        dies.kill()
        dies.wait(10)
        if state == "lost":
            shutil.rmtree(default_state_dir(net.hosts["robot_b"].config))
        net.start("robot_b")
        first_message_within(sub, 15)
        wait_logged(net, "robot_b", "/listener_dies died without unregistering", timeout=20)
        cuts = net.hosts["robot_a"].logs().count("grant_removed")
        net.cli("revoke", "robot_b", "subscribe", "/listener_back", "/secret")
        pause_before_the_grant(net, "after_the_cut", "robot_a", cuts, sub)
        assert not got(read_lines(sub, None, 1.0)), "still receiving after the grant was removed"
        granted = time.monotonic()
        net.cli("grant", "robot_b", "subscribe", "/listener_back", "/secret", "std_msgs/String")
        took = first_message_within(sub, 10, since=granted)
        print(f"after a restart ({state}), a grant given back: first message {took:.2f} s after `grant`")
        env = {**net.ros_env("robot_b"), "PATH": "/usr/bin:/bin"}
        nodes = subprocess.run(on_host(["rosnode", "list"], env), env=env, capture_output=True, text=True, timeout=60)
        assert "/listener_back" in nodes.stdout and "/listener_dies" not in nodes.stdout, nodes
        assert sub.poll() is None and pub.poll() is None


def call_service(net, host: str) -> str:
    """A rospy service client on ``host`` calls robot A's /rospy_loggers: its LOGGERS line."""
    with running([SYS_PY, str(NODES / "services.py"), "call", "/rospy_loggers"], env=net.ros_env(host)) as client:
        return read_lines(client, "LOGGERS", 20)[-1]


@pytest.mark.parametrize("state", ["state_dir", "no_state_dir"])
@pytest.mark.parametrize("restarted", ["master", "robot_a", "robot_b"])
def test_after_an_interceptor_restart_the_graph_works(tmp_path, restarted, state):
    """robot A's talker and service server and robot B's listener keep running while one
    interceptor restarts, with its state directory or with none: the listener receives
    again within 15 s, and a listener started after the restart receives and a service
    call answers, each within its first bounded wait."""
    extra = ({name: f'state_dir = "{tmp_path / "state" / name}"' for name in ("master", "robot_a", "robot_b")}
             if state == "state_dir" else None)
    with robot_network(tmp_path, extra=extra) as net, \
            running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "120"],
                    env=net.ros_env("robot_a")) as pub, \
            running([SYS_PY, str(NODES / "services.py"), "serve", "0", "120"], env=net.ros_env("robot_a")) as server, \
            running([SYS_PY, NODE, "sub", "/rospy_listener", "/chatter", "120"], env=net.ros_env("robot_b")) as sub:
        for proc in (pub, server, sub):
            read_lines(proc, "READY", 20)
        first_message_within(sub, 20)
        assert "rospy.server=debug" in call_service(net, "robot_b")
        net.stop(restarted)
        net.start(restarted)
        restarted_at = time.monotonic()
        read_lines(sub, None, 0.2)  # what arrived before the restart
        took = first_message_within(sub, 15, since=restarted_at)
        with running([SYS_PY, NODE, "sub", "/victim", "/chatter", "60"], env=net.ros_env("robot_b")) as late:
            read_lines(late, "READY", 20)
            late_took = first_message_within(late, 10)
        assert "rospy.server=debug" in call_service(net, "robot_b")
        print(f"{restarted} restarted ({state}): the running listener again after {took:.2f} s, "
              f"a new one {late_took:.2f} s after READY")
        assert pub.poll() is None and server.poll() is None and sub.poll() is None


def test_parameters_set_before_a_rosmaster_restart_are_there_after_it(tmp_path):
    """Past plain ROS: rosmaster dies and a new one starts on the same port; the master's
    interceptor sets again what peers set through it (a key deleted stays deleted)."""
    import subprocess

    from cryptoros.lab.network import clean_env, stop
    from tests.support import require, run

    require("rosparam")
    with robot_network(tmp_path, start=("master", "robot_b")) as net:
        net.cli("grant-tools", "robot_b", "--param-ns", "/")

        def rosparam(*argv: str) -> subprocess.CompletedProcess:
            return run(["rosparam", *argv], env=net.ros_env("robot_b"), timeout=20)

        deadline = time.monotonic() + 15
        while rosparam("set", "/robot/speed", "1.5").returncode != 0:  # the grant reaches robot B live
            assert time.monotonic() < deadline, "rosparam set still refused"
            time.sleep(0.5)
        assert rosparam("set", "/robot/name", "r1").returncode == 0
        assert rosparam("set", "/gone", "x").returncode == 0
        assert rosparam("delete", "/gone").returncode == 0
        old = next(p for p in net.procs if "--core" in p.args)  # Debian's rosmaster
        stop(old)
        new = subprocess.Popen(old.args, env=clean_env(ROS_MASTER_URI=net.rosmaster_uri, ROS_IP="127.0.0.1",
                                                         ROS_HOME=str(tmp_path)),
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        net.procs.append(new)
        wait_logged(net, "master", "parameters replayed")
        got_speed = rosparam("get", "/robot/speed")
        assert got_speed.returncode == 0 and got_speed.stdout.strip() == "1.5", got_speed
        assert rosparam("get", "/robot/name").stdout.strip() == "r1"
        assert rosparam("get", "/gone").returncode != 0  # deleted before the restart: not replayed
