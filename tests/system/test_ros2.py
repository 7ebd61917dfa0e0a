"""The interceptor's ROS 2 role with real Jazzy rclpy nodes on separate domains.

Robot A (domain a), robot B (domain b), robot C (domain c), each behind its own
``cryptoros-interceptor`` (role ``ros2``); unmodified rclpy talkers, listeners, a
service server and a client as subprocesses (tests/ros2_nodes). The only way between
domains is the interceptors (see tests/ros2_support.py for the policy).
"""

from __future__ import annotations

import contextlib
import json
import re
import signal
import ssl
import struct
import time
import urllib.request

import jwt
import pytest
from cryptography.hazmat.primitives.asymmetric import rsa

from cryptoros.ros2.target import StreamTarget
from cryptoros.grants import Grants
from cryptoros.tokens import build_claims, sign_token
from tests.interceptor_harness import rogue_preamble, rogue_tls, signing_key
from tests.ros2_support import SET_BOOL, collect, collect_through, got, ros2_network
from tests.support import Capture, until


@pytest.fixture(scope="module")
def network(tmp_path_factory):
    with ros2_network(tmp_path_factory.mktemp("ros2")) as net:
        yield net


def test_talker_on_a_reaches_listener_on_b_through_the_interceptors(network):
    with network.node("robot_b", "listener.py", "string", "/chatter", "25") as sub:
        sub.until("READY", 20)
        with network.node("robot_a", "talker.py", "string", "/chatter", "100000", "20"):
            lines = collect(sub, 40, 25)
            # the sending robot's streams are open streams too (its status said 0 while its
            # metric said 1): both robots' status and /healthz count the /chatter stream
            for name in ("robot_a", "robot_b"):
                status, health = (_get_json(network, name, path) for path in ("/status", "/healthz"))
                assert status["peers"].get("robot_b" if name == "robot_a" else "robot_a", 0) >= 1, (name, status)
                assert status["open_streams"] == sum(status["peers"].values()) >= 1, (name, status)
                assert health["open_streams"] >= 1, (name, health)
    seqs = got(lines)
    assert not [line for line in lines if line.startswith("BAD")]
    assert seqs == list(range(seqs[0], seqs[0] + 40)), "messages lost or reordered"


def _get_json(network, name: str, path: str) -> dict:
    with urllib.request.urlopen(f"http://127.0.0.1:{network.robots[name].metrics_port}{path}", timeout=5) as reply:
        return json.loads(reply.read())


def test_reliable_burst_arrives_without_loss_through_the_interceptors(network):
    """KEEP_ALL talker and listener: once the path is up (first message), a burst of
    2,000 messages as fast as the talker can publish arrives whole and in order, as on a
    direct DDS path (flow control end to end, no drops in the bridges or interceptors)."""
    with network.node("robot_b", "listener.py", "string", "/chatter", "60", "--keep-all") as sub:
        sub.until("READY", 20)
        with network.node("robot_a", "talker.py", "string", "/chatter", "2100", "20", "--keep-all",
                          "--burst-on-signal") as talker:
            lines = collect(sub, 1, 60)  # the path is up: now the burst
            talker.proc.send_signal(signal.SIGUSR1)
            lines += collect_through(sub, 2099, 60)
    seqs = got(lines)
    assert not [line for line in lines if line.startswith("BAD")]
    assert seqs == list(range(seqs[0], 2100)), f"{2100 - seqs[0] - len(seqs)} message(s) lost or reordered"


def test_a_talker_frozen_past_its_dds_lease_keeps_its_offer_and_is_known_again(network):
    """The talker is stopped (SIGSTOP: a process starved or paused) 50 ms into a burst for
    longer than the localhost profile's 3 s lease: its participant drops out of bridge A's
    graph and comes back with the same writer, but without its node name, when it goes on.
    Robot A keeps the offer through the absence (VANISHED_GRACE: a withdrawn stream lost what
    the bridge had taken) and its bridge knows the returning writer's node (NAME_MEMORY_S),
    so the offer goes on. Withdrawn at once and not recognised, the listener got 1,214
    messages and then none: never offered again. (Whether DDS then delivers the rest is
    DDS's: on a quiet host all 20,000 arrived, on a loaded one the flow did not always
    resume; docs/ros2.md.)"""
    a = network.robots["robot_a"]
    with network.node("robot_b", "listener.py", "string", "/chatter", "90", "--keep-all") as sub:
        sub.until("READY", 20)
        with network.node("robot_a", "talker.py", "string", "/chatter", "20100", "20", "--keep-all",
                          "--burst-on-signal") as talker:
            collect(sub, 1, 60)  # the path is up: now the burst, and the freeze
            log_before = len(a.logs())
            talker.proc.send_signal(signal.SIGUSR1)
            time.sleep(0.05)
            talker.proc.send_signal(signal.SIGSTOP)
            try:
                deadline = time.monotonic() + 30
                while not re.search(r"/chatter \[std_msgs/msg/String\] has no named publisher|no longer offering "
                                    r"topic /chatter", a.logs()[log_before:]):
                    assert time.monotonic() < deadline, "the frozen talker never left robot A's graph"
                    time.sleep(0.1)
                left_at = time.monotonic()
            finally:
                talker.proc.send_signal(signal.SIGCONT)
            deadline = time.monotonic() + 20
            while "/chatter [std_msgs/msg/String] is back in the graph" not in a.logs()[log_before:]:
                if "no longer offering topic /chatter" in a.logs()[log_before:]:
                    withdrawn = time.monotonic() - left_at
                    _dds_never_told_bridge_a(network, withdrawn)
                    raise AssertionError(f"robot A withdrew the offer {withdrawn:.1f} s after the talker left its graph")
                assert time.monotonic() < deadline, "robot A never knew the talker again"
                time.sleep(0.1)


