"""Every ROS 2 sample checked before it is republished, rate limits
that throttle and never stall, the receiver's QoS, and a stream cut when the grant
that carried it is revoked. Unit tests of the pure parts, and real rclpy processes
behind real interceptors for the system behaviour.
"""

from __future__ import annotations

import socket
import ssl
import struct
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cryptoros.ros2 import framing as fr
from cryptoros.ros2.cdr import CdrError, checker_for
from cryptoros.ros2.target import QoS, StreamTarget, receiver_qos
from interceptor.pump import MessageBudget

# ---------------------------------------------------------------- samples of the demo's types


def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def _samples() -> dict[str, bytes]:
    ts = _typestore()
    T, H = ts.types["builtin_interfaces/msg/Time"], ts.types["std_msgs/msg/Header"]
    header = H(stamp=T(sec=5, nanosec=7), frame_id="map")
    P, Q = ts.types["geometry_msgs/msg/Point"], ts.types["geometry_msgs/msg/Quaternion"]
    V = ts.types["geometry_msgs/msg/Vector3"]
    layout = ts.types["std_msgs/msg/MultiArrayLayout"](
        dim=[ts.types["std_msgs/msg/MultiArrayDimension"](label="x", size=3, stride=3)], data_offset=0)
    msgs = {
        "std_msgs/msg/String": ts.types["std_msgs/msg/String"](data="héllo"),
        "geometry_msgs/msg/PoseStamped": ts.types["geometry_msgs/msg/PoseStamped"](
            header=header, pose=ts.types["geometry_msgs/msg/Pose"](position=P(x=1.0, y=2.0, z=0.0),
                                                                   orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0))),
        "sensor_msgs/msg/LaserScan": ts.types["sensor_msgs/msg/LaserScan"](
            header=header, angle_min=0.0, angle_max=1.0, angle_increment=0.1, time_increment=0.0, scan_time=0.1,
            range_min=0.1, range_max=10.0, ranges=np.arange(360, dtype=np.float32),
            intensities=np.zeros(0, dtype=np.float32)),
        "geometry_msgs/msg/Twist": ts.types["geometry_msgs/msg/Twist"](linear=V(x=0.5, y=0.0, z=0.0),
                                                                       angular=V(x=0.0, y=0.0, z=0.1)),
        "std_msgs/msg/UInt8MultiArray": ts.types["std_msgs/msg/UInt8MultiArray"](
            layout=layout, data=np.arange(7, dtype=np.uint8)),
    }
    return {t: bytes(ts.serialize_cdr(m, t)) for t, m in msgs.items()}


SAMPLES = _samples()


@pytest.mark.parametrize("type_name", sorted(SAMPLES))
def test_genuine_samples_pass_and_broken_ones_are_refused(type_name):
    check, raw = checker_for(type_name), SAMPLES[type_name]
    check(raw)
    check(raw + b"\x00" * 3)  # alignment padding at the end
    for bad in (b"", raw[:3], raw[:-1] if len(raw) > 8 else raw[:4], raw + b"\x00" * 8, b"\x00\x06" + raw[2:]):
        with pytest.raises(CdrError):
            check(bad)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(sorted(SAMPLES)), st.data())
def test_random_and_mutated_payloads_raise_cdr_errors_and_nothing_else(type_name, data):
    raw = bytearray(SAMPLES[type_name])
    how = data.draw(st.sampled_from(["random", "flip", "cut", "grow"]))
    if how == "random":
        raw = bytearray(data.draw(st.binary(max_size=200)))
    elif how == "flip":
        i = data.draw(st.integers(0, len(raw) - 1))
        raw[i] = data.draw(st.integers(0, 255))
    elif how == "cut":
        raw = raw[: data.draw(st.integers(0, len(raw) - 1))]
    else:
        raw += data.draw(st.binary(min_size=4, max_size=50))
    # fuzz: a CdrError or nothing, never another exception (a crash of the receiving role)
    try:
        checker_for(type_name)(bytes(raw))
    except CdrError:
        pass
    if how in ("cut", "grow"):  # a length off by more than padding never passes
        with pytest.raises(CdrError):
            checker_for(type_name)(bytes(raw))


# ---------------------------------------------------------------- service bodies

PROBE_SRV = """string name
builtin_interfaces/Time[] stamps
---
bool ok
string[] labels
uint8[] blob
"""


