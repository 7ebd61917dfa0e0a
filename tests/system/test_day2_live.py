"""Grants and revocations take effect live, and a stream never
outlives its authority. Real rosmaster, rospy nodes, interceptors and authz daemon;
only the admin CLI is used, never SIGHUP or a restart.

- A grant added with ``cryptoros-authz grant`` lets the node in within 10 s.
- A grant removed with ``cryptoros-authz revoke`` cuts exactly the stream it covered
  within 5 s; the robot's other stream keeps flowing.
- With the revocation feed stale, /healthz answers 503 and new streams are refused.
"""

from __future__ import annotations

import contextlib
import json
import subprocess
import time
import urllib.error
import urllib.request
import xmlrpc.client

import pytest

from tests.interceptor_harness import NODE, SYS_PY, robot_network, wait_registered
from cryptoros.lab.network import clean_env, stop
from tests.support import VENV_BIN, run, running, until
from tests.interceptor_harness import got, read_lines

pytestmark = [pytest.mark.ros1]


@pytest.fixture(scope="module")
def network(tmp_path_factory):
    with robot_network(tmp_path_factory.mktemp("day2"), start=("master", "robot_a", "robot_b")) as net:
        yield net



def arrivals(proc, seconds: float, window: float = 0.2) -> list[float]:
    """When a listener printed GOT lines during ``seconds`` (to within ``window``)."""
    out = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        lines = read_lines(proc, None, window)
        if any(line.startswith("GOT") for line in lines):
            out.append(time.monotonic())
    return out


def test_a_new_grant_takes_effect_within_10_s_and_removing_it_cuts_only_its_stream(network):
    local_b = xmlrpc.client.ServerProxy(network.hosts["robot_b"].master_uri)
    dummy = "http://127.0.0.1:9/"
    assert local_b.registerSubscriber("/listener_s", "/secret", "std_msgs/String", dummy)[0] == -1
    network.cli("grant", "robot_b", "subscribe", "/listener_s", "/secret", "std_msgs/String")
    started = time.monotonic()
    while local_b.registerSubscriber("/listener_s", "/secret", "std_msgs/String", dummy)[0] != 1:
        assert time.monotonic() - started < 10, "the new grant did not reach robot B's interceptor within 10 s"
        time.sleep(0.2)
    local_b.unregisterSubscriber("/listener_s", "/secret", dummy)
    with running([SYS_PY, NODE, "pub", "/talker_a", "/secret", "100000", "20", "60"], env=network.ros_env("robot_a")) as sec, \
            running([SYS_PY, NODE, "pub", "/rospy_talker", "/chatter", "100000", "20", "60"],
                    env=network.ros_env("robot_a")) as chat:
        read_lines(sec, "READY", 20)
        read_lines(chat, "READY", 20)
        wait_registered(network, "/talker_a")
        wait_registered(network, "/rospy_talker")
        with running([SYS_PY, NODE, "sub", "/listener_s", "/secret", "60"], env=network.ros_env("robot_b")) as s_sub, \
                running([SYS_PY, NODE, "sub", "/rospy_listener", "/chatter", "60"], env=network.ros_env("robot_b")) as c_sub:
            read_lines(s_sub, "READY", 20)
            read_lines(c_sub, "READY", 20)
            assert got(read_lines(s_sub, "GOT", 20))
            assert got(read_lines(c_sub, "GOT", 20))
            network.cli("revoke", "robot_b", "subscribe", "/listener_s", "/secret")
            revoked_at = time.monotonic()
            # /chatter keeps flowing, with no gap, while /secret stops within 5 s
            chatter = arrivals(c_sub, 6)
            read_lines(s_sub, None, 0.1)  # what /secret got until now, up to 6 s after the revoke
            secret = arrivals(s_sub, 2)
            assert not secret, "the revoked /secret stream still delivered 6 s after the revoke"
            assert chatter and chatter[-1] > revoked_at + 5
            gaps = [b - a for a, b in zip([revoked_at, *chatter], chatter)]
            assert max(gaps) < 1.0, f"the /chatter stream stalled {max(gaps):.2f} s"
    log = network.hosts["robot_a"].logs()
    assert "grant_removed" in log


