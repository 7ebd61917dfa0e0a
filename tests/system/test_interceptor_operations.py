"""Interceptor operations with real ROS 1: revocation cut-off, confidentiality on the
wire, hostile bytes on every port, SIGHUP and SIGTERM, metrics."""

from __future__ import annotations

import json
import os
import random
import re
import signal
import socket
import struct
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from tests.interceptor_harness import NODE, SYS_PY, robot_network, rogue_preamble, rogue_tls
from tests.interceptor_harness import denials, got, read_lines, rogue_to, token_of
from tests.ros1_flow import flow_policy, legit_flow
from tests.support import Capture, running

pytestmark = [pytest.mark.ros1]


FLOOD_LIMIT = 100.0  # messages per second robot B accepts from any one peer


@pytest.fixture(scope="module")
def network(tmp_path_factory):
    limits = f"[limits]\nmax_messages_per_second = {FLOOD_LIMIT}"
    # the legitimate flows around the attacks: robot C to robot B, robot A to robot C
    policy = flow_policy(flow_policy(talker="robot_c", listener="robot_b"), talker="robot_a", listener="robot_c")
    with robot_network(tmp_path_factory.mktemp("net"), extra={"robot_b": limits}, policy=policy) as net:
        yield net


def metrics(network, host) -> str:
    url = f"http://127.0.0.1:{network.hosts[host].metrics_port}/metrics"
    return urllib.request.urlopen(url, timeout=5).read().decode()


def flow_works(network, node_pub="/talker_a", node_sub="/listener_b", count=5) -> list[str]:
    """A talker on A and a listener on B exchange ``count`` messages (fresh processes)."""
    with running([SYS_PY, NODE, "sub", node_sub, "/chatter", "20"], env=network.ros_env("robot_b")) as sub:
        read_lines(sub, "READY", 20)
        with running([SYS_PY, NODE, "pub", node_pub, "/chatter", str(count), "20", "1"], env=network.ros_env("robot_a")):
            return got(read_lines(sub, f"GOT secret-{count - 1}", 30))


# ------------------------------------------------------------------ confidentiality


def test_capture_between_interceptors_holds_no_published_string(network, tmp_path):
    # Without interceptors (straight to rosmaster), the strings are on the wire.
    plain = Capture(tmp_path / "plain.pcap", "tcp", prove_loopback=True)
    with running([SYS_PY, NODE, "sub", "/listener_b", "/chatter", "20"], env=network.ros_env(None)) as sub:
        read_lines(sub, "READY", 20)
        with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "20", "50", "1"], env=network.ros_env(None)):
            read_lines(sub, "GOT secret-19", 30)
    plain_bytes = plain.stop(until=b"secret-19")  # what the listener got, in the file too
    # the published strings are readable on the wire
    assert b"secret-" in plain_bytes, f"the control capture missed them ({plain.dropped} packets dropped by the kernel)"

    # With interceptors: capture only what travels between hosts (127.0.0.2-5).
    hosts = " or ".join(f"host {h.address}" for h in network.hosts.values())
    secure = Capture(tmp_path / "secure.pcap", f"tcp and ({hosts})", prove_loopback=True,
                     marker_host=network.hosts["robot_a"].address)  # live before the flow starts
    assert flow_works(network, count=20) == [f"secret-{i}" for i in range(20)]
    secure_bytes = secure.stop()
    assert len(secure_bytes) > 5000, "the capture saw no traffic between the interceptors"
    assert b"secret-" not in secure_bytes
    assert b"/chatter" not in secure_bytes and b"std_msgs/String" not in secure_bytes


# ------------------------------------------------------------------ hostile bytes


def send_garbage(host: str, port: int, payload: bytes) -> None:
    try:
        with socket.create_connection((host, port), timeout=5) as s:
            s.sendall(payload)
            s.settimeout(1)
            with_timeout_read(s)
    except OSError:
        pass


def with_timeout_read(s) -> None:
    try:
        while s.recv(65536):
            pass
    except OSError:
        pass