def test_service_requests_and_responses_are_checked_against_their_srv_and_bounded_in_elements():
    """ROS 2 audit (HIGH): service bodies went to the bridge unchecked, where rclpy builds
    the message: a 12 MiB answer claiming as many empty elements took the bridge to
    2.5 GB. Requests and responses are now checked like topic samples, against the
    service's .srv, with at most MAX_SERVICE_ELEMENTS strings and messages in their
    sequences (numbers in arrays do not count: one array each)."""
    from cryptoros.ros2.cdr import MAX_SERVICE_ELEMENTS, service_checkers

    check_request, check_response = service_checkers("cryptoros_test/srv/Probe", PROBE_SRV)
    ts = _typestore_with_probe()
    T = ts.types["builtin_interfaces/msg/Time"]
    Req, Resp = ts.types["cryptoros_test/msg/Probe_Request"], ts.types["cryptoros_test/msg/Probe_Response"]
    request = bytes(ts.serialize_cdr(Req(name="x", stamps=[T(sec=1, nanosec=2)] * 3), Req.__msgtype__))
    check_request(request)
    blob = np.zeros(1 << 20, dtype=np.uint8)
    fine = bytes(ts.serialize_cdr(Resp(ok=True, labels=["a"] * 10, blob=blob), Resp.__msgtype__))
    check_response(fine)
    many = bytes(ts.serialize_cdr(Resp(ok=True, labels=["a"] * (MAX_SERVICE_ELEMENTS + 1),
                                       blob=np.zeros(0, dtype=np.uint8)), Resp.__msgtype__))
    for _ in range(2):  # refused each time, and the budget starts over for the next body
        with pytest.raises(CdrError, match="strings and messages"):
            check_response(many)
        check_response(fine)
    with pytest.raises(CdrError):  # a request is no response
        check_response(request)
    claimed = b"\x00\x01\x00\x00\x01\x00\x00\x00" + struct.pack("<I", 4_000_000) + b"\x00" * 4_000_000
    with pytest.raises(CdrError):
        check_response(claimed)
    with pytest.raises(CdrError):
        check_request(request + b"\x00" * 8)
    with pytest.raises(CdrError, match="not a service definition"):
        service_checkers("cryptoros_test/srv/NoSeparator", "string name\n")


def _typestore_with_probe():
    from cryptoros.ros2.cdr import _typestore

    return _typestore()  # service_checkers registered the probe's request and response in it


def test_a_service_frame_of_max_message_size_with_its_id_fits_the_bridge_link():
    """ROS 2 audit (HIGH): a peer's service frame of exactly max_message_size, given its
    call id by the interceptor, was 4 bytes over the bridge's limit; the bridge took it
    for a broken link and exited (every flow of the robot down 2 s, as often as the peer
    liked). Both ends of the link allow LINK_SLACK bytes beyond it."""
    size = 4096
    frame = fr.encode(fr.CALL, 7, fr.ID.pack(1) + b"\x00" * size)
    decoder = fr.FrameDecoder(max_size=size + fr.LINK_SLACK)
    decoder.feed(frame)
    assert [(kind, chan, len(body)) for kind, chan, body in decoder.frames()] == [(fr.CALL, 7, size + 4)]
    from pathlib import Path

    import cryptoros.ros2

    bridge = (Path(cryptoros.ros2.__file__).parent / "bridge_node.py").read_text()
    assert "FrameDecoder(max_size=self.max_size + fr.LINK_SLACK)" in bridge


# ---------------------------------------------------------------- the limiter


@pytest.mark.parametrize("factor", [1, 10, 1000])
def test_a_burst_of_any_size_is_throttled_to_the_rate_and_never_stalls(factor):
    now = [0.0]
    budget = MessageBudget(200, clock=lambda: now[0])
    burst = int(budget.burst)
    batch = burst * factor
    waited = 0.0
    for _ in range(1000):  # a bounded loop: it must get through long before this
        wait = budget.delay(batch)
        if wait == 0:
            break
        waited += wait
        now[0] += wait
    else:
        raise AssertionError(f"a batch of {batch} never passed")
    # the batch passes once the bucket is full; the debt it leaves holds the next ones back
    assert waited <= 1.0 / 200 * burst + 1e-9
    then = now[0]
    while budget.delay(1) > 0:
        now[0] += budget.delay(1)
    assert now[0] - then == pytest.approx(max(0, batch - burst + 1) / 200, rel=0.01, abs=0.01)