def _dds_never_told_bridge_a(network, withdrawn: float) -> None:
    """xfail, with the evidence, when the withdrawal is Fast DDS's and not the
    interceptor's: the offer was kept its whole grace (VANISHED_GRACE), and a fresh
    participant on robot A's domain sees the resumed talker while bridge A's did not.
    (Bridge A dropped the frozen talker at its lease's end; the talker, on resuming, still
    held bridge A as alive and never sent it its endpoints again: about one run in three
    under the full suite's load this session. The interceptor cannot see it through
    rclpy: docs/ros2.md.)"""
    from interceptor.ros2 import VANISHED_GRACE

    if withdrawn < VANISHED_GRACE - 0.5:
        return  # withdrawn before its grace: the interceptor's fault, a failure
    with network.node("robot_a", "publishers.py", "/chatter", "5") as probe:
        lines = probe.until("DONE", 20)
    if any(line.strip() == "PUB talker" for line in lines):
        pytest.xfail(f"Fast DDS: a fresh participant on robot A's domain sees the resumed talker, bridge A "
                     f"never did again; robot A kept the offer {withdrawn:.1f} s, its grace")


def test_a_subscriber_on_robot_b_killed_mid_stream_costs_the_others_no_message(network):
    """Two KEEP_ALL listeners on robot B, a burst of 12,000 messages; one listener is
    killed (SIGKILL: no goodbye in discovery) after the first 1,000. Bridge B's KEEP_ALL
    writer stays matched to the dead reader until its participant's lease ends, and fills
    up with samples nobody acknowledges; with Fast DDS's default 20 s lease the bridge gave
    up after PUBLISH_PATIENCE and the live listener lost thousands (measured: 14,140 of
    32,000 at 2,000 a second). The localhost profile's 3 s lease forgets the dead one first."""
    log_before = len(network.robots["robot_b"].logs())
    with network.node("robot_b", "listener.py", "string", "/chatter", "120", "--keep-all") as sub, \
            network.node("robot_b", "listener.py", "string", "/chatter", "120", "--keep-all",
                         "--node", "doomed") as doomed:
        sub.until("READY", 20)
        doomed.until("READY", 20)
        with network.node("robot_a", "talker.py", "string", "/chatter", "12100", "20", "--keep-all",
                          "--burst-on-signal") as talker:
            lines = collect(sub, 1, 60)  # the path is up: now the burst
            collect(doomed, 1, 60)
            talker.proc.send_signal(signal.SIGUSR1)
            lines += collect_through(sub, 1000, 60)
            doomed.proc.kill()
            try:
                lines += collect_through(sub, 12099, 30)
            except AssertionError as exc:
                raise AssertionError(f"robot B's live listener stopped after the other listener was killed: {exc}") from None
    seqs = got(lines)
    assert not [line for line in lines if line.startswith("BAD")]
    assert seqs == list(range(seqs[0], 12100)), f"{12100 - seqs[0] - len(seqs)} message(s) lost or reordered"
    assert "not taking messages" not in network.robots["robot_b"].logs()[log_before:]


def test_a_stuck_subscriber_on_robot_b_does_not_stall_robot_bs_other_topics(network):
    """A KEEP_ALL listener on robot B stops taking messages: its reader fills, then bridge
    B's publisher. The bridge waits for it (PUBLISH_PATIENCE, and again on a writer made
    anew), then drops that topic's messages (reported) and only probes it once a second,
    so the other topics arriving on robot B keep flowing instead of waiting behind every
    stuck message."""
    # The burst starts only once the path is up (the stuck listener took its first message):
    # a talker that bursts before bridge A's reader matched it has sent everything before
    # anyone listened (volatile: nothing is kept), and the test would wait for nothing.
    with network.node("robot_b", "listener.py", "string", "/stuck", "60", "--keep-all", "--stall-after", "1") as stuck, \
            network.node("robot_b", "listener.py", "twist", "/twist", "60") as flow:
        stuck.until("READY", 20)
        flow.until("READY", 20)
        with network.node("robot_a", "talker.py", "twist", "/twist", "100000", "20"):
            assert collect(flow, 10, 30), "/twist did not flow"
            with network.node("robot_a", "talker.py", "string", "/stuck", "100000", "20", "--keep-all",
                              "--burst-on-signal") as talker:
                stuck.until("STALLED", 30)
                talker.proc.send_signal(signal.SIGUSR1)
                # The burst fills the stuck reader (about a second at full rate, several on a
                # loaded host), then the bridge waits PUBLISH_PATIENCE, makes the writer anew,
                # waits PUBLISH_PATIENCE on the new one and then drops and says so. /twist
                # goes on meanwhile (delayed at most the patience, never behind every stuck
                # message: then it came at one message a patience): 12 s worth of it arrive
                # within a bounded wait, and 4 s worth more once /stuck is dropped. Counts
                # over a bounded wait, not rates: the burst shares robot A's message budget
                # with /twist, and a loaded host drains it slower.
                collect(flow, 12 * 20, 60)
                until(lambda: "not taking messages" in network.robots["robot_b"].logs(), 30,
                      "bridge B reporting the stuck subscriber")
                flow.until(None, 0.2)  # what /twist printed while the log was awaited
                collect(flow, 4 * 20, 30)  # the stuck topic's messages are now dropped at once