def test_healthz_and_new_streams_fail_closed_when_the_feed_is_stale(tmp_path):
    from tests.interceptor_harness import rogue_preamble, rogue_tls

    extra = {"robot_a": "[limits]\nmax_feed_age = 3.0\n"}
    with robot_network(tmp_path, start=("master", "robot_a"), extra=extra) as net:
        host = net.hosts["robot_a"]
        health = f"http://127.0.0.1:{host.metrics_port}/healthz"
        assert json.loads(urllib.request.urlopen(health, timeout=5).read())["status"] == "ok"
        status, body = net.daemon.token("robot_b")
        assert status == 200
        net.authz_proc.terminate()
        net.authz_proc.wait(timeout=10)
        deadline = time.monotonic() + 15
        while True:
            try:
                urllib.request.urlopen(health, timeout=5)
            except urllib.error.HTTPError as exc:
                assert exc.code == 503
                assert json.loads(exc.read())["status"] == "feed_stale"
                break
            assert time.monotonic() < deadline, "/healthz never reported the stale feed"
            time.sleep(0.2)
        cert, key = net.pki.pki.cert_path_for("robot_b"), net.pki.pki.key_path_for("robot_b")
        with rogue_tls(host.address, host.public_port, ca=net.pki.ca_cert, cert=cert, key=key) as s:
            reply = rogue_preamble(s, body["access_token"], "node", "1")
        assert reply is None or reply.ok is False
        assert "feed_stale" in host.logs()


@contextlib.contextmanager
def talker_a_to_listener_b(tmp_path, *, seconds: int, extra: dict[str, str] | None = None):
    """A fresh network with robot A's talker reaching robot B's listener: (net, sub, pub)."""
    with robot_network(tmp_path, start=("master", "robot_a", "robot_b"), extra=extra) as net, \
            running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", str(seconds)],
                    env=net.ros_env("robot_a")) as pub:
        read_lines(pub, "READY", 20)
        wait_registered(net, "/talker_a")
        with running([SYS_PY, NODE, "sub", "/rospy_listener", "/chatter", str(seconds)],
                     env=net.ros_env("robot_b")) as sub:
            read_lines(sub, "READY", 20)
            assert got(read_lines(sub, "GOT", 20))
            yield net, sub, pub


@pytest.mark.parametrize("restarted", ["robot_a", "robot_b", "master"])
def test_restarting_an_interceptor_needs_no_node_restart(tmp_path, restarted):
    """The talker on A and the listener on B keep running; the interceptor of A (the
    publisher's), of B (the subscriber's) or of the master restarts with its state
    directory: the listener receives again within 10 s."""
    extra = {name: f'state_dir = "{tmp_path / "state" / name}"' for name in ("master", "robot_a", "robot_b")}
    with talker_a_to_listener_b(tmp_path, extra=extra, seconds=90) as (net, sub, pub):
        net.stop(restarted)
        read_lines(sub, None, 0.5)  # drain what arrived before the restart
        if restarted == "master":  # a call while the master's side is down: not worded as a denial
            with net.inside("robot_b"):
                code, text, _ = xmlrpc.client.ServerProxy(net.hosts["robot_b"].master_uri).getSystemState("/probe")
            assert code == -1 and "no answer" in text and "denied" not in text, text
        net.start(restarted)
        restarted_at = time.monotonic()
        read_lines(sub, None, 0.2)
        lines = read_lines(sub, "GOT", 10)
        assert got(lines), f"nothing arrived within 10 s of restarting {restarted}'s interceptor"
        assert time.monotonic() - restarted_at < 10.5
        assert sub.poll() is None and pub.poll() is None
        assert "state restored" in net.hosts[restarted].logs()