def test_the_receiver_decides_qos():
    from interceptor.config import Ros2Settings

    asked = QoS(reliability="reliable", durability="transient_local", depth=1000)
    here = Ros2Settings(domain_id=1, python=__import__("pathlib").Path("/x"), depth=10, transient_local=("/map",))
    spy = receiver_qos(asked, depth=here.depth, keep_for_late_joiners=here.keeps_for_late_joiners("/spyout"))
    assert (spy.durability, spy.depth) == ("volatile", 10)
    team_map = receiver_qos(asked, depth=here.depth, keep_for_late_joiners=here.keeps_for_late_joiners("/map"))
    assert (team_map.durability, team_map.depth) == ("transient_local", 10)


# ---------------------------------------------------------------- real rclpy processes


@pytest.fixture(scope="module")
def network(tmp_path_factory):
    from tests.ros2_support import ros2_network

    # robot B keeps at most 1 MiB of one peer's samples for late joiners (/latched only)
    with ros2_network(tmp_path_factory.mktemp("ros2h"), start=("robot_a", "robot_b", "robot_c"),
                      extra={"robot_b": "max_kept_bytes_per_peer = 1048576"}) as net:
        yield net


def _rogue(network, host, as_name):
    from tests.interceptor_harness import rogue_tls

    h = network.robots[host]
    return rogue_tls(h.address, h.public_port, ca=network.pki.ca_cert, cert=network.pki.pki.cert_path_for(as_name),
                     key=network.pki.pki.key_path_for(as_name))


def _granted_token(network, manager: str, node: str, topic: str, type_name: str = "std_msgs/msg/String") -> str:
    """Grant ``manager``'s ``node`` to publish ``topic``; a token of it that carries the grant."""
    import jwt

    network.cli("grant", manager, "publish", node, topic, type_name)
    deadline = time.monotonic() + 10  # the daemon caches a manager's grants for a second
    while True:
        status, body = network.daemon.token(manager)
        assert status == 200
        grants = jwt.decode(body["access_token"], options={"verify_signature": False})["grants"]
        if topic in str(grants.get(node, {})):
            return body["access_token"]
        assert time.monotonic() < deadline, "the new grant never reached a token"
        time.sleep(0.2)


def test_an_empty_or_garbage_sample_is_refused_and_the_listener_keeps_receiving(network):
    """An insider with robot A's publish grant sends an empty and a garbage sample on its
    own stream; robot A's flow keeps reaching robot B's listener, during and after."""
    from tests.interceptor_harness import rogue_preamble
    from tests.ros2_support import flow_around

    target = StreamTarget(kind="topic", name="/chatter", type="std_msgs/msg/String", node="/talker").encode()
    status, body = network.daemon.token("robot_a")
    assert status == 200

    def attack(seen) -> None:
        with _rogue(network, "robot_b", "robot_a") as s:  # an insider with robot A's publish grant
            assert rogue_preamble(s, body["access_token"], "ros2", target).ok
            bad_utf8 = b"\x00\x01\x00\x00" + struct.pack("<I", 3) + b"\xff\xfe\x00"
            s.sendall(fr.encode(fr.DATA, 0, b"") + fr.encode(fr.DATA, 0, bad_utf8))
            seen.more_from_a(20, 15, "robot B's listener stopped receiving robot A's messages")

    flow_around(network, attack)  # no BAD line: asserted there
    log = network.robots["robot_b"].denials()
    assert "DENY ros2 sample from robot_a on /chatter" in log
    assert log.count("DENY ros2 sample") == 1  # once per stream


def test_a_local_subscriber_of_another_type_does_not_take_a_granted_topic_off_the_air(network):
    """ROS 2 audit: a node on robot A under no grant subscribed /chatter as Int32 (any
    local node may subscribe): the topic then had two types, robot A withdrew its granted
    talker's /chatter (``type_conflict``) and robot B's listener heard nothing while the
    other node ran. A topic's type is now its granted publishers'."""
    from tests.ros2_support import flow_around

    log_before = len(network.robots["robot_a"].logs())

    def attack(seen) -> None:
        with network.node("robot_a", "listener.py", "twist", "/chatter", "30", "--node", "other_type") as other:
            other.until("READY", 20)
            seen.more_from_a(60, 20, "robot B's listener stopped hearing robot A while /chatter had two types")

    flow_around(network, attack, during_bound=2.0)
    assert "type_conflict" not in network.robots["robot_a"].logs()[log_before:]