def test_a_peer_that_stops_reading_stalls_none_of_the_senders_other_flows(network):
    """ROS 2 audit: robot C (subscribed to robot A's images) stopped reading (its
    interceptor SIGSTOPped): robot A paused its bridge for every batch while C's stream
    was backed up, and robot B got 263 of robot A's 900 /chatter messages in 45 s, once
    nothing for 66 s. A stream that has not drained for STUCK_AFTER (10 s) is stuck: its
    messages are dropped, logged once, and it pauses nothing."""
    import os

    from tests.ros2_support import IMAGE

    grant = ("robot_c", "subscribe", "*", "/image", IMAGE)
    network.cli("grant", *grant)
    robot_a, robot_c = network.robots["robot_a"], network.robots["robot_c"]
    try:
        with network.node("robot_b", "listener.py", "string", "/chatter", "120") as chatter, \
                network.node("robot_c", "listener.py", "image", "/image", "120") as images:
            chatter.until("READY", 20)
            images.until("READY", 20)
            with network.node("robot_a", "talker.py", "string", "/chatter", "1000000", "20"), \
                    network.node("robot_a", "talker.py", "image", "/image", "1000000", "50"):
                collect(images, 5, 60)  # robot A's stream to robot C flows
                collect(chatter, 5, 30)
                os.kill(robot_c.proc.pid, signal.SIGSTOP)
                try:
                    until(lambda: "has not drained for" in robot_a.logs(), 40,
                          "robot A marking its stream to the stopped robot C stuck")
                    chatter.until(None, 0.2)  # what came while that was awaited
                    collect(chatter, 100, 15)  # 5 s of robot A's /chatter, C still stopped
                finally:
                    os.kill(robot_c.proc.pid, signal.SIGCONT)
    finally:
        network.cli("revoke", *grant)


def test_topic_not_granted_to_the_sender_never_leaves_robot_a(network):
    with network.node("robot_b", "listener.py", "string", "/secret", "30") as sub:
        sub.until("READY", 20)
        with network.node("robot_a", "talker.py", "string", "/secret", "100000", "20"):
            # robot A's bridge sees its talker (DDS discovery: seconds on a loaded machine)
            # and refuses the topic; from then on nothing is sent, and nothing came before
            deadline = time.monotonic() + 30
            while "/secret" not in network.robots["robot_a"].denials():
                assert time.monotonic() < deadline, network.robots["robot_a"].logs()[-2000:]
                time.sleep(0.1)
            lines = sub.until(None, 2)
    assert got(lines) == []
    assert "not_granted" in network.robots["robot_a"].denials()


def test_robot_whose_manager_may_not_subscribe_receives_nothing(network):
    with network.node("robot_c", "listener.py", "string", "/chatter", "8") as c_sub, \
            network.node("robot_b", "listener.py", "string", "/chatter", "8") as b_sub:
        c_sub.until("READY", 20)
        b_sub.until("READY", 20)
        with network.node("robot_a", "talker.py", "string", "/chatter", "100000", "20"):
            b_lines = collect(b_sub, 20, 20)
            c_lines = c_sub.until(None, 2)
    assert got(b_lines)
    assert got(c_lines) == []
    assert "robot_c may not subscribe /chatter" in network.robots["robot_a"].denials()


@pytest.mark.parametrize("kind", ["twist", "scan", "image"])
def test_message_types_arrive_intact_and_in_order(network, kind):
    topic = {"twist": "/twist", "scan": "/scan", "image": "/image"}[kind]
    with network.node("robot_b", "listener.py", kind, topic, "25") as sub:
        sub.until("READY", 20)
        with network.node("robot_a", "talker.py", kind, topic, "100000", "20"):
            lines = collect(sub, 30, 25)
    seqs = got(lines)
    assert not [line for line in lines if line.startswith("BAD")], "a message arrived altered"
    assert seqs == list(range(seqs[0], seqs[0] + 30)), "messages lost or reordered"


def test_service_call_across_robots(network):
    with network.node("robot_a", "server.py", "/set_flag", "flag_server") as server:
        server.until("READY", 20)
        with network.node("robot_b", "client.py", "/set_flag", "3", "25") as client:
            lines = client.until("RESULT True flag set to True by flag_server", 30)[-1:]
            lines += client.until("RESULT True flag set to False by flag_server", 10)[-1:]
        calls = server.until(None, 0.5)
    assert lines == ["RESULT True flag set to True by flag_server", "RESULT True flag set to False by flag_server"]
    assert "CALLED True" in calls or calls == []  # the server printed its calls (some may already be read)


def test_a_service_server_that_leaves_and_returns_twice_is_given_its_grace_both_times(network):
    """A server that leaves robot A's graph keeps its offer VANISHED_GRACE (a restart, or
    a process that missed its lease). On its return the offer forgot which granted node
    served it, so its second absence was withdrawn at once: ``no longer offering service
    /set_flag``, and robot B's proxy with its callers' calls went with it."""
    a = network.robots["robot_a"]
    left = "service /set_flag [std_srvs/srv/SetBool] has no named server in the graph"
    withdrawn = "no longer offering service /set_flag"
    said = re.compile(r"no longer offering service /set_flag|offering service /set_flag|"
                      r"service /set_flag \S+ is back|service /set_flag \S+ has no named server")

    def offered() -> bool:  # what robot A last said of /set_flag's offer (an earlier test's may stand)
        last = said.findall(a.logs())[-1:]
        return bool(last) and (last[0].startswith("offering") or last[0].endswith("is back"))

    for leaving in (1, 2):
        with network.node("robot_a", "server.py", "/set_flag", "flag_server") as server:
            server.until("READY", 20)
            until(offered, 20, "robot A offering /set_flag")
            mark = len(a.logs())
        seen = until(lambda start=mark: next((n for n in (withdrawn, left) if n in a.logs()[start:]), None), 20,
                     f"server gone from robot A's graph ({leaving})")
        assert seen == left, f"absence {leaving}: withdrawn without its grace:\n{a.logs()[mark:]}"