def test_a_restarted_rosmaster_gets_the_registrations_replayed(tmp_path):
    """Past plain ROS: rosmaster dies and a new one starts on the same port; the master's
    interceptor replays every registration it forwarded, so a listener started after
    the restart finds robot A's talker, with no node restarted."""
    with talker_a_to_listener_b(tmp_path, seconds=90) as (net, sub, pub):
        old = next(p for p in net.procs if "--core" in p.args)  # Debian's rosmaster
        stop(old)
        new = subprocess.Popen(old.args, env=clean_env(ROS_MASTER_URI=net.rosmaster_uri, ROS_IP="127.0.0.1",
                                                         ROS_HOME=str(tmp_path)),
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        net.procs.append(new)
        deadline = time.monotonic() + 15
        while "registrations replayed" not in net.hosts["master"].logs():
            assert time.monotonic() < deadline, "no replay within 15 s:\n" + net.hosts["master"].logs()
            time.sleep(0.2)
        code, _, state = xmlrpc.client.ServerProxy(net.rosmaster_uri).getSystemState("/probe")
        publishers = dict((topic, nodes) for topic, nodes in state[0])
        assert code == 1 and "/talker_a" in publishers.get("/chatter", []), state
        with running([SYS_PY, NODE, "sub", "/late_listener", "/chatter", "30"], env=net.ros_env("robot_b")) as late:
            read_lines(late, "READY", 20)
            assert got(read_lines(late, "GOT", 20)), "a listener started after the restart got nothing"
        read_lines(sub, None, 0.2)
        assert got(read_lines(sub, "GOT", 10)), "the old listener stopped receiving"
        assert sub.poll() is None and pub.poll() is None

def saved_exports(state) -> dict:
    """The exports in an interceptor's state file (id: [kind, host, port, uri])."""
    return json.loads(next(state.glob("*.state.json")).read_text())["translator"]["exports"]


def test_a_node_restarting_on_new_ports_releases_its_old_exports(tmp_path):
    """A node restart costs no export slot for good: when robot A's talker, killed with
    no chance to unregister, registers again from new ports, its old node API and TCPROS
    server exports are released (else about 5,000 restarts would use up export_limit and
    refuse every new node on the host). An ``unregister*`` the old process sends late
    (a node slow to shut down while its replacement starts) takes no export slot and
    leaves the new process's registrations and exports alone."""
    state = tmp_path / "state"
    with robot_network(tmp_path, start=("master", "robot_a", "robot_b"),
                       extra={"robot_a": f'state_dir = "{state}"'}) as net:
        sizes, previous = [], {}

        def released_and_new() -> dict | None:
            """The new process's exports once the state file holds still (a fresh-clone run
            read it between two of the talker's registrations: [2, 2, 3])."""
            exports = saved_exports(state)
            if len(exports) < 2 or not exports.keys().isdisjoint(previous):
                return None
            time.sleep(0.3)
            return exports if saved_exports(state) == exports else None

        for _ in range(3):
            with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "30"],
                         env=net.ros_env("robot_a")) as pub:
                read_lines(pub, "READY", 20)
                wait_registered(net, "/talker_a")
                with running([SYS_PY, NODE, "sub", "/rospy_listener", "/chatter", "30"],
                             env=net.ros_env("robot_b")) as sub:
                    read_lines(sub, "READY", 20)
                    assert got(read_lines(sub, "GOT", 20))  # the talker's TCPROS server was exported too
                exports = until(released_and_new, 10, f"the old exports released in the state file: {previous}")
                sizes.append(len(exports))
                previous = exports
                pub.kill()  # no unregistration: the next process's registration releases them
                pub.wait(10)
        assert sizes[0] >= 2 and sizes == [sizes[0]] * 3, sizes
        assert "released" in net.hosts["robot_a"].logs()

        old_api = next(uri for kind, _h, _p, uri in previous.values() if kind == "x")
        old_rpc = next(uri for kind, _h, _p, uri in previous.values() if kind == "t")
        with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "30"],
                     env=net.ros_env("robot_a")) as pub:
            read_lines(pub, "READY", 20)
            wait_registered(net, "/talker_a")
            current = until(released_and_new, 10, "the killed talker's exports released")
            local_a = xmlrpc.client.ServerProxy(net.hosts["robot_a"].master_uri)
            with net.inside("robot_a"):
                late = [local_a.unregisterPublisher("/talker_a", "/chatter", old_api),
                        local_a.unregisterPublisher("/talker_a", "/rosout", old_api),
                        local_a.unregisterService("/talker_a", "/talker_a/get_loggers", old_rpc),
                        local_a.unregisterService("/talker_a", "/talker_a/set_logger_level", old_rpc)]
            # nothing was registered under them: the master's interceptor has no relay for
            # them any more (unknown_endpoint), and rosmaster would find nothing either
            assert all(count == 0 and (code == 1 or "unknown_endpoint" in msg) for code, msg, count in late), late
            with running([SYS_PY, NODE, "sub", "/late_listener", "/chatter", "30"], env=net.ros_env("robot_b")) as sub:
                read_lines(sub, "READY", 20)
                assert got(read_lines(sub, "GOT", 20)), "the new talker's exports went with the old one's late unregister"
            assert saved_exports(state) == current  # nothing exported for the old endpoints