def test_removing_the_grant_cuts_an_open_ros2_stream_within_5_s(network):
    """robot_c's /spy stream on /chatter is cut within 5 s of its grant's removal; robot
    A's /chatter keeps reaching robot B's listener, during and after."""
    from tests.ros2_support import flow_around

    result: dict[str, float | None] = {}

    def attack(_seen) -> None:
        result["cut"] = _cut_after_revoking(network)

    flow_around(network, attack)
    cut = result["cut"]
    assert cut is not None and cut < 5, f"the stream was not cut within 5 s ({cut})"


def _cut_after_revoking(network) -> float | None:
    """Seconds from revoking robot_c's grant to its open stream being cut (None: not within 10 s)."""
    from tests.interceptor_harness import rogue_preamble

    token = _granted_token(network, "robot_c", "/spy", "/chatter")
    target = StreamTarget(kind="topic", name="/chatter", type="std_msgs/msg/String", node="/spy").encode()
    sample = _string_cdr("secret-500000")  # what robot B's listener reads as an insider's message
    with _rogue(network, "robot_b", "robot_c") as s:
        assert rogue_preamble(s, token, "ros2", target).ok
        s.sendall(fr.encode(fr.DATA, 0, sample))
        network.cli("revoke", "robot_c", "publish", "/spy", "/chatter")
        revoked_at = time.monotonic()
        s.settimeout(0.2)
        cut = None
        while time.monotonic() - revoked_at < 10:
            try:
                s.sendall(fr.encode(fr.DATA, 0, sample))
                if s.recv(100) == b"":
                    cut = time.monotonic() - revoked_at
                    break
            except socket.timeout:
                continue
            except (OSError, ssl.SSLError):
                cut = time.monotonic() - revoked_at
                break
    return cut


# ---------------------------------------------------------------- a robot's domain private to its host