def test_a_peer_offering_a_service_this_robot_serves_itself_is_refused(network):
    """ROS 2 audit: a peer's service was proxied on robot A's domain while a local server
    served the same name: two servers, and a caller took whichever answered first."""
    grants = [("robot_c", "serve", "/flag_server", "/set_flag", SET_BOOL), ("robot_a", "call", "*", "/set_flag", SET_BOOL)]
    for grant in grants:
        network.cli("grant", *grant)
    a = network.robots["robot_a"]
    mark, logged = len(a.denials()), len(a.logs())
    target = StreamTarget(kind="service", name="/set_flag", type=SET_BOOL, node="/flag_server").encode()
    try:
        with network.node("robot_a", "server.py", "/set_flag", "flag_server") as server:
            server.until("READY", 20)
            until(lambda: re.search(r"offering service /set_flag|/set_flag \S+ is back", a.logs()[logged:]), 20,
                  "robot A offering its own /set_flag server (its graph has it)")
            with _rogue(network, "robot_a", "robot_c") as s:
                reply = rogue_preamble(s, network.daemon.token("robot_c")[1]["access_token"], "ros2", target)
                if reply is not None and reply.ok:
                    s.settimeout(10)
                    with contextlib.suppress(ConnectionError, ssl.SSLError):
                        assert s.recv(100) == b""
    finally:
        for grant in grants:
            network.cli("revoke", *grant[:4])
    assert "/set_flag has a server on this robot's domain" in network.robots["robot_a"].denials()[mark:]


def test_a_remote_service_that_never_answers_holds_none_of_the_others(network):
    """ROS 2 audit: calls to a remote server that never answers held all of bridge B's
    service threads (8), and robot A's /set_flag waited 30 s behind them. Each remote
    service now holds at most MAX_CALLS_PER_SERVICE of them; its further calls get no
    answer at once."""
    service_threads = 16  # cryptoros/ros2/bridge_node.py SERVICE_THREADS (a module of the ROS 2 venv)
    grants = [("robot_a", "serve", "/hang_server", "/hang", SET_BOOL), ("robot_b", "call", "*", "/hang", SET_BOOL)]
    for grant in grants:
        network.cli("grant", *grant)
    try:
        with network.node("robot_a", "server.py", "/hang", "hang_server", "--hang") as hang, \
                network.node("robot_a", "server.py", "/set_flag", "flag_server") as flag:
            hang.until("READY", 20)
            flag.until("READY", 20)
            # more calls to /hang at once than bridge B has threads
            with network.node("robot_b", "client.py", "/hang", str(service_threads + 2), "60", "--at-once") as stuck:
                stuck.until("SENT", 40)
                hang.until("HELD True", 30)  # they reached the server, which holds them
                with network.node("robot_b", "client.py", "/set_flag", "1", "20") as client:
                    client.until("RESULT True flag set to True by flag_server", 25)
    finally:
        for grant in grants:
            network.cli("revoke", *grant)


def test_an_insiders_services_that_never_answer_hold_none_of_another_robots(network):
    """ROS 2 re-audit: an insider (robot C) serving four services robot B may call, none
    of them ever answering, held all 16 of bridge B's service threads with 4 calls each;
    robot A's /set_flag then waited 28 s. One peer's services now hold at most
    MAX_CALLS_PER_PEER (8) threads together; its further calls get no answer at once."""
    names = [f"/hog{i}" for i in range(4)]
    with _services_for_b(network, "robot_c", "/hog_server", names):
        status, body = network.daemon.token("robot_c")
        with contextlib.ExitStack() as held, \
                network.node("robot_a", "server.py", "/set_flag", "flag_server") as flag:
            for name in names:  # robot C offers each, reads its requests and never answers
                s = held.enter_context(_rogue(network, "robot_b", "robot_c"))
                target = StreamTarget(kind="service", name=name, type=SET_BOOL, node="/hog_server").encode()
                reply = rogue_preamble(s, body["access_token"], "ros2", target)
                assert reply is not None and reply.ok, reply
            flag.until("READY", 20)
            hogs = [held.enter_context(network.node("robot_b", "client.py", name, "5", "60", "--at-once"))
                    for name in names]
            for hog in hogs:
                hog.until("SENT", 40)
            with network.node("robot_b", "client.py", "/set_flag", "1", "20") as client:
                client.until("RESULT True flag set to True by flag_server", 25)


def test_latched_message_reaches_a_late_subscriber_with_transient_local(network):
    log_before = len(network.robots["robot_b"].logs())
    with network.node("robot_a", "talker.py", "string", "/latched", "1", "10", "--latched"):
        # robot A's interceptor finds the topic and opens its stream to B, which republishes it
        deadline = time.monotonic() + 20
        while "republishing /latched" not in network.robots["robot_b"].logs()[log_before:]:
            assert time.monotonic() < deadline, network.robots["robot_b"].logs()[log_before:][-2000:]
            time.sleep(0.1)
        with network.node("robot_b", "listener.py", "string", "/latched", "10", "--latched") as sub:
            lines = sub.until("GOT 0", 12)
    assert got(lines) == [0]