def test_nodes_that_shut_down_cleanly_under_new_names_release_their_exports(tmp_path):
    """Nodes that come and go under names never used again (rostopic, rosbag record and
    scripts run anonymous nodes) unregister everything when they shut down cleanly: robot
    A's interceptor then releases their exports, so the count returns to where it was
    (else a cron job running rostopic every minute would use up export_limit in days).
    A rospy node that logged keeps a parameter subscription rospy never withdraws: the
    interceptor withdraws it for the node, and the master's host releases its relay."""
    state = tmp_path / "state"
    with robot_network(tmp_path, start=("master", "robot_a", "robot_b"),
                       extra={"robot_a": f'state_dir = "{state}"'}) as net, \
            running([SYS_PY, NODE, "sub", "/rospy_listener", "/chatter", "60"], env=net.ros_env("robot_b")) as sub:
        read_lines(sub, "READY", 20)

        def exports() -> int:
            files = list(state.glob("*.state.json"))
            return len(json.loads(files[0].read_text())["translator"]["exports"]) if files else 0

        baseline = exports()
        relays_released = net.hosts["master"].logs().count("released (no registration behind it)")
        for name in ("/talker_a", "/rospy_talker", "/roscpp_talker"):  # three names, each used once
            with running([SYS_PY, NODE, "pub", name, "/chatter", "3", "20", "0.2"], env=net.ros_env("robot_a")) as pub:
                read_lines(pub, "SENT 3", 20)
                assert pub.wait(timeout=20) == 0  # exits by itself: rospy unregisters at exit
            deadline = time.monotonic() + 10
            while exports() != baseline:
                assert time.monotonic() < deadline, f"{name}: {exports()} exports, {baseline} before it ran"
                time.sleep(0.1)
        assert net.hosts["robot_a"].logs().count("of a node that unregistered everything") == 3
        # a rospy node that logs subscribes a parameter, and rospy never withdraws that
        # subscription: the interceptor does it for the node, so that its exports here and
        # its relay at the master's host go too (ROS 1 policy audit: two per node, for good)
        logged = run([SYS_PY, "-c", LOGGING_NODE, "rospy_talker"], env=net.ros_env("robot_a"), timeout=30)
        assert logged.returncode == 0 and "hello from /rospy_talker" in logged.stderr + logged.stdout, logged
        deadline = time.monotonic() + 10
        while exports() != baseline:
            assert time.monotonic() < deadline, f"logging /rospy_talker: {exports()} exports, {baseline} before it ran"
            time.sleep(0.1)
        assert "/rospy_talker unregistered all but 1 parameter subscription(s)" in net.hosts["robot_a"].logs()
        deadline = time.monotonic() + 10
        while net.hosts["master"].logs().count("released (no registration behind it)") < relays_released + 4:
            assert time.monotonic() < deadline, net.hosts["master"].logs()[-3000:]
            time.sleep(0.1)


#: a rospy node as people write them: it logs (rospy then subscribes a parameter) and publishes
LOGGING_NODE = """
import sys, rospy
from std_msgs.msg import String
rospy.init_node(sys.argv[1])
pub = rospy.Publisher('/chatter', String, queue_size=10, latch=True)
rospy.loginfo('hello from %s', rospy.get_name())
rospy.sleep(0.5)
pub.publish(String(data='x'))
rospy.sleep(0.5)
"""