def test_hostile_bytes_on_every_port_leave_it_serving(network):
    """A stranger's and an insider's garbage on every port of robot A, while robot A's
    /flow to robot C goes on (tests/ros1_flow.py)."""
    with legit_flow(network, "robot_a", "robot_c") as flow:
        _hostile_bytes(network, flow)


def _hostile_bytes(network, flow) -> None:
    rng = random.Random(7)
    a = network.hosts["robot_a"]
    b = network.hosts["robot_b"]
    # Make robot B hold relays toward robot A (so relay ports exist), then find them.
    assert flow_works(network) == [f"secret-{i}" for i in range(5)]
    relays = [int(line.split("relay 127.0.0.1:")[1].split()[0]) for line in b.logs().splitlines() if "relay 127.0.0.1:" in line]
    assert relays
    tcpros_header = lambda fields: struct.pack("<I", len(fields)) + fields  # noqa: E731
    payloads = [
        os.urandom(4096),
        bytes(rng.getrandbits(8) for _ in range(100)),
        b"\x16\x03\x01\x00",  # truncated TLS record
        struct.pack("<I", 0xFFFFFFF0) + b"x" * 100,  # oversized declared header
        tcpros_header(b"\x05\x00\x00\x00topic"),  # field without '='
        b"POST / HTTP/1.1\r\nContent-Length: 999999999999\r\n\r\n",
        b"POST / HTTP/1.1\r\nContent-Length: 60\r\n\r\n<?xml version='1.0'?><!DOCTYPE x [<!ENTITY a 'b'>]><x/>",
        b"GET /metrics HTTP/1.1\r\n" + b"X: " + b"a" * 70000 + b"\r\n\r\n",
    ]
    ports = [(a.address, a.public_port), ("127.0.0.1", a.local_master_port), ("127.0.0.1", a.metrics_port),
             *(("127.0.0.1", p) for p in relays[:4])]
    from concurrent.futures import ThreadPoolExecutor

    with flow.held("garbage on every port"), ThreadPoolExecutor(max_workers=16) as pool:  # all at once: a small flood
        list(pool.map(lambda job: send_garbage(*job), [(h, p, pl) for h, p in ports for pl in payloads]))
    # TLS with a valid certificate, then garbage in place of the preamble and stream.
    token = token_of(network, "robot_b")
    cert, key = network.pki.pki.cert_path_for("robot_b"), network.pki.pki.key_path_for("robot_b")
    def over_tls(payload: bytes, preamble: tuple[str, str] | None) -> None:
        try:
            with rogue_tls(a.address, a.public_port, ca=network.pki.ca_cert, cert=cert, key=key) as s:
                if preamble is not None:  # a valid token first, then garbage as the stream
                    rogue_preamble(s, token, *preamble)
                s.sendall(payload)
                s.settimeout(1)
                with_timeout_read(s)
        except OSError:
            pass

    jobs = [(pl, None) for pl in payloads]
    jobs += [(struct.pack("<I", 0x7FFFFFFF) + os.urandom(64), p) for p in (("topic", "2"), ("node", "1"), ("master", ""))]
    with flow.held("garbage over TLS"), ThreadPoolExecutor(max_workers=8) as pool:
        list(pool.map(lambda job: over_tls(*job), jobs))
    for host in network.hosts.values():
        assert host.proc is None or host.proc.poll() is None, f"{host.name} died:\n{host.logs()[-2000:]}"
    assert flow_works(network, node_pub="/talker_a", node_sub="/listener_b") == [f"secret-{i}" for i in range(5)]


def count_received(network, host_pub, host_sub, count, seconds) -> int:
    """A flood of ``count`` messages as fast as rospy sends them; how many arrive in
    ``seconds`` after the first one."""
    with running([SYS_PY, NODE, "sub", "/victim", "/chatter", "30"], env=network.ros_env(host_sub)) as sub:
        read_lines(sub, "READY", 20)
        with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", str(count), "0", "10"],
                     env=network.ros_env(host_pub)):
            read_lines(sub, "GOT secret-0", 30)
            return 1 + len(got(read_lines(sub, None, seconds)))