def test_two_robots_bridging_the_same_topic_do_not_loop(network):
    with network.node("robot_a", "listener.py", "string", "/both", "30", "--node", "watcher") as a_sub:
        a_sub.until("READY", 20)
        with network.node("robot_a", "talker.py", "string", "/both", "100000", "20"), \
                network.node("robot_b", "talker.py", "string", "/both", "100000", "20", "--node", "talker_b",
                             "--offset", "1000000"):
            deadline = time.monotonic() + 25
            lines: list[str] = []
            while time.monotonic() < deadline:
                lines += a_sub.until(None, 1)
                seqs = got(lines)
                if sum(s >= 1000000 for s in seqs) >= 30:
                    break
            lines += a_sub.until(None, 2)
    seqs = got(lines)
    remote = [s for s in seqs if s >= 1000000]
    local = [s for s in seqs if s < 1000000]
    assert len(remote) >= 30, "robot B's messages did not reach robot A"
    assert local, "robot A's own talker was not heard"
    duplicates = sorted({s for s in seqs if seqs.count(s) > 1})
    assert duplicates == [], f"messages came back around the loop: {duplicates[:10]}"


# ------------------------------------------------------------------ tokens and bad input
def _rogue(network, host, as_name):
    h = network.robots[host]
    return rogue_tls(h.address, h.public_port, ca=network.pki.ca_cert, cert=network.pki.pki.cert_path_for(as_name),
                     key=network.pki.pki.key_path_for(as_name))


CHATTER = StreamTarget(kind="topic", name="/chatter", type="std_msgs/msg/String", node="/talker").encode()


def test_forged_expired_foreign_and_revoked_tokens_are_refused(network):
    key, kid = signing_key(network)
    now = int(time.time())
    a_der = ssl.PEM_cert_to_DER_cert(network.pki.pki.cert_path_for("robot_a").read_text())

    def claims(**kw):
        c = build_claims(issuer="cryptoros-authz", audience="cryptoros", subject="robot_a",
                         grants=Grants.from_claim({"/talker": {"publish": [["/chatter", "std_msgs/msg/String"]]}}),
                         cert_der=a_der, now=now, lifetime=300)
        c.update(kw)
        return c

    forged = sign_token(claims(), rsa.generate_private_key(public_exponent=65537, key_size=2048), kid)
    expired = sign_token(claims(iat=now - 900, nbf=now - 900, exp=now - 600), key, kid)
    status, body = network.daemon.token("robot_c")
    foreign = body["access_token"]  # genuine, but bound to robot C's certificate
    status, body = network.daemon.token("robot_a")
    assert status == 200
    revoked = body["access_token"]
    jti = jwt.decode(revoked, options={"verify_signature": False})["jti"]
    ok_result = network.cli("revoke-token", jti)
    assert ok_result.returncode == 0, ok_result.stderr
    time.sleep(1.5)  # two polls of the revocation feed
    for token in (forged, expired, foreign, revoked):
        with _rogue(network, "robot_b", "robot_a") as s:
            reply = rogue_preamble(s, token, "ros2", CHATTER)
        assert reply is None or reply.ok is False, token[:30]
    log = network.robots["robot_b"].denials()
    for reason in ("bad_signature", "expired", "cnf_mismatch", "revoked"):
        assert reason in log, reason


def test_malformed_targets_and_frames_are_refused_and_the_interceptor_keeps_serving(network):
    # ROS 2's own /rosout is never carried, whatever a grant says (robot A granted it here)
    rosout = ("robot_a", "publish", "/talker", "/rosout", "rcl_interfaces/msg/Log")
    network.cli("grant", *rosout)
    try:
        token = network.daemon.token("robot_a")[1]["access_token"]
        for target in ("", "{", '{"kind":"topic"}', '{"kind":"topic","name":"chatter","type":"x","node":"/t"}',
                       CHATTER.replace("/talker", "/intruder"),
                       CHATTER.replace("/chatter", "/rosout").replace("std_msgs/msg/String", "rcl_interfaces/msg/Log")):
            with _rogue(network, "robot_b", "robot_a") as s:
                reply = rogue_preamble(s, token, "ros2", target)
                if reply is not None and reply.ok:  # the target parsed: the grant check closes the stream
                    s.settimeout(5)
                    assert s.recv(100) == b""
                else:
                    assert reply is None or reply.ok is False
    finally:
        network.cli("revoke", *rosout[:4])  # which revokes the token that held it
    with _rogue(network, "robot_b", "robot_a") as s:  # a frame declaring 4 GB
        reply = rogue_preamble(s, network.daemon.token("robot_a")[1]["access_token"], "ros2", CHATTER)
        assert reply.ok
        s.sendall(struct.pack("<IBI", 0xFFFFFFF0, 16, 0) + b"x" * 100)
        s.settimeout(5)
        with contextlib.suppress(ConnectionError, ssl.SSLError):
            assert s.recv(100) == b""
    log = network.robots["robot_b"].denials()
    assert "bad_target" in log or "ros2 target" in log
    assert "/intruder may not publish /chatter" in log
    assert "/rosout [rcl_interfaces/msg/Log] stays on each robot" in log, log
    assert "outside 0.." in log
    test_talker_on_a_reaches_listener_on_b_through_the_interceptors(network)  # still serving


def test_the_unfinished_frames_of_one_peer_are_bounded(network):
    """ROS 2 audit: an insider announced 16 MiB frames on 80 streams and sent all but the
    last byte of each: robot B held 1.4 GB, and nothing ended it. Robot B now holds at
    most PARTIAL_FRAMES_PER_PEER x max_message_size of one peer's unfinished frames: the
    stream over it is cut (``partial_frames``), and robot B goes on serving."""
    from cryptoros.ros2 import framing as fr
    from interceptor.ros2_partial import PARTIAL_FRAMES_PER_PEER

    _leave_frames_unfinished(network, [CHATTER] * (PARTIAL_FRAMES_PER_PEER + 1), fr.DATA)
    test_talker_on_a_reaches_listener_on_b_through_the_interceptors(network)  # still serving