def test_a_node_killed_without_unregistering_is_cleaned_up_as_rosnode_cleanup_would(tmp_path):
    """A node that dies without unregistering (SIGKILL, a crash) left rosmaster listing it,
    and its exports, relay and name held for good. Its robot's interceptor finds its API
    port closed and withdraws its registrations for it: rosmaster lists it no more and the
    master's host releases its relay."""
    import os
    import signal

    with robot_network(tmp_path, start=("master", "robot_a", "robot_b"), limits={"dead_node_check": 1}) as net, \
            running([SYS_PY, NODE, "sub", "/rospy_listener", "/chatter", "120"], env=net.ros_env("robot_b")) as sub:
        read_lines(sub, "READY", 20)
        wait_registered(net, "/rospy_listener")
        released = net.hosts["master"].logs().count("released (no registration behind it)")
        os.kill(sub.pid, signal.SIGKILL)
        sub.wait(timeout=10)

        def listed() -> bool:
            with net.inside("master"):
                state = xmlrpc.client.ServerProxy(net.rosmaster_uri).getSystemState("/test")[2]
            return "/rospy_listener" in {n for section in state for _name, nodes in section for n in nodes}

        until(lambda: not listed(), 20, "rosmaster no longer lists the killed /rospy_listener")
        assert "/rospy_listener died without unregistering" in net.hosts["robot_b"].logs()
        until(lambda: net.hosts["master"].logs().count("released (no registration behind it)") > released, 20,
              "the master's interceptor releases the killed node's relay")


#: A node of its own making (plain XML-RPC, as some clients are): it publishes and
#: subscribes a parameter, then unregisters its publication and lives on, printing each
#: parameter update the master sends it.
PARAM_ONLY_NODE = """
import os, sys, threading, xmlrpc.client
from xmlrpc.server import SimpleXMLRPCServer
server = SimpleXMLRPCServer(("127.0.0.1", 0), logRequests=False, allow_none=True)
uri = "http://127.0.0.1:%d/" % server.server_address[1]
server.register_function(lambda caller: [1, "", os.getpid()], "getPid")
def param_update(caller, key, value):
    print("UPDATE", key, value, flush=True)
    return [1, "", 0]
server.register_function(param_update, "paramUpdate")
threading.Thread(target=server.serve_forever, daemon=True).start()
master = xmlrpc.client.ServerProxy(os.environ["ROS_MASTER_URI"])
print(master.registerPublisher("/talker_a", "/chatter", "std_msgs/String", uri)[:2], flush=True)
print(master.subscribeParam("/talker_a", uri, "/talker_a/gain")[:2], flush=True)
print(master.unregisterPublisher("/talker_a", "/chatter", uri)[:2], flush=True)
print("READY", flush=True)
sys.stdin.readline()
"""


def test_a_live_node_left_with_only_parameter_subscriptions_keeps_them(tmp_path):
    """A node that unregisters all but its parameter subscriptions and keeps running
    (its API answers) keeps them: the master's updates still reach it. Only a node whose
    API no longer answers is taken to have exited, and they are withdrawn for it."""
    with robot_network(tmp_path, start=("master", "robot_a")) as net, \
            running([SYS_PY, "-c", PARAM_ONLY_NODE], env=net.ros_env("robot_a"), stdin=subprocess.PIPE) as node:
        lines = read_lines(node, "READY", 20)
        assert all(line.startswith("[1,") for line in lines[:3]), lines
        until(lambda: "and its API still answers: kept for it" in net.hosts["robot_a"].logs(), 20,
              "robot A's interceptor keeps the live node's parameter subscription")
        setter = xmlrpc.client.ServerProxy(net.hosts["robot_a"].master_uri)
        assert setter.setParam("/rospy_talker", "/talker_a/gain", 7)[0] == 1  # a node robot A's grants name
        assert any("UPDATE /talker_a/gain/ 7" in line for line in read_lines(node, "UPDATE", 20))
        assert "withdrawn for it" not in net.hosts["robot_a"].logs()


