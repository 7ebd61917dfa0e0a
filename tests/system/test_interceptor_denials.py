"""What the interceptors refuse, each with the node that should keep running still running.

Real rosmaster, real rospy nodes, real interceptors and authz daemon (see
tests/interceptor_harness.py). A "rogue" is a process speaking to an interceptor's
public port by hand with some certificate and some token: a compromised robot or a
stranger on the network.
"""

from __future__ import annotations

import ssl
import time
import xmlrpc.client

import pytest

from cryptoros.ros1.xmlrpc import Response
from cryptoros.tls import cert_thumbprint_s256
from cryptoros.grants import Grants
from cryptoros.tokens import build_claims, sign_token
from tests.interceptor_harness import (
    NODE,
    separate_hosts,
    SYS_PY,
    robot_network,
    rogue_preamble,
    rogue_tcpros,
    rogue_tls,
    rogue_xmlrpc,
    signing_key,
)
from tests.support import running, until
from tests.interceptor_harness import denials, token_of, got, master_state, nodes_in_state, read_lines, wait_registered

pytestmark = [pytest.mark.ros1]


@pytest.fixture(scope="module")
def network(tmp_path_factory):
    with robot_network(tmp_path_factory.mktemp("net"), start=("master", "robot_a", "robot_b", "robot_c"),
                       netns=separate_hosts()) as net:
        yield net


def cert(network, name):
    return network.pki.pki.cert_path_for(name), network.pki.pki.key_path_for(name)


def public(network, host):
    h = network.hosts[host]
    return h.address, h.public_port


def rogue(network, host, as_name, *, pki=None):
    c, k = (pki or network.pki).pki.cert_path_for(as_name), (pki or network.pki).pki.key_path_for(as_name)
    return rogue_tls(*public(network, host), ca=network.pki.ca_cert, cert=c, key=k)


def talker(network, count=100000, hz=20, node="/talker_a", topic="/chatter"):
    return running([SYS_PY, NODE, "pub", node, topic, str(count), str(hz), "30"], env=network.ros_env("robot_a"))


def test_manager_without_grant_cannot_register_its_publisher(network):
    with running([SYS_PY, NODE, "pub", "/talker_c", "/chatter", "100000", "20", "30"], env=network.ros_env("robot_c")) as pub:
        read_lines(pub, "READY", 20)
        with running([SYS_PY, NODE, "sub", "/listener_b", "/chatter", "30"], env=network.ros_env("robot_b")) as sub:
            read_lines(sub, "READY", 20)
            time.sleep(3)
            assert got(read_lines(sub, None, 0.5)) == []
        publishers = dict(master_state(network)[0])
        assert "/talker_c" not in publishers.get("/chatter", [])
        assert pub.poll() is None, "the refused node should keep running"
    assert "not_granted" in denials(network, "robot_c")


def test_subscriber_without_grant_receives_nothing(network):
    with talker(network, topic="/secret") as pub:
        read_lines(pub, "READY", 20)
        with running([SYS_PY, NODE, "sub", "/listener_b", "/secret", "30"], env=network.ros_env("robot_b")) as sub:
            read_lines(sub, "READY", 20)
            time.sleep(3)
            assert got(read_lines(sub, None, 0.5)) == []
            assert sub.poll() is None
        assert pub.poll() is None
    assert "may not subscribe /secret" in denials(network, "robot_b")