def test_message_flood_from_a_peer_is_throttled_to_the_configured_rate(network):
    """Seed 001's denial of service (a flooded command topic): without interceptors the
    victim takes all of it; behind them, at most the configured rate per peer; and robot
    C's /flow to robot B goes on through the flood and after it (tests/ros1_flow.py)."""
    plain = count_received(network, None, None, 5000, 3.0)
    with legit_flow(network, "robot_c", "robot_b") as flow, flow.held("robot A's flood"):
        protected = count_received(network, "robot_a", "robot_b", 5000, 3.0)
    assert plain >= 2000, plain
    assert protected <= FLOOD_LIMIT * (1 + 3.0) + 50, protected
    assert protected >= FLOOD_LIMIT, protected  # throttled, not cut off


# ------------------------------------------------------------------ metrics, reload, revocation, stop


def test_metrics_count_connections_bytes_allows_and_denials(network):
    flow_works(network)
    text = metrics(network, "robot_a")
    for needle in (
        'cryptoros_interceptor_connections_total{direction="in",purpose="topic"}',
        'cryptoros_interceptor_bytes_total{direction="tx"}',
        'cryptoros_interceptor_allowed_total{kind="topic"}',
        "cryptoros_interceptor_token_expiry_seconds",
    ):
        assert needle in text, needle
    with urllib.request.urlopen(f"http://127.0.0.1:{network.hosts['robot_a'].metrics_port}/healthz", timeout=5) as r:
        assert r.status == 200


def test_sighup_reload_keeps_open_streams_and_disabled_manager_is_cut_off_within_5s(network):
    with running([SYS_PY, NODE, "sub", "/listener_b", "/chatter", "60"], env=network.ros_env("robot_b")) as sub:
        read_lines(sub, "READY", 20)
        with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "50", "30"], env=network.ros_env("robot_a")):
            read_lines(sub, "GOT secret-20", 30)
            for name, peer in (("robot_a", "robot_b"), ("robot_b", "robot_a")):  # the stream, on either side
                url = f"http://127.0.0.1:{network.hosts[name].metrics_port}/status"
                with urllib.request.urlopen(url, timeout=5) as reply:
                    status = json.loads(reply.read())
                assert status["peers"].get(peer, 0) >= 1, (name, status["peers"])
                assert status["open_streams"] == sum(status["peers"].values()), (name, status)
            for name in ("robot_a", "robot_b", "master"):
                network.hosts[name].proc.send_signal(signal.SIGHUP)
            before = len(got(read_lines(sub, None, 2.0)))
            assert before >= 50, "the stream stalled across SIGHUP"
            assert "reloaded" in network.hosts["robot_a"].logs()
            # Disable robot B: its open stream must stop within 5 s.
            result = network.cli("disable-manager", "robot_b")
            try:
                assert result.returncode == 0, result.stderr
                disabled_at = time.monotonic()
                read_lines(sub, None, 5.0)  # whatever still arrives in the next 5 s
                after = got(read_lines(sub, None, 3.0))
                assert after == [], (f"robot B still receives {len(after)} messages 5 s after being disabled; "
                                     f"robot A's log: {network.hosts['robot_a'].logs()[-3000:]}\n"
                                     f"robot B's log: {network.hosts['robot_b'].logs()[-3000:]}")
                assert time.monotonic() - disabled_at >= 5
                text = metrics(network, "robot_a")
                assert re.search(r'^cryptoros_interceptor_revocation_cutoffs_total\{reason="(subject_disabled|revoked)"\} '
                                 r'[1-9]', text, re.M), "the cut is not counted with its reason"
            finally:  # the module's later tests need robot B
                assert network.cli("enable-manager", "robot_b").returncode == 0
    # the tests after this one ask the daemon for robot B's token at once: wait out its
    # cache of the managers (seen once: access_denied right after enable-manager)
    deadline = time.monotonic() + 10
    while network.daemon.token("robot_b")[0] != 200:
        assert time.monotonic() < deadline, "the daemon still refuses robot B a token after enable-manager"
        time.sleep(0.1)