def _leave_frames_unfinished(network, targets: list[str], kind: int) -> None:
    """As robot A, one stream to robot B per target, each announcing a 16 MiB frame of
    ``kind`` (the default max_message_size) and sending all of it but its last byte, until
    robot B cuts one (``partial_frames``)."""
    from cryptoros.ros2 import framing as fr

    status, body = network.daemon.token("robot_a")
    size = 16 << 20
    chunk = b"\x00" * (1 << 20)
    with contextlib.ExitStack() as held:
        for target in targets:
            s = held.enter_context(_rogue(network, "robot_b", "robot_a"))
            reply = rogue_preamble(s, body["access_token"], "ros2", target)
            assert reply is not None and reply.ok, reply
            try:
                s.sendall(fr.HEAD.pack(5 + size, kind, 0 if kind == fr.DATA else 1))
                for k in range(16):
                    s.sendall(chunk[:-1] if k == 15 else chunk)
            except OSError:  # cut while it sent: the stream over the limit
                break
        until(lambda: "partial_frames" in network.robots["robot_b"].denials(), 30,
              "robot B cutting the stream whose unfinished frame is over the limit")


def _b_may_call(network, names: list[str]) -> bool:
    """Whether robot B's own token (its /status) grants calls to every one of ``names``."""
    with urllib.request.urlopen(f"http://127.0.0.1:{network.robots['robot_b'].metrics_port}/status",
                                timeout=5) as reply:
        token = json.load(reply)["token"]  # None while robot B fetches its next one (a grant changed)
    return token is not None and set(names) <= {g[2] for g in token["grants"] if g[1] == "call"}


@contextlib.contextmanager
def _services_for_b(network, manager: str, server: str, names: list[str]):
    """``manager``'s node ``server`` granted to serve ``names`` and robot B to call them,
    once robot B's own token carries the calls; the grants revoked after."""
    grants = [g for name in names for g in ((manager, "serve", server, name, SET_BOOL),
                                            ("robot_b", "call", "*", name, SET_BOOL))]
    for grant in grants:
        network.cli("grant", *grant)
    try:
        until(lambda: _b_may_call(network, names), 30, "robot B's token granting the calls")
        yield
    finally:
        for grant in grants:
            network.cli("revoke", *grant)


def test_a_malformed_answer_from_a_remote_server_costs_only_its_own_call(network):
    """ROS 2 audit: an insider serving a service robot B may call answered one call with
    an empty response; bridge B's thread serving every remote service died on it, and
    robot A's /set_flag went unanswered from then on (``cryptoros status`` said ok). The
    malformed answer is now no answer: robot B's interceptor checks it against the
    service's response type before the bridge sees it, and ends that stream with a DENY
    naming the peer; the other services go on."""
    from cryptoros.ros2 import framing as fr

    with _services_for_b(network, "robot_a", "/bad_server", ["/bad_answer"]):
        status, body = network.daemon.token("robot_a")
        with _rogue(network, "robot_b", "robot_a") as s, \
                network.node("robot_a", "server.py", "/set_flag", "flag_server") as server:
            target = StreamTarget(kind="service", name="/bad_answer", type=SET_BOOL, node="/bad_server").encode()
            reply = rogue_preamble(s, body["access_token"], "ros2", target)
            assert reply is not None and reply.ok, reply
            server.until("READY", 20)
            with network.node("robot_b", "client.py", "/bad_answer", "1", "20") as bad:
                s.settimeout(30)
                head = b""
                while len(head) < fr.HEAD.size:  # robot B's request: answered with no CDR at all
                    chunk = s.recv(fr.HEAD.size - len(head))
                    assert chunk, "robot B closed the service stream before a request came"
                    head += chunk
                _length, kind, rid = fr.HEAD.unpack(head)
                assert kind == fr.SRV_REQUEST
                s.sendall(fr.encode(fr.SRV_RESPONSE, rid, b"\x01"))
                assert not [line for line in bad.until(None, 8) if line.startswith("RESULT")]
            with network.node("robot_b", "client.py", "/set_flag", "2", "30") as client:
                client.until("RESULT True flag set to True by flag_server", 35)
                client.until("RESULT True flag set to False by flag_server", 10)
        until(lambda: any("DENY ros2 from robot_a@" in line and "no encapsulation header" in line
                          for line in network.robots["robot_b"].logs().splitlines()), 10,
              "robot B logging the malformed answer, naming robot A")


def test_the_unfinished_frames_of_a_peers_service_streams_count_against_its_budget(network):
    """Re-audit: the budget of unfinished frames counted topic streams only; a peer
    serving several services could leave one frame of up to max_message_size unfinished on
    each, without limit. Service streams now count against the same budget."""
    from cryptoros.ros2 import framing as fr
    from interceptor.ros2_partial import PARTIAL_FRAMES_PER_PEER

    names = [f"/unfinished{i}" for i in range(PARTIAL_FRAMES_PER_PEER + 1)]
    with _services_for_b(network, "robot_a", "/part_server", names):
        _leave_frames_unfinished(network, [StreamTarget(kind="service", name=name, type=SET_BOOL,
                                                        node="/part_server").encode() for name in names],
                                 fr.SRV_RESPONSE)
    test_talker_on_a_reaches_listener_on_b_through_the_interceptors(network)  # still serving


# ------------------------------------------------------------------ confidentiality, metrics