def test_header_with_wrong_type_or_md5_is_refused_by_the_publishers_interceptor(network):
    """A compromised robot B (valid certificate and token) skips its own interceptor's
    checks and speaks to robot A's interceptor by hand."""
    token = token_of(network, "robot_b")
    with talker(network) as pub:
        read_lines(pub, "READY", 20)
        wait_registered(network, "/talker_a")
        with rogue(network, "master", "robot_b") as s:
            assert rogue_preamble(s, token, "master").ok
            reply = rogue_xmlrpc(s, "lookupNode", "/rogue", "/talker_a")
        code, _, node_api = reply.value
        assert code == 1 and node_api.startswith(f"cryptoros://{network.hosts['robot_a'].address}:")
        x_id = node_api.rsplit("/", 1)[1]
        with rogue(network, "robot_a", "robot_b") as s:
            assert rogue_preamble(s, token, "node", x_id).ok
            reply = rogue_xmlrpc(s, "requestTopic", "/listener_b", "/chatter", [["TCPROS"]])
        code, _, (_, t_host, _) = reply.value
        assert code == 1
        t_id = t_host.rsplit("/", 1)[1]
        base = {"callerid": "/listener_b", "topic": "/chatter", "type": "std_msgs/String",
                "md5sum": "992ce8a1687cec8c8bd883ec73ca41d1", "tcp_nodelay": "1"}
        # a peer's value is quoted in the refusal: its newline wrote a line of the insider's choosing
        forged = "2026-11-29 05:30:00,000 cryptoros.interceptor INFO ALLOW topic from robot_c: FORGED"
        for bad in ({"type": "std_msgs/Int32"}, {"md5sum": "0" * 32}, {"topic": "/secret"},
                    {"topic": f"/nope\n{forged}"}, {"topic": "/nope\r\x00" + "x" * 20000}):
            with rogue(network, "robot_a", "robot_b") as s:
                assert rogue_preamble(s, token, "topic", t_id).ok
                answer = rogue_tcpros(s, {**base, **bad})
            assert "error" in answer and "md5sum" not in answer, (bad, answer)
        with rogue(network, "robot_a", "robot_b") as s:  # the genuine header works
            assert rogue_preamble(s, token, "topic", t_id).ok
            answer = rogue_tcpros(s, base)
            assert answer.get("md5sum") == base["md5sum"] and answer.get("callerid") == "/talker_a"
        assert pub.poll() is None
    log = denials(network, "robot_a")
    assert "type_mismatch" in log or "published as" in log
    assert "md5sum" in log
    lines = network.hosts["robot_a"].logs().splitlines()
    assert not [line for line in lines if line.startswith(forged) or "\x00" in line], "a peer's value wrote raw"
    assert "/nope\\n2026-11-29" in log and "/nope\\r\\x00xxx" in log, log[-3000:]
    assert max(len(line) for line in lines) < 5000  # a peer's 20,000 characters cut


def test_shutdown_is_dropped_for_the_master_and_for_nodes(network):
    token = token_of(network, "robot_b")
    with talker(network) as pub:
        read_lines(pub, "READY", 20)
        wait_registered(network, "/talker_a")
        # to the master, through the master's interceptor
        with rogue(network, "master", "robot_b") as s:
            assert rogue_preamble(s, token, "master").ok
            reply = rogue_xmlrpc(s, "shutdown", "/evil", "bye")
        assert isinstance(reply, Response) and reply.value[0] == -1
        # to the master, from a local process through its host's interceptor
        with network.inside("robot_b"):
            local_master = xmlrpc.client.ServerProxy(network.hosts["robot_b"].master_uri)
            assert local_master.shutdown("/evil", "bye")[0] == -1
            # to a node, through the relay a local process on B is handed
            code, _, relay = local_master.lookupNode("/evil", "/talker_a")
            assert code == 1 and relay.startswith("http://127.0.0.1:")
            assert xmlrpc.client.ServerProxy(relay).shutdown("/evil", "bye")[0] == -1
        # ... and by hand, straight to A's interceptor with B's valid token
        node_api = rogue_lookup(network, token, "/talker_a")
        with rogue(network, "robot_a", "robot_b") as s:
            assert rogue_preamble(s, token, "node", node_api.rsplit("/", 1)[1]).ok
            assert rogue_xmlrpc(s, "shutdown", "/master", "bye").value[0] == -1
            s.close()
        time.sleep(1)
        assert pub.poll() is None, "the talker was shut down"
        assert "/talker_a" in nodes_in_state(master_state(network))
    with network.inside("master"):
        assert xmlrpc.client.ServerProxy(network.rosmaster_uri).getPid("/t")[0] == 1  # rosmaster alive
    assert denials(network, "robot_a").count("shutdown_dropped") >= 1