def listening_inode(host) -> str:
    """The kernel's inode of the socket listening on ``host``'s public port."""
    want = f"{socket.inet_aton(host.address)[::-1].hex().upper()}:{host.public_port:04X}"
    rows = [line.split() for line in Path(f"/proc/{host.proc.pid}/net/tcp").read_text().splitlines()[1:]]
    inodes = [row[9] for row in rows if row[1] == want and row[3] == "0A"]
    assert len(inodes) == 1, inodes
    return inodes[0]


def test_a_reload_swaps_the_certificate_source_and_never_rebinds_the_public_port(network):
    """SIGHUP reads [tls] again into a new certificate source; the listening socket is the
    same one before and after (no window where the port is closed or taken), and the next
    handshake is served."""
    a = network.hosts["robot_a"]
    before = listening_inode(a)
    assert "reloaded" in sighup(a)
    assert listening_inode(a) == before
    assert token_exchanges(network, "robot_a", "robot_b", 2) == [True, True]


def sighup(host, timeout: float = 20) -> str:
    """SIGHUP ``host``'s interceptor; the log lines it wrote until the reload's outcome."""
    before = len(host.logs())
    host.proc.send_signal(signal.SIGHUP)
    deadline = time.monotonic() + timeout
    while "reloaded" not in (lines := host.logs()[before:]) and "reload failed" not in lines:
        assert time.monotonic() < deadline, "no reload outcome in the log"
        time.sleep(0.1)
    return lines


def token_exchanges(net, host: str, as_name: str, count: int) -> list[bool]:
    """``count`` refresh streams in a row to ``host`` as ``as_name`` (its certificate and a
    genuine token): which were accepted."""
    token = token_of(net, as_name)
    accepted = []
    for _ in range(count):
        with rogue_to(net, host, as_name) as s:
            reply = rogue_preamble(s, token, "refresh")
        accepted.append(reply is not None and reply.ok)
    return accepted


def test_sighup_applies_a_changed_limit_and_refuses_a_key_that_needs_a_restart(tmp_path):
    """Day 2: a SIGHUP applies every key it can ([limits] here: new streams per second,
    observed on real streams) and refuses the whole reload, naming the key, when one needs
    a restart ([authz] url): nothing is swapped, and the interceptor keeps following its
    authorization server as before."""
    with robot_network(tmp_path, start=("master", "robot_a")) as net:
        a = net.hosts["robot_a"]
        assert token_exchanges(net, "robot_a", "robot_b", 6) == [True] * 6  # 50 per second by default
        original = a.config.read_text()
        limited = original + "[limits]\nmax_new_connections_per_second = 0.2\n"
        moved = limited.replace(f'url = "{net.authz_url}"', f'url = ["https://127.0.0.1:9", "{net.authz_url}"]')
        assert moved != limited
        a.config.write_text(moved)
        lines = sighup(a)
        assert "reload failed, keeping the old state: [authz] url changed: needs a restart of the interceptor" in lines
        assert "reloaded" not in lines
        assert token_exchanges(net, "robot_a", "robot_b", 6) == [True] * 6  # all or nothing: the limit is not in
        # the old authorization server is still followed: robot B disabled there is refused here
        token = token_of(net, "robot_b")
        assert net.cli("disable-manager", "robot_b").returncode == 0
        try:
            deadline = time.monotonic() + 10
            while "revoked: token" not in denials(net, "robot_a"):  # disabling revokes its tokens
                assert time.monotonic() < deadline, "robot A did not learn from its feed that robot B is disabled"
                with rogue_to(net, "robot_a", "robot_b") as s:
                    rogue_preamble(s, token, "refresh")
                time.sleep(0.2)
        finally:
            assert net.cli("enable-manager", "robot_b").returncode == 0

        def let_in_again() -> bool:
            status, body = net.daemon.token("robot_b")  # the daemon may refuse for a moment after enabling
            if status != 200:
                return False
            with rogue_to(net, "robot_a", "robot_b") as s:
                reply = rogue_preamble(s, body["access_token"], "refresh")
            return reply is not None and reply.ok

        deadline = time.monotonic() + 10
        while not let_in_again():
            assert time.monotonic() < deadline, "robot B was not let in again after enable-manager"
            time.sleep(0.2)
        a.config.write_text(limited)  # the limit alone: applied
        lines = sighup(a)
        assert "reloaded" in lines and "reload failed" not in lines
        accepted = token_exchanges(net, "robot_a", "robot_b", 6)
        assert accepted[0] and sum(accepted) <= 2, accepted  # a burst of 1 (twice 0.2), then 0.2 per second
        assert "rate_limited" in denials(net, "robot_a")