def test_capture_between_interceptors_holds_no_published_string(network, tmp_path):
    hosts = " or ".join(f"host {r.address}" for r in network.robots.values())
    capture = Capture(tmp_path / "ros2.pcap", f"tcp and ({hosts})", prove_loopback=True,
                      marker_host=network.robots["robot_a"].address)  # live before the talker starts
    with network.node("robot_b", "listener.py", "string", "/chatter", "20") as sub:
        sub.until("READY", 20)
        with network.node("robot_a", "talker.py", "string", "/chatter", "100000", "50"):
            collect(sub, 50, 20)
    data = capture.stop()
    assert len(data) > 5000, "the capture saw no traffic between the interceptors"
    assert b"secret-" not in data and b"/chatter" not in data and b"std_msgs" not in data


def test_metrics_count_streams_bytes_allows_and_denials(network):
    a, b = network.metrics("robot_a"), network.metrics("robot_b")
    assert 'cryptoros_interceptor_connections_total{direction="out",purpose="ros2"}' in a
    assert 'cryptoros_interceptor_connections_total{direction="in",purpose="ros2"}' in b
    assert 'cryptoros_interceptor_allowed_total{kind="ros2_topic"}' in b
    assert 'cryptoros_interceptor_denied_total{kind="ros2_publish",reason="not_granted"}' in a
    assert 'cryptoros_interceptor_bytes_total{direction="rx"}' in b
    tx = [line for line in a.splitlines() if line.startswith('cryptoros_interceptor_bytes_total{direction="tx"}')]
    assert tx and float(tx[0].split()[-1]) > 10000


# ------------------------------------------------------------------ only through the interceptors; revocation


def test_with_the_interceptors_stopped_nothing_arrives(network):
    network.stop("robot_a")
    network.stop("robot_b")
    try:
        with network.node("robot_b", "listener.py", "string", "/chatter", "6") as sub:
            sub.until("READY", 20)
            with network.node("robot_a", "talker.py", "string", "/chatter", "100000", "20"):
                lines = sub.until(None, 5)
        assert got(lines) == []
    finally:
        network.start("robot_a")
        network.start("robot_b")


def test_sighup_keeps_streams_withdraws_a_topic_made_local_and_cuts_a_disabled_manager_within_5s(network):
    robot_a = network.robots["robot_a"]
    with network.node("robot_b", "listener.py", "string", "/chatter", "60") as sub:
        sub.until("READY", 20)
        with network.node("robot_a", "talker.py", "string", "/chatter", "100000", "50"):
            collect(sub, 20, 25)
            for name in ("robot_a", "robot_b"):
                network.robots[name].proc.send_signal(signal.SIGHUP)
            assert len(got(sub.until(None, 2.0))) >= 50, "the stream stalled across SIGHUP"
            assert "reloaded" in robot_a.logs()
            # [ros2] local on SIGHUP withdraws /chatter, and the log says why (it said
            # "its publisher, its server or the grant that carried it is gone", both there)
            config, seen = robot_a.config.read_text(), len(robot_a.logs())
            robot_a.config.write_text(config + 'local = ["/chatter"]\n')  # the file ends in [ros2]
            try:
                robot_a.proc.send_signal(signal.SIGHUP)
                withdrawn = until(lambda: [line for line in robot_a.logs()[seen:].splitlines()
                                           if "no longer offering topic /chatter" in line], 10,
                                  "robot A withdrawing /chatter")[0]
                assert withdrawn.endswith("its name is local to this robot ([ros2] local)"), withdrawn
            finally:
                robot_a.config.write_text(config)
                robot_a.proc.send_signal(signal.SIGHUP)
            collect(sub, 5, 20)  # offered again once /chatter is not local
            result = network.cli("disable-manager", "robot_a")
            assert result.returncode == 0, result.stderr
            try:
                sub.until(None, 5.0)  # whatever still arrives within 5 s
                after = got(sub.until(None, 3.0))
                assert after == [], f"robot B still receives {len(after)} messages 5 s after robot A was disabled"
            finally:
                network.cli("enable-manager", "robot_a")
    assert re.search(r'^cryptoros_interceptor_revocation_cutoffs_total\{reason="(subject_disabled|revoked)"\} [1-9]',
                     network.metrics("robot_b"), re.M), "the cut is not counted with its reason"


def test_a_disabled_robots_refusals_of_a_peers_retries_are_one_line_and_its_flow_resumes_when_enabled(network):
    """Robot B disabled while robot A's talker streams to it: robot A retries its stream
    and robot B, holding no token, refuses each. A day-2 audit saw a line per connection
    (11 in 8 s: its source port in the key); a verified peer's refusals are grouped by
    its manager and address. Enabled again, the flow resumes."""
    robot_b = network.robots["robot_b"]
    with network.node("robot_b", "listener.py", "string", "/chatter", "60") as sub:
        sub.until("READY", 20)
        with network.node("robot_a", "talker.py", "string", "/chatter", "100000", "50"):
            collect(sub, 10, 25)
            seen_b = len(robot_b.logs())
            assert network.cli("disable-manager", "robot_b").returncode == 0
            try:
                deadline = time.monotonic() + 20
                while "DENY stream from robot_a@" not in robot_b.logs()[seen_b:]:  # robot B refuses
                    assert time.monotonic() < deadline, robot_b.logs()[seen_b:][-3000:]
                    time.sleep(0.2)
                sub.until(None, 6.0)  # robot A retries meanwhile
                refused = [line for line in robot_b.logs()[seen_b:].splitlines()
                           if "DENY stream from robot_a@" in line and "no_token" in line]
            finally:
                assert network.cli("enable-manager", "robot_b").returncode == 0
            assert len(refused) == 1, refused
            start = time.monotonic()
            collect(sub, 5, 30)
            print(f"a disabled robot enabled again: its flow back after {time.monotonic() - start:.1f} s")