def rogue_lookup(network, token, node):
    with rogue(network, "master", "robot_b") as s:
        assert rogue_preamble(s, token, "master").ok
        return rogue_xmlrpc(s, "lookupNode", "/rogue", node).value[2]


def test_publisher_update_accepted_only_from_the_masters_interceptor(network):
    token = token_of(network, "robot_b")
    with running([SYS_PY, NODE, "sub", "/listener_b", "/chatter", "30"], env=network.ros_env("robot_b")) as sub:
        read_lines(sub, "READY", 20)
        wait_registered(network, "/listener_b")
        node_api = rogue_lookup(network, token, "/listener_b")
        with rogue(network, "robot_b", "robot_a") as s:  # robot A is not the master
            assert rogue_preamble(s, token_of(network, "robot_a"), "node", node_api.rsplit("/", 1)[1]).ok
            reply = rogue_xmlrpc(s, "publisherUpdate", "/master", "/chatter", ["cryptoros://127.0.0.2:1/x/1"])
        assert reply.value[0] == -1
    assert "not_from_master" in denials(network, "robot_b")


def test_existing_node_name_from_another_manager_is_refused(network):
    with talker(network) as pub:
        read_lines(pub, "READY", 20)
        wait_registered(network, "/talker_a")
        # robot B's wildcard subscribe grant would let any of its nodes subscribe, but
        # /talker_a belongs to robot A: registering that name again is a hijack.
        with running([SYS_PY, NODE, "sub", "/talker_a", "/chatter", "10"], env=network.ros_env("robot_b")) as hijack:
            read_lines(hijack, "READY", 20)
            time.sleep(2)
        assert pub.poll() is None, "the hijack shut the real talker down"
    assert "name_taken" in network.hosts["master"].logs()
    # robot B's operator finds the master's refusal in robot B's own log and denials too
    told = [line for line in denials(network, "robot_b").splitlines()
            if "name_taken" in line and "the master's interceptor refused" in line and "/talker_a" in line]
    assert told, denials(network, "robot_b")


def test_a_name_squatted_through_a_wildcard_goes_to_the_manager_whose_grants_name_it(network):
    """Robot B's grant lets any of its nodes subscribe /chatter (``*``); robot A's grants
    name /roscpp_talker itself. B's node takes that name before A's starts (a squat: no
    owner, no hold yet). A's node registers it all the same: the registry gives A that
    very name. rosmaster then drops what the squatter had registered, the master's
    interceptor forgets it too, and the squatter can no longer act under the name."""
    def publishers_and_subscribers():
        publishers, subscribers, _services = master_state(network)
        return dict(publishers).get("/chatter", []), dict(subscribers).get("/chatter", [])

    log_before = len(network.hosts["master"].logs())
    with running([SYS_PY, NODE, "sub", "/roscpp_talker", "/chatter", "30"], env=network.ros_env("robot_b")) as squat:
        read_lines(squat, "READY", 20)
        deadline = time.monotonic() + 20
        while "/roscpp_talker" not in publishers_and_subscribers()[1]:  # the squat went through
            assert time.monotonic() < deadline, publishers_and_subscribers()
            time.sleep(0.1)
        with talker(network, node="/roscpp_talker") as pub:
            read_lines(pub, "READY", 20)
            deadline = time.monotonic() + 20
            # A's publisher is registered, B's subscription under the name is gone
            while (state := publishers_and_subscribers()) and not \
                    ("/roscpp_talker" in state[0] and "/roscpp_talker" not in state[1]):
                assert time.monotonic() < deadline, state
                time.sleep(0.1)
            assert pub.poll() is None
        assert "/roscpp_talker registered from another API" in network.hosts["master"].logs()[log_before:]
    assert "name_taken" not in "".join(line for line in network.hosts["master"].logs()[log_before:].splitlines()
                                       if "robot_a" in line and "/roscpp_talker" in line)