def test_sigterm_stops_the_interceptor_cleanly(network):
    host = network.hosts["robot_c"]
    network.start("robot_c")
    host.proc.send_signal(signal.SIGTERM)
    assert host.proc.wait(timeout=15) == 0
    with pytest.raises(OSError):
        socket.create_connection((host.address, host.public_port), timeout=1).close()



def test_cryptoros_status_shows_token_grants_feed_certificate_and_peers(network):
    """Day 2: `cryptoros status --config` on a host answers who its interceptor is to
    the registry now, read from the interceptor itself (its loopback /status): here
    robot A while robot B's listener receives its talker."""
    import json

    from tests.support import run, script

    deadline = time.monotonic() + 20  # the test before disabled and re-enabled robot B: its token is back first
    while True:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{network.hosts['robot_b'].metrics_port}/healthz", timeout=5):
                break
        except urllib.error.HTTPError:
            assert time.monotonic() < deadline, "robot B's authority did not come back after enable-manager"
            time.sleep(0.1)
    host = network.hosts["robot_a"]
    status = [script("cryptoros"), "status", "--config", str(host.config)]
    with running([SYS_PY, NODE, "sub", "/listener_b", "/chatter", "30"], env=network.ros_env("robot_b")) as sub:
        read_lines(sub, "READY", 20)
        with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "1"],
                     env=network.ros_env("robot_a")):
            assert got(read_lines(sub, "GOT", 30))
            shown = run(status, timeout=30)
            raw = json.loads(run([*status, "--json"], timeout=30).stdout)
    assert shown.returncode == 0, shown.stdout + shown.stderr
    assert "manager robot_a (node)" in shown.stdout and shown.stdout.splitlines()[0].endswith(": ok")
    assert "token     subject robot_a" in shown.stdout and "publish /chatter" in shown.stdout
    assert "cert      serial" in shown.stdout and "feed      age" in shown.stdout and "robot_b (" in shown.stdout
    assert raw["token"]["subject"] == "robot_a" and raw["feed"]["age"] is not None and raw["feed"]["age"] < 60
    # (fresh: under max_feed_age; the server's heartbeats renew it every feed_heartbeat, 15 s)
    assert raw["certificate"]["days_left"] > 300
    assert raw["peers"].get("robot_b", 0) >= 1  # robot B's topic stream into robot A
    down = run([script("cryptoros"), "status", "--url", "http://127.0.0.1:9/status"], timeout=30)
    assert down.returncode == 2 and "cannot read" in down.stderr and "Traceback" not in down.stderr
    # the interceptor's own /healthz (an easy mistake for /status): one line, no false all-clear
    healthz = f"http://127.0.0.1:{host.metrics_port}/healthz"
    for command in ("status", "denials"):
        probe = run([script("cryptoros"), command, "--url", healthz], timeout=30)
        assert probe.returncode == 2 and probe.stdout == "", probe.stdout + probe.stderr
        assert probe.stderr.strip() == (f"cryptoros {command}: error: {healthz} did not answer as an interceptor's "
                                        "/status (no manager, roles, public, health, certificate, feed, denials): "
                                        "give its [listen] metrics endpoint's /status"), probe.stderr
    # ROS 2 audit: a file whose [listen] metrics port another interceptor answers on was
    # shown that interceptor's state as its own
    other = host.config.with_name("robot_a_on_b_port.toml")
    a_port, b_port = host.metrics_port, network.hosts["robot_b"].metrics_port
    text = host.config.read_text()
    assert f"127.0.0.1:{a_port}" in text
    other.write_text(text.replace(f"127.0.0.1:{a_port}", f"127.0.0.1:{b_port}"))
    wrong = run([script("cryptoros"), "status", "--config", str(other)], timeout=30)
    assert wrong.returncode == 2 and wrong.stdout == "", wrong.stdout + wrong.stderr
    assert wrong.stderr.strip() == (f"cryptoros status: error: http://127.0.0.1:{b_port}/status is the interceptor "
                                    f"of manager robot_b, not robot_a as {other} says: is robot_a's interceptor "
                                    "running, and does another use its [listen] metrics port?"), wrong.stderr