def test_the_localhost_profile_keeps_a_robots_domain_from_a_stranger_on_another_host(tmp_path):
    """Robot A's rclpy talker in its own network namespace; a stranger in another one,
    given A's address as a static peer. Without the profile (the control: what
    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST alone gives) the stranger reads the topic;
    with it, or with the bridge's profile derived from it, nothing."""
    import os
    import subprocess

    from cryptoros.lab.netns import NetnsLab
    from cryptoros.ros2.profile import PROFILE_ENV, localhost_env, write_bridge_profile
    from tests.interceptor_harness import separate_hosts
    from tests.ros2_support import NODES, fresh_domains, ros2_env, ros2_python

    separate_hosts()
    python = str(ros2_python())
    (domain,) = fresh_domains(1)
    bridge_profile = write_bridge_profile(tmp_path)
    got = {}
    with NetnsLab() as lab:
        a, s = lab.add_host("a"), lab.add_host("s")
        for profile in ("none", "localhost", "bridge"):
            env_a = ros2_env(domain, localhost_profile=profile != "none")
            if profile == "bridge":
                env_a[PROFILE_ENV] = str(bridge_profile)
            env_s = {**ros2_env(domain, localhost_profile=False), "ROS_STATIC_PEERS": a.address}
            talker = subprocess.Popen(a.argv([python, str(NODES / "talker.py"), "string", "/secret", "100000", "20"]),
                                      env=env_a, cwd=str(NODES), stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
            try:
                listener = subprocess.run(s.argv([python, str(NODES / "listener.py"), "string", "/secret", "8"]),
                                          env=env_s, cwd=str(NODES), capture_output=True, text=True, timeout=60)
            finally:
                talker.terminate()
                talker.wait(timeout=10)
            got[profile] = [line for line in listener.stdout.splitlines() if line.startswith("GOT")]
    assert got["none"], "control: without the profile the stranger should read the topic (the test can fail)"
    assert got["localhost"] == [], f"with the profile the stranger read {len(got['localhost'])} messages"
    assert got["bridge"] == [], f"with the bridge's profile the stranger read {len(got['bridge'])} messages"
    assert os.path.exists(localhost_env({})["FASTRTPS_DEFAULT_PROFILES_FILE"])


def test_the_bridges_profile_caps_the_samples_a_reliable_keep_all_path_holds(tmp_path):
    """A reliable KEEP_ALL publisher and a subscriber that never takes: the publisher gets
    out what the writer's and the reader's histories hold, then blocks. Fast DDS's default
    (the robot's localhost profile) holds 5,000 each; the bridge's profile 1,000 each, so
    a bridge never queues the backlog at which every message costs Fast DDS twice the
    CPU (docs/ros2.md, "The slow mode"). Counted, so a profile Fast DDS ignored fails."""
    import subprocess

    from cryptoros.ros2.profile import BRIDGE_MAX_SAMPLES, PROFILE_ENV, write_bridge_profile
    from tests.ros2_support import NODES, fresh_domains, ros2_env, ros2_python

    python = str(ros2_python())
    (domain,) = fresh_domains(1)
    bridge_profile = write_bridge_profile(tmp_path)
    sent = {}
    for profile in ("localhost", "bridge"):
        env = ros2_env(domain)
        if profile == "bridge":
            env[PROFILE_ENV] = str(bridge_profile)
        hold = subprocess.Popen([python, str(NODES / "backlog.py"), "hold", "/backlog"], env=env, cwd=str(NODES),
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        try:
            assert hold.stdout.readline().strip() == "READY"
            fill = subprocess.run([python, str(NODES / "backlog.py"), "fill", "/backlog", str(20 * BRIDGE_MAX_SAMPLES)],
                                  env=env, cwd=str(NODES), capture_output=True, text=True, timeout=90)
        finally:
            hold.stdin.close()
            hold.wait(timeout=15)
        assert fill.stdout.startswith("SENT "), fill.stderr[-2000:]
        sent[profile] = int(fill.stdout.split()[1])
    assert sent["bridge"] == 2 * BRIDGE_MAX_SAMPLES, sent
    assert sent["localhost"] > 4 * BRIDGE_MAX_SAMPLES, f"control: Fast DDS's default should hold more: {sent}"


def test_dribbled_preambles_to_the_ros2_role_are_cut_at_the_deadline(network):
    """Finding 7: the insider's preamble slowloris against the ros2 role: one byte a
    second on each of 12 TLS connections with its certificate; every one is closed by
    the preamble deadline (5 s) or refused past the per-certificate cap (8)."""
    from cryptoros.tunnel import Preamble, encode
    from tests.interceptor_harness import dribble

    from tests.ros2_support import flow_around

    status, body = network.daemon.token("robot_a")
    preamble = encode(Preamble(token=body["access_token"], purpose="ros2", target="{}"))
    left: list = []

    def attack(_seen) -> None:
        socks = [_rogue(network, "robot_b", "robot_a") for _ in range(12)]
        try:
            left.extend(dribble(socks, preamble, steps=20))
        finally:
            for s in socks:
                s.close()

    flow_around(network, attack)  # robot A's /chatter reaches robot B during and after
    assert not left, f"{len(left)} dribbling connections still open"
    log = network.robots["robot_b"].denials()
    assert "preamble_timeout" in log and "unauthenticated streams from this certificate" in log


# ---------------------------------------------------------------- only granted publishers are forwarded


def test_a_rogue_publisher_under_an_ungranted_name_is_dropped_from_its_first_sample(network):
    """Finding 5: a process on robot A's domain publishing robot A's granted ``/chatter``
    under a name without a grant (``/rogue``, 100 Hz, its own sequence numbers from
    500000) while the granted ``/talker`` runs: robot B gets none of the rogue's samples,
    not even the first, and the talker's messages keep arriving (the topic is not taken
    off the air); robot A logs the refusal."""
    from tests.ros2_support import collect, got

    with network.node("robot_b", "listener.py", "string", "/chatter", "60") as sub:
        sub.until("READY", 20)
        with network.node("robot_a", "talker.py", "string", "/chatter", "100000", "20"):
            assert got(collect(sub, 5, 25)), "nothing arrived before the rogue"
            with network.node("robot_a", "talker.py", "string", "/chatter", "100000", "100", "--node", "rogue",
                              "--offset", "500000") as rogue:
                rogue.until("READY", 20)
                # readiness: robot A's bridge has seen the rogue's samples (and refused them);
                # until then there is nothing to drop (DDS discovery takes longer on a busy machine)
                deadline = time.monotonic() + 30
                while "/rogue may not publish /chatter" not in network.robots["robot_a"].denials():
                    assert time.monotonic() < deadline, "robot A's bridge never saw the rogue's samples"
                    time.sleep(0.2)
                # newcomer audit: ROS 2 refusals named no grant, ROS 1 ones did
                assert ("to allow: cryptoros-authz grant robot_a publish /rogue /chatter std_msgs/msg/String"
                        in network.robots["robot_a"].denials()), network.robots["robot_a"].denials()
                during = collect(sub, 60, 20)  # 3 s of the talker while the rogue publishes 5x faster
            after = collect(sub, 40, 20)  # and once the rogue is gone
    assert not [s for s in got(after) if s >= 500000]
    seqs = got(during)
    assert not [s for s in seqs if s >= 500000], "a sample of the ungranted publisher reached robot B"
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "the granted talker's messages were interrupted"


# ---------------------------------------------------------------- need to know


def test_a_peer_without_the_grant_learns_no_name_of_what_robot_a_offers(network):
    """Finding 8: robot A offers ``/twist`` to its peers B and C; C's manager may not
    subscribe it. A learns C's grants from C's token first (a ``refresh`` exchange, no
    target) and never opens the stream to C: C's interceptor receives no ``ros2`` stream
    preamble at all, so neither the topic's name, type, node nor QoS."""
    from tests.ros2_support import collect, got

    def ros2_streams_in(name: str) -> float:
        for line in network.metrics(name).splitlines():
            if line.startswith("cryptoros_interceptor_connections_total") and 'purpose="ros2"' in line \
                    and 'direction="in"' in line:
                return float(line.rsplit(" ", 1)[1])
        return 0.0

    before = ros2_streams_in("robot_c")
    with network.node("robot_b", "listener.py", "twist", "/twist", "30") as sub:
        sub.until("READY", 20)
        with network.node("robot_a", "talker.py", "twist", "/twist", "100000", "20"):
            assert got(collect(sub, 10, 25)), "robot B did not receive /twist"
    assert ros2_streams_in("robot_c") == before, "robot C was offered a stream it may not receive"
    assert "/twist" not in network.robots["robot_c"].logs()
    denials = network.robots["robot_a"].denials()
    assert "robot_c may not subscribe /twist [geometry_msgs/msg/Twist]: not offered to it" in denials
    # the hint names the node it cannot know as a placeholder, and says what to put there
    assert "to allow: cryptoros-authz grant robot_c subscribe NODE /twist geometry_msgs/msg/Twist  # NODE: " in denials


def test_the_token_a_robot_shows_a_peer_is_narrowed_to_that_peer(network):
    """Finding 8, the token: what robot A answers a peer's preamble with is a token whose
    audience is that peer's certificate and whose grants are only A's grants on names
    the peer's manager holds a grant on (RFC 8707). Robot C (no grant on anything A
    publishes or serves) learns none of A's names; robot B, granted all of them, learns
    them; and the token A showed C is refused by robot B (another audience)."""
    import jwt

    from tests.interceptor_harness import rogue_preamble, token_of

    def reply_to(as_name: str) -> str:
        with _rogue(network, "robot_a", as_name) as s:
            reply = rogue_preamble(s, token_of(network, as_name), "refresh")
        assert reply is not None and reply.ok
        return reply.token

    def claims(token: str) -> dict:
        return jwt.decode(token, options={"verify_signature": False})

    c_names = {name for actions in claims(token_of(network, "robot_c"))["grants"].values()
               for rows in actions.values() for name, _type in rows}
    for_c, for_b = reply_to("robot_c"), reply_to("robot_b")
    assert claims(for_c)["aud"].startswith("urn:cryptoros:peer:") and claims(for_c)["aud"] != claims(for_b)["aud"]
    names_for_c = {name for actions in claims(for_c)["grants"].values() for rows in actions.values() for name, _ in rows}
    assert names_for_c <= c_names and not names_for_c & {"/twist", "/set_flag", "/secret", "/scan"}
    assert {"/twist", "/set_flag", "/chatter"} <= {
        name for actions in claims(for_b)["grants"].values() for rows in actions.values() for name, _ in rows}
    # robot B refuses the token narrowed for C: presented as robot A's it fails the audience check
    with _rogue(network, "robot_b", "robot_a") as s:
        assert not rogue_preamble(s, for_c, "refresh").ok
    assert "bad_audience" in network.robots["robot_b"].denials()


# ---------------------------------------------------------------- what the receiver keeps


def _string_cdr(text: str) -> bytes:
    ts = _typestore()
    return bytes(ts.serialize_cdr(ts.types["std_msgs/msg/String"](data=text), "std_msgs/msg/String"))


def _insider_latched_stream(network):
    """robot_c granted to publish /latched as /spy; its token and a transient_local target."""
    token = _granted_token(network, "robot_c", "/spy", "/latched")
    target = StreamTarget(kind="topic", name="/latched", type="std_msgs/msg/String", node="/spy",
                          qos=QoS(reliability="reliable", durability="transient_local", depth=1000)).encode()
    return token, target


def _late_listener_hears(network, seconds: float = 4.0) -> list[str]:
    with network.node("robot_b", "listener.py", "string", "/latched", str(seconds), "--latched") as late:
        late.until("READY", 20)
        return [line for line in late.until("END", seconds + 20) if line.startswith(("GOT", "BAD"))]


def test_samples_kept_for_late_joiners_are_dropped_when_the_grant_that_carried_them_goes(network):
    """Finding 2: robot A's latched talker and an insider's transient_local stream both
    leave a sample robot B keeps for late joiners (control: a late listener gets both);
    once the insider's grant is revoked and its stream cut, a new late listener gets
    robot A's sample and nothing of the insider's (the topic stays advertised: A's
    stream is still open)."""
    from tests.interceptor_harness import rogue_preamble

    token, target = _insider_latched_stream(network)
    try:
        with network.node("robot_a", "talker.py", "string", "/latched", "1", "1", "--latched", "--offset", "7"):
            deadline = time.monotonic() + 30
            while _late_listener_hears(network, 2.0) != ["GOT 7"]:
                assert time.monotonic() < deadline, "robot A's latched sample never reached robot B"
            with _rogue(network, "robot_b", "robot_c") as s:
                assert rogue_preamble(s, token, "ros2", target).ok
                s.sendall(fr.encode(fr.DATA, 0, _string_cdr("secret-4242")))
                assert sorted(_late_listener_hears(network)) == ["GOT 4242", "GOT 7"], "the control failed"
                network.cli("revoke", "robot_c", "publish", "/spy", "/latched")
                s.settimeout(10)
                with pytest.raises((OSError, ssl.SSLError)):  # cut: reset, or EOF then a failing send
                    while s.recv(100):
                        pass
                    s.sendall(fr.encode(fr.DATA, 0, _string_cdr("secret-1")))
                    raise OSError("closed")
            assert _late_listener_hears(network) == ["GOT 7"], "a late joiner got the revoked insider's sample"
    finally:
        network.cli("revoke", "robot_c", "publish", "/spy", "/latched")


def test_a_peer_over_its_kept_memory_budget_is_refused_with_a_clear_denial(network):
    """Finding 2: robot B keeps at most 1 MiB of one peer's samples for late joiners; an
    insider's transient_local stream of 200 KB samples (depth capped at 10: 2 MB) is cut
    with ``kept_budget`` and nothing of it is replayed to a late joiner."""
    from tests.interceptor_harness import rogue_preamble
    from tests.ros2_support import flow_around

    token, target = _insider_latched_stream(network)

    def attack(_seen) -> None:
        with _rogue(network, "robot_b", "robot_c") as s:
            assert rogue_preamble(s, token, "ros2", target).ok
            s.settimeout(10)
            with pytest.raises((OSError, ssl.SSLError)):
                for i in range(50):
                    s.sendall(fr.encode(fr.DATA, 0, _string_cdr("x" * 200_000 + f"-{i}")))
                while s.recv(100):
                    pass
                raise OSError("closed")

    try:
        flow_around(network, attack)  # robot A's /chatter reaches robot B during and after
        log = network.robots["robot_b"].denials()
        assert "kept_budget" in log and "max_kept_bytes_per_peer" in log
        # robot A's latched sample of the test before ("GOT 7") may still be kept: its offer
        # outlives its talker by VANISHED_GRACE; nothing of the insider's may be
        assert [line for line in _late_listener_hears(network) if line != "GOT 7"] == []
    finally:
        network.cli("revoke", "robot_c", "publish", "/spy", "/latched")