def test_a_node_killed_and_started_again_has_the_relays_of_its_old_api_released(network):
    """SIGKILL leaves no time to unregister: the restarted node registers the same name
    from a new API. rosmaster drops what the old API had registered; the master's
    interceptor forgets it too and releases the relay it kept for the old API at once,
    not when the relay limit pushes it out."""
    log_before = len(network.hosts["master"].logs())
    with talker(network, node="/talker_a") as first:
        read_lines(first, "READY", 20)
        wait_registered(network, "/talker_a")
        first.kill()
        first.wait(timeout=10)
    with talker(network, node="/talker_a") as again:
        read_lines(again, "READY", 20)
        deadline = time.monotonic() + 20
        while "/talker_a registered from another API" not in (new := network.hosts["master"].logs()[log_before:]):
            assert time.monotonic() < deadline, new[-3000:]
            time.sleep(0.1)
        assert "released (no registration behind it)" in network.hosts["master"].logs()[log_before:]
        publishers, _subscribers, _services = master_state(network)
        assert dict(publishers).get("/chatter", []).count("/talker_a") == 1


def test_a_replaced_nodes_parameter_subscription_frees_its_relay_too(network):
    """A node's parameter subscription (roscpp's cached parameters) holds a relay at the
    master's interceptor; when the node registers from another API, rosmaster drops the
    subscription and the master's interceptor releases that relay."""
    local_b = xmlrpc.client.ServerProxy(network.hosts["robot_b"].master_uri)
    log_before = len(network.hosts["master"].logs())
    with network.inside("robot_b"):
        assert local_b.subscribeParam("/rospy_listener", "http://127.0.0.1:9/", "/rospy_listener/rate")[0] == 1
        assert local_b.registerSubscriber("/rospy_listener", "/chatter", "std_msgs/String",
                                          "http://127.0.0.1:10/")[0] == 1
        try:
            deadline = time.monotonic() + 10
            while "released (no registration behind it)" not in (new := network.hosts["master"].logs()[log_before:]):
                assert time.monotonic() < deadline, new[-3000:]
                time.sleep(0.1)
            assert "/rospy_listener registered from another API" in new
        finally:
            local_b.unregisterSubscriber("/rospy_listener", "/chatter", "http://127.0.0.1:10/")


def test_a_restarting_nodes_name_is_held_for_its_manager_in_between(network):
    """Robot A's /rospy_talker stops (rospy unregisters it) and is started again. In
    between, robot B's node of the same name (B's grant names any node subscribing
    /chatter) is refused: the name stays robot A's for [limits] name_hold_seconds (120 s
    by default). Robot A's restarted node registers it again."""
    def denied_names() -> int:
        return sum(1 for line in network.hosts["master"].logs().splitlines()
                   if "name_taken" in line and "/rospy_talker" in line)

    with running([SYS_PY, NODE, "pub", "/rospy_talker", "/chatter", "3", "20", "0.2"],
                 env=network.ros_env("robot_a")) as pub:
        read_lines(pub, "READY", 20)
        wait_registered(network, "/rospy_talker")
        pub.wait(timeout=30)  # it publishes and ends by itself (a SIGTERM would skip rospy's unregistering)
    deadline = time.monotonic() + 20
    while "/rospy_talker" in nodes_in_state(master_state(network)):  # unregistered as it ended
        assert time.monotonic() < deadline, "/rospy_talker stayed registered after it stopped"
        time.sleep(0.1)
    before = denied_names()
    with running([SYS_PY, NODE, "sub", "/rospy_talker", "/chatter", "10"], env=network.ros_env("robot_b")) as squat:
        read_lines(squat, "READY", 20)  # rospy does not wait for its registration: READY comes anyway
        deadline = time.monotonic() + 20
        while denied_names() == before:
            assert time.monotonic() < deadline, "robot B's node took the released name"
            time.sleep(0.1)
    assert "/rospy_talker" not in nodes_in_state(master_state(network))
    with talker(network, node="/rospy_talker") as pub:  # the owner takes its name back
        read_lines(pub, "READY", 20)
        wait_registered(network, "/rospy_talker")


def refused_at_handshake(host, port, ca, cert, key) -> bool:
    """True when the TLS handshake fails. Under TLS 1.3 the server's verdict on the
    client certificate arrives after the client's own handshake completed: as an alert
    on the first read, or as the connection closing with nothing sent."""
    try:
        with rogue_tls(host, port, ca=ca, cert=cert, key=key) as s:
            s.settimeout(10)
            from cryptoros.tunnel import Preamble, encode

            s.sendall(encode(Preamble(token="x", purpose="node", target="1")))
            return s.recv(1) == b""
    except (ssl.SSLError, ConnectionError):
        return True