#: A subscriber node of our own node client with two subscriptions; on a line on stdin it
#: drops the second (one of the two registrations behind its relay at the master host).
TWO_SUBSCRIPTIONS = """
import asyncio, sys
from cryptoros.ros1.node import Node

async def main():
    node = Node("/listener_x", sys.argv[1], host="127.0.0.1")
    await node.start()
    await node.subscribe("/chatter", "std_msgs/String", lambda m: print("GOT", m.data, flush=True))
    await node.subscribe("/secret", "std_msgs/String", lambda m: None)
    print("SUBSCRIBED", flush=True)
    await asyncio.get_running_loop().run_in_executor(None, sys.stdin.readline)
    await node.unsubscribe("/secret")
    print("UNSUBSCRIBED", flush=True)
    await asyncio.sleep(60)

asyncio.run(main())
"""


def test_after_a_master_interceptor_restart_a_node_keeps_its_relay_until_its_last_registration(tmp_path):
    """The master's interceptor counts the registrations behind each relay it holds for
    rosmaster, and closes a relay when its last one goes. Restarted from its state, it
    counts the restored registrations again: a subscriber that drops one of its two
    subscriptions after the restart keeps its relay, so rosmaster still reaches it when a
    publisher appears (before, the counts started at zero and the first unregister
    closed the relay)."""
    import sys

    from tests.interceptor_harness import DEFAULT_POLICY

    policy = DEFAULT_POLICY.replace(
        "    - {{node: '*', topic: /chatter, type: std_msgs/String}}\n",
        "    - {{node: '*', topic: /chatter, type: std_msgs/String}}\n"
        "    - {{node: '*', topic: /secret, type: std_msgs/String}}\n")
    with robot_network(tmp_path, policy=policy, extra={"master": f'state_dir = "{tmp_path / "state"}"'}) as net, \
            running([sys.executable, "-c", TWO_SUBSCRIPTIONS, net.hosts["robot_b"].master_uri],
                    env=net.ros_env("robot_b"), stdin=subprocess.PIPE) as listener:
        read_lines(listener, "SUBSCRIBED", 20)
        net.stop("master")
        net.start("master")
        assert "state restored" in net.hosts["master"].logs()
        listener.stdin.write("\n")
        listener.stdin.flush()
        read_lines(listener, "UNSUBSCRIBED", 20)
        with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "1"], env=net.ros_env("robot_a")):
            assert got(read_lines(listener, "GOT", 20)), "rosmaster no longer reaches the listener"


def test_a_certificate_revoked_by_the_ca_is_cut_everywhere_within_5_s_without_sighup(tmp_path):
    """Day 2, revocation without SIGHUP: robot B's certificate is revoked with the CA
    (a new CRL; no interceptor is signalled). The authorization server's feed lists the
    serial, so robot A cuts robot B's open stream within 5 s and refuses its new ones
    (its token is bound to the revoked certificate); robot B's own interceptor drops
    its token (the feed names its serial) or finds its feed polls refused, and says so
    in /healthz (503)."""
    with talker_a_to_listener_b(tmp_path, seconds=60) as (net, sub, _pub):
        net.pki.revoke("robot_b")
        revoked_at = time.monotonic()
        deadline = revoked_at + 5
        while "certificate_revoked" not in net.hosts["robot_a"].logs():
            assert time.monotonic() < deadline, net.hosts["robot_a"].logs()[-3000:]
            time.sleep(0.1)
        read_lines(sub, None, 1.0)  # whatever was in flight
        assert not got(read_lines(sub, None, 3.0)), "robot B still receives over a revoked certificate"
        url = f"http://127.0.0.1:{net.hosts['robot_b'].metrics_port}/healthz"
        with pytest.raises(urllib.error.HTTPError) as unhealthy:
            urllib.request.urlopen(url, timeout=5)
        # it learnt it from the feed (its token dropped: no_token) or from the feed's 401 (authz_refused)
        assert unhealthy.value.code == 503
        assert b"authz_refused" in unhealthy.value.read() or "was revoked by the CA" in net.hosts["robot_b"].logs()
        if "was revoked by the CA" in net.hosts["robot_b"].logs():  # its token dropped (else held until it expires)
            # robot B's own tools say why in their one line; each of their calls asks for a
            # token again (so does the refresh loop): one warning for all of them
            config = str(net.hosts["robot_b"].config)
            for argv in (("rosnode", "list"), ("rosparam", "get", "/x")):
                refused = run([str(VENV_BIN / "cryptoros"), "run", "--config", config, "--", *argv],
                              env=net.ros_env("robot_b"), timeout=20)
                assert refused.returncode == 1 and refused.stderr.strip() == "ERROR: denied by cryptoros: no_token", \
                    refused
            assert net.hosts["robot_b"].logs().count("cannot refresh access token") == 1, net.hosts["robot_b"].logs()