def _healthz(network, name: str) -> int:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{network.hosts[name].metrics_port}/healthz", timeout=5) as r:
            return r.status
    except urllib.error.HTTPError as exc:
        return exc.code


def test_a_node_started_right_after_enable_manager_is_registered(network):
    """Day 2: right after `enable-manager` the robot's interceptor may not hold its token
    yet; a node starting in that moment waits for it (one refresh attempt) instead of
    having its registration refused."""
    assert network.cli("disable-manager", "robot_b").returncode == 0
    deadline = time.monotonic() + 20
    while _healthz(network, "robot_b") == 200:  # robot B's interceptor dropped its token
        assert time.monotonic() < deadline, "robot B kept its token after disable-manager"
        time.sleep(0.1)
    assert network.cli("enable-manager", "robot_b").returncode == 0
    with running([SYS_PY, NODE, "sub", "/listener_b", "/chatter", "30"], env=network.ros_env("robot_b")) as sub:
        read_lines(sub, "READY", 20)
        with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "5"],
                     env=network.ros_env("robot_a")):
            assert got(read_lines(sub, "GOT", 30)), "the listener started right after enable-manager got nothing"


def test_streams_opened_right_after_a_peers_renewal_are_accepted(network):
    """Day-2 audit: robot A's certificate renewed (the runbook's renew, set-cert, SIGHUP)
    while robot B's nodes subscribed to it: the first new stream from B after A's reload
    was refused (``bad_audience``: B's token was for A's old certificate), and a fresh
    ``rostopic echo`` waited with no message. Every new subscriber after the reload must
    receive."""
    a = network.hosts["robot_a"]
    with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20", "1"], env=network.ros_env("robot_a")):
        for i in range(3):  # streams from B to A in a row before the renewal (spares, kept sessions)
            with running([SYS_PY, NODE, "sub", f"/listener_b{i}", "/chatter", "20"], env=network.ros_env("robot_b")) as sub:
                assert got(read_lines(sub, "GOT", 30)), f"listener {i} before the renewal received nothing"
        renewed = network.pki.issue("robot_a", kind="interceptor", sans=(f"IP:{a.address}",), force=True)
        result = network.cli("set-cert", "robot_a", "--fingerprint", renewed.fingerprint_sha256)
        assert result.returncode == 0, result.stderr
        assert "reloaded certificates" in sighup(a)
        for i in range(3):
            with running([SYS_PY, NODE, "sub", f"/listener_r{i}", "/chatter", "20"], env=network.ros_env("robot_b")) as sub:
                assert got(read_lines(sub, "GOT", 15)), (
                    f"listener {i} after robot A's renewal received nothing; robot A's denials: "
                    f"{denials(network, 'robot_a')[-1500:]}")