def test_a_reload_that_gets_no_token_for_the_new_certificate_keeps_the_old_one_everywhere(network):
    """Day 2: the operator renews robot A's certificate files but forgets ``set-cert``
    and sends SIGHUP. The authorization server refuses the new certificate, so the
    reload fails as a whole: robot A keeps presenting the old certificate with a token
    bound to it, and its new streams to robot B flow (before, the listener and TLS
    contexts were swapped first and every new stream was refused, cnf_mismatch)."""
    address = network.robots["robot_a"].address
    network.pki.issue("robot_a", kind="interceptor", sans=(f"IP:{address}",), force=True)  # not in the registry
    log_before, b_before = len(network.robots["robot_a"].logs()), len(network.robots["robot_b"].logs())
    network.robots["robot_a"].proc.send_signal(signal.SIGHUP)
    deadline = time.monotonic() + 20
    while "reload failed, keeping the old state" not in network.robots["robot_a"].logs()[log_before:]:
        assert time.monotonic() < deadline, network.robots["robot_a"].logs()[log_before:][-2000:]
        time.sleep(0.1)
    assert "reloaded certificates" not in network.robots["robot_a"].logs()[log_before:]
    with network.node("robot_b", "listener.py", "scan", "/scan", "40") as sub:
        sub.until("READY", 20)
        with network.node("robot_a", "talker.py", "scan", "/scan", "100000", "20"):
            assert got(collect(sub, 10, 30)), "robot A's new streams were refused after a failed reload"
    assert "cnf_mismatch" not in network.robots["robot_b"].logs()[b_before:]


def test_a_renewed_certificate_is_used_everywhere_after_sighup(network):
    """Day 2: robot A's certificate is renewed (new key), the registry bound to it
    (``set-cert``: tokens of the old one revoked), the old one revoked with the CA and
    robot A reloaded. Every holder of
    the certificate reads the new one: the authorization server sees it (a token is
    issued), the token is bound to it, and robot B accepts robot A's new streams."""
    import json
    import urllib.error
    import urllib.request

    def healthy() -> bool:  # robot A's own authority holds (the earlier test disabled and re-enabled it)
        url = f"http://127.0.0.1:{network.robots['robot_a'].metrics_port}/healthz"
        try:
            with urllib.request.urlopen(url, timeout=5) as r:
                return json.loads(r.read())["status"] == "ok"
        except urllib.error.HTTPError:
            return False

    deadline = time.monotonic() + 20
    while not healthy():
        assert time.monotonic() < deadline, "robot A's /healthz did not turn ok"
        time.sleep(0.1)
    address = network.robots["robot_a"].address
    old_serial = int(_get_json(network, "robot_a", "/status")["certificate"]["serial"], 16)  # the one in use
    renewed = network.pki.issue("robot_a", kind="interceptor", sans=(f"IP:{address}",), force=True)
    result = network.cli("set-cert", "robot_a", "--fingerprint", renewed.fingerprint_sha256)
    assert result.returncode == 0, result.stderr
    # the old certificate revoked, as the runbook does: robot A, still on it, says so
    # once; the reload that installs the new one did too (ROS 2 audit), the old serial
    # checked against the feed the reload reads
    network.pki.revoke(old_serial)
    until(lambda: f"our own certificate (serial {old_serial:x}) was revoked" in network.robots["robot_a"].logs(),
          20, "robot A reporting its old certificate revoked")
    log_before = len(network.robots["robot_a"].logs())
    network.robots["robot_a"].proc.send_signal(signal.SIGHUP)
    deadline = time.monotonic() + 20
    while "reloaded certificates" not in network.robots["robot_a"].logs()[log_before:]:
        assert time.monotonic() < deadline, network.robots["robot_a"].logs()[log_before:][-2000:]
        time.sleep(0.1)
    with network.node("robot_b", "listener.py", "scan", "/scan", "40") as sub:
        sub.until("READY", 20)
        with network.node("robot_a", "talker.py", "scan", "/scan", "100000", "20"):
            assert got(collect(sub, 10, 30)), "robot B received nothing from robot A's renewed certificate"
    tail = network.robots["robot_a"].logs()[log_before:]
    assert "access token installed" in tail, tail[-2000:]  # the authorization server took the new certificate
    assert " ERROR " not in tail, tail[-2000:]


def test_a_best_effort_publisher_beside_a_reliable_one_leaves_reliable_subscribers_served(network):
    """ROS 2 audit: a second granted publisher of /chatter with best-effort QoS made robot
    B republish best effort, which no reliable subscriber matches: B's reliable listener
    got nothing for as long as it ran (7 s, 150 messages). Robot B's writer is reliable
    whatever the offer says: the listener gets both talkers' messages."""
    with network.node("robot_b", "listener.py", "string", "/chatter", "60") as sub:
        sub.until("READY", 20)
        with network.node("robot_a", "talker.py", "string", "/chatter", "100000", "20"):
            collect(sub, 5, 25)  # the reliable flow is up
            with network.node("robot_a", "talker.py", "string", "/chatter", "200", "20", "--best-effort",
                              "--offset", "500000"):
                lines = collect(sub, 120, 40)
    seqs = got(lines)
    best_effort = [s for s in seqs if s >= 500_000]
    assert len(best_effort) >= 20 and len(seqs) - len(best_effort) >= 20, (len(best_effort), len(seqs), lines[-5:])