def test_a_robot_disabled_and_revoked_then_readmitted_takes_its_new_certificate_on_sighup(tmp_path):
    """ROS 2 audit (the same gateway serves ROS 1): robot B disabled and its certificate
    revoked, as the runbook's "Revoke a robot's certificate" does, then re-admitted (a new
    certificate, set-cert, enable-manager) and reloaded as its error line says. The feed
    it held still listed its manager as disabled (a revoked certificate cannot poll it),
    and every reload was refused against it: ``subject_disabled`` while the registry said
    enabled. A reload reads the feed with the new certificate first."""
    import signal

    with talker_a_to_listener_b(tmp_path, seconds=120) as (net, sub, _pub):
        b = net.hosts["robot_b"]

        def status() -> dict:
            with urllib.request.urlopen(f"http://127.0.0.1:{b.metrics_port}/status", timeout=5) as reply:
                return json.loads(reply.read())

        assert net.cli("disable-manager", "robot_b").returncode == 0
        until(lambda: "robot_b" in status().get("feed", {}).get("disabled_managers", []), 15,
              "robot B's feed lists its own manager as disabled")
        net.pki.revoke("robot_b")
        until(lambda: "HTTP 401" in b.logs(), 20, "robot B's feed polls refused (its certificate revoked)")
        renewed = net.pki.issue("robot_b", kind="interceptor", sans=(f"IP:{b.address}",), force=True)
        assert net.cli("set-cert", "robot_b", "--fingerprint", renewed.fingerprint_sha256).returncode == 0
        assert net.cli("enable-manager", "robot_b").returncode == 0
        # the authorization server has taken the re-admission (its cache of the managers)
        until(lambda: net.daemon.token("robot_b")[0] == 200, 15, "a token for robot B's new certificate")
        before = len(b.logs())
        b.proc.send_signal(signal.SIGHUP)
        until(lambda: "reloaded certificates" in b.logs()[before:] or "reload failed" in b.logs()[before:], 20,
              "robot B's reload outcome")
        assert "reloaded certificates" in b.logs()[before:], b.logs()[before:][-2000:]
        assert got(read_lines(sub, "GOT", 30)), "robot B's listener receives nothing after its re-admission"


def test_a_robot_disabled_for_a_while_then_enabled_receives_again_within_5_s(tmp_path):
    """Robot B's manager disabled for 9 s (its streams cut, its token refused), then
    enabled: its running listener receives again within 5 s of the enable. A day-2 audit
    measured 7.9 s: the subscriber's interceptor waited out its 8 s back-off between
    token exchanges with robot A, its own token back meanwhile; the back-off now ends
    when its own token changes."""
    with talker_a_to_listener_b(tmp_path, seconds=120) as (net, sub, _pub):
        assert net.cli("disable-manager", "robot_b").returncode == 0
        try:
            deadline = time.monotonic() + 20
            while got(read_lines(sub, None, 1.0)):  # the cut
                assert time.monotonic() < deadline, "robot B still receives with its manager disabled"
            read_lines(sub, None, 8.0)  # its interceptor's exchanges with robot A back off meanwhile
        finally:
            assert net.cli("enable-manager", "robot_b").returncode == 0
        enabled = time.monotonic()
        assert got(read_lines(sub, "GOT", 15)), "robot B's listener receives nothing after the enable"
        took = time.monotonic() - enabled
        print(f"robot B disabled 9 s, then enabled: its listener receives again after {took:.1f} s")
        assert took < 5.0, f"the listener received again only {took:.1f} s after the enable"