def test_tls_without_certificate_other_ca_or_revoked_fails_the_handshake(network, tmp_path):
    import signal

    from tests.pki_fixtures import TestPKIFactory

    host, port = public(network, "robot_a")
    ca = network.pki.ca_cert
    assert refused_at_handshake(host, port, ca, None, None)
    other = TestPKIFactory(tmp_path / "other")
    foreign = other.issue("robot_b", kind="interceptor", sans=("IP:127.0.0.3",))
    assert refused_at_handshake(host, port, ca, foreign.cert_path, foreign.key_path)
    revoked = network.pki.issue("revoked_robot", kind="interceptor", sans=("IP:127.0.0.9",))
    # Before revocation the same certificate gets through the handshake (and is then
    # refused for having no valid token, which is another test).
    with rogue_tls(host, port, ca=ca, cert=revoked.cert_path, key=revoked.key_path) as s:
        assert rogue_preamble(s, "x", "node", "1").ok is False
    network.pki.revoke("revoked_robot")
    # The interceptor reads the CRL at start and on SIGHUP: reload, then try again.
    network.hosts["robot_a"].proc.send_signal(signal.SIGHUP)
    deadline = time.monotonic() + 10
    while "reloaded" not in network.hosts["robot_a"].logs() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert refused_at_handshake(host, port, ca, revoked.cert_path, revoked.key_path)
    assert network.hosts["robot_a"].proc.poll() is None
    # Each refused handshake is a denial with its reason, in the log and in /metrics.
    # each is logged as robot A handles the failed handshake, a moment after the client saw it fail
    for reason in ("peer did not return a certificate", "unable to get local issuer certificate", "certificate_revoked"):
        until(lambda reason=reason: reason in denials(network, "robot_a"), 5, f"robot A logging {reason}")
    import urllib.request

    with network.inside("robot_a"):
        metrics = urllib.request.urlopen(f"http://127.0.0.1:{network.hosts['robot_a'].metrics_port}/metrics", timeout=5)
        text = metrics.read().decode()
    assert 'kind="tls",reason="certificate_verify_failed"' in text
    assert 'kind="tls",reason="peer_did_not_return_a_certificate"' in text


def test_valid_certificate_with_bad_tokens_is_refused(network):
    key, kid = signing_key(network)
    now = int(time.time())
    b_cert = cert(network, "robot_b")[0]
    b_der = ssl.PEM_cert_to_DER_cert(b_cert.read_text())

    def claims(**kw):
        c = build_claims(issuer="cryptoros-authz", audience="cryptoros", subject="robot_b", grants=Grants(),
                         cert_der=b_der, now=now, lifetime=300)
        c.update(kw)
        return c

    from cryptography.hazmat.primitives.asymmetric import rsa

    forged = sign_token(claims(), rsa.generate_private_key(public_exponent=65537, key_size=2048), kid)
    expired = sign_token(claims(iat=now - 900, nbf=now - 900, exp=now - 600), key, kid)
    other_cert = token_of(network, "robot_c")  # genuine, but bound to robot C's certificate
    assert claims()["cnf"]["x5t#S256"] == cert_thumbprint_s256(b_der)
    for token in ("", "not.a.token", forged, expired, other_cert):
        with rogue(network, "robot_a", "robot_b") as s:
            if token:
                reply = rogue_preamble(s, token, "node", "1")
            else:  # no token at all: garbage instead of a preamble
                s.sendall(b"GET / HTTP/1.1\r\n\r\n")
                reply = None
                try:
                    data = s.recv(100)
                    reply = data or None
                except (ssl.SSLError, ConnectionError):
                    pass
            assert reply is None or getattr(reply, "ok", False) is False, (token[:20], reply)
    log = denials(network, "robot_a")
    for reason in ("bad_signature", "expired", "cnf_mismatch"):
        assert reason in log
