"""ROS 2 role pieces with no network: frames, stream targets, the [ros2] config section."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from cryptoros.errors import ConfigError, PolicyDenied, RemoteProtocolError
from cryptoros.policy.ros2 import local_offer, manager_may, may_learn
from cryptoros.ros2 import framing as fr
from cryptoros.ros2.target import QoS, StreamTarget
from cryptoros.grants import Grants
from interceptor.config import parse


def test_frames_round_trip_whole_byte_by_byte_and_with_trailing_data():
    frames = [(fr.DATA, 0, b"\x00\x01\x00\x00abc"), (fr.SRV_REQUEST, 7, b""), (fr.PUBLISH, 3, bytes(100_000))]
    wire = b"".join(fr.encode(*f) for f in frames)
    whole = fr.FrameDecoder()
    whole.feed(wire + b"\x05")
    assert whole.frames() == frames and whole.buffered == 1
    byte_by_byte, out = fr.FrameDecoder(), []
    for i in range(len(wire)):
        byte_by_byte.feed(wire[i : i + 1])
        out += byte_by_byte.frames()
    assert out == frames


def test_oversized_or_unexpected_frames_are_refused_before_buffering():
    decoder = fr.FrameDecoder(max_size=1000, kinds=frozenset({fr.DATA}))
    decoder.feed(fr.HEAD.pack(5 + 1001, fr.DATA, 0))
    with pytest.raises(fr.FrameError):
        decoder.frames()
    decoder = fr.FrameDecoder(kinds=frozenset({fr.DATA}))
    decoder.feed(fr.encode(fr.PUBLISH, 0, b"x"))
    with pytest.raises(fr.FrameError):
        decoder.frames()


@given(st.binary(max_size=64))
def test_any_input_parses_or_raises_frame_error(data):
    """Fuzz: any bytes give frames or a FrameError, never another exception; the frames
    given are of a known kind and are exactly the bytes they were read from."""
    decoder = fr.FrameDecoder(max_size=1 << 16)
    decoder.feed(data)
    try:
        frames = decoder.frames()
    except fr.FrameError:
        return
    assert all(kind in fr.KINDS for kind, _chan, _payload in frames)
    wire = b"".join(fr.encode(*frame) for frame in frames)
    assert data[: len(wire)] == wire and decoder.buffered == len(data) - len(wire)


@given(st.lists(st.tuples(st.sampled_from([fr.MESSAGE, fr.DATA, fr.CONTROL]), st.integers(0, 2), st.binary(max_size=40)),
                max_size=12),
       st.lists(st.integers(1, 64), max_size=30))
def test_runs_keep_consecutive_frames_of_one_channel_whole_whatever_the_chunks(frames, cuts):
    wire = b"".join(fr.encode(*f) for f in frames)
    decoder, got, pos = fr.FrameDecoder(), [], 0
    for cut in [*cuts, len(wire)]:
        decoder.feed(wire[pos : pos + cut])
        pos += cut
        for kind, chan, count, block in decoder.runs():
            payloads = fr.payloads(block)
            assert len(payloads) == count and bytes(block) == b"".join(fr.encode(kind, chan, p) for p in payloads)
            got += [(kind, chan, p) for p in payloads]
        if pos >= len(wire):
            break
    assert got == frames and decoder.buffered == 0


def test_retag_rewrites_every_header_in_place():
    block = bytearray(b"".join(fr.encode(fr.MESSAGE, 5, p) for p in (b"a", b"", bytes(70_000))))
    assert fr.retag(block, fr.DATA, 0) is block
    decoder = fr.FrameDecoder()
    decoder.feed(bytes(block))
    assert decoder.frames() == [(fr.DATA, 0, b"a"), (fr.DATA, 0, b""), (fr.DATA, 0, bytes(70_000))]


def test_runs_refuse_oversized_frames_from_the_header():
    decoder = fr.FrameDecoder(max_size=1000, kinds=frozenset({fr.DATA}))
    decoder.feed(fr.encode(fr.DATA, 0, b"ok") + fr.HEAD.pack(5 + 1001, fr.DATA, 0))
    with pytest.raises(fr.FrameError):
        decoder.runs()


@given(st.lists(st.binary(max_size=40), min_size=1, max_size=60), st.integers(1, 70))
def test_pieces_split_a_run_into_at_most_most_frames_each_and_lose_nothing(payloads, most):
    frames = bytearray(b"".join(fr.encode(fr.DATA, 0, p) for p in payloads))
    pieces = fr.pieces(frames, len(payloads), most)
    assert all(0 < count <= most for count, _ in pieces)
    assert sum(count for count, _ in pieces) == len(payloads)
    assert [p for _, piece in pieces for p in fr.payloads(piece)] == payloads


def test_a_recheck_never_reuses_a_peer_token_older_than_its_wait():
    """At a recheck only a peer token learnt at most RECHECK_MARGIN before the wait ended
    counts, whatever the timer: one firing a hair before PEER_RECHECK does not reuse the
    token learnt at its start (a re-added grant would reach its flow a recheck late)."""
    from interceptor.ros2 import PEER_RECHECK, RECHECK_MARGIN, reusable

    learnt = 100.0
    ended = learnt + PEER_RECHECK - 0.001  # the timer fired early
    assert not reusable(learnt, now=ended, recheck=ended)
    assert reusable(ended - RECHECK_MARGIN, now=ended, recheck=ended)
    assert not reusable(None, now=ended, recheck=ended)
    # between rechecks, a token learnt within PEER_RECHECK answers
    assert reusable(learnt, now=learnt + PEER_RECHECK - 0.1, recheck=None)
    assert not reusable(learnt, now=learnt + PEER_RECHECK, recheck=None)


def test_stream_target_round_trip_and_strict_decoding():
    t = StreamTarget(kind="topic", name="/scan", type="sensor_msgs/msg/LaserScan", node="/lidar",
                     qos=QoS(reliability="best_effort", durability="transient_local", depth=5))
    assert StreamTarget.decode(t.encode()) == t
    s = StreamTarget(kind="service", name="/set_flag", type="std_srvs/srv/SetBool", node="/flag_server")
    assert StreamTarget.decode(s.encode()) == s and (s.action, s.peer_action) == ("serve", "call")
    for bad in ('[]', '{"kind":"topic","name":"/a","type":"std_msgs/msg/String","node":"/n","x":1}',
                '{"kind":"topic","name":"/a","type":"std_srvs/srv/SetBool","node":"/n"}',
                '{"kind":"topic","name":"a","type":"std_msgs/msg/String","node":"/n"}',
                '{"kind":"topic","name":"/a","type":"std_msgs/msg/String","node":"/n","qos":{"reliability":"x",'
                '"durability":"volatile","depth":1}}'):
        with pytest.raises(RemoteProtocolError):
            StreamTarget.decode(bad)


def test_manager_may_is_decided_per_manager():
    grants = Grants.from_claim({"/listener": {"subscribe": [["/chatter", "std_msgs/msg/String"]]}})
    assert manager_may(grants, "subscribe", "/chatter", "std_msgs/msg/String")
    assert not manager_may(grants, "subscribe", "/chatter", "std_msgs/msg/Int32")
    assert not manager_may(grants, "publish", "/chatter", "std_msgs/msg/String")


# ---------------------------------------------------------------- the ROS 2 policy (pure)

STRING = "std_msgs/msg/String"
A_GRANTS = Grants.from_claim({"/talker": {"publish": [["/chatter", STRING]], "serve": [["/set_flag", "std_srvs/srv/SetBool"]]}})


def _pub(node, reliability="reliable", durability="volatile"):
    return {"node": node, "reliability": reliability, "durability": durability}


def test_a_publisher_discovery_has_not_named_yet_does_not_take_the_topic_off_the_air():
    offer = local_offer("topic", "/chatter", [STRING], [_pub("/talker"), _pub("/_NODE_NAME_UNKNOWN_")],
                        grants=A_GRANTS, depth=10)
    assert offer.writers == frozenset({"/talker"}) and offer.refused == ()


def test_a_topic_is_offered_with_only_its_granted_publishers_as_writers():
    offer = local_offer("topic", "/chatter", [STRING], [_pub("/talker"), _pub("/rogue", "best_effort")],
                        grants=A_GRANTS, depth=10)
    assert offer.writers == frozenset({"/talker"}) and offer.refused == ("/rogue",)
    assert offer.target.node == "/talker"
    assert offer.target.qos.reliability == "reliable"  # the rogue's QoS does not choose the stream's


@pytest.mark.parametrize(("kind", "name", "types", "sources", "reason"), [
    ("topic", "/chatter", [STRING], [_pub("/rogue")], "not_granted"),
    ("topic", "/chatter", [STRING, "std_msgs/msg/Int32"], [_pub("/talker")], "type_conflict"),
    ("topic", "/secret", [STRING], [_pub("/talker")], "not_granted"),
    # a service cannot be filtered per server: one ungranted server withholds it
    ("service", "/set_flag", ["std_srvs/srv/SetBool"], [{"node": "/flag_server"}], "not_granted"),
])
def test_what_a_robot_may_not_offer_is_denied_with_a_reason(kind, name, types, sources, reason):
    with pytest.raises(PolicyDenied) as info:
        local_offer(kind, name, types, sources, grants=A_GRANTS, depth=10)
    assert info.value.reason == reason


def _typed(node, type_name=STRING, reliability="reliable"):
    return {**_pub(node, reliability), "type": type_name}


def test_a_topic_is_decided_by_its_granted_publishers_types_not_a_subscribers_or_a_rogues():
    """ROS 2 audit: an ungranted node subscribing /chatter as Int32 (or publishing it)
    made the topic's types two, and the granted talker's /chatter went off the air."""
    both = [STRING, "std_msgs/msg/Int32"]  # what the graph lists: every endpoint's type
    offer = local_offer("topic", "/chatter", both, [_typed("/talker")], grants=A_GRANTS, depth=10)
    assert offer.target.type == STRING and offer.writers == frozenset({"/talker"}) and offer.refused == ()
    offer = local_offer("topic", "/chatter", both, [_typed("/talker"), _typed("/rogue", "std_msgs/msg/Int32")],
                        grants=A_GRANTS, depth=10)
    assert offer.target.type == STRING and offer.refused == ("/rogue",)
    with pytest.raises(PolicyDenied, match="may not publish /chatter") as info:
        local_offer("topic", "/chatter", both, [_typed("/talker", "std_msgs/msg/Int32")], grants=A_GRANTS, depth=10)
    assert info.value.reason == "not_granted"
    two = Grants.from_claim({"/talker": {"publish": [["/chatter", STRING]]},
                             "/other": {"publish": [["/chatter", "std_msgs/msg/Int32"]]}})
    conflict = r"granted nodes: /other \[std_msgs/msg/Int32\], /talker \[std_msgs/msg/String\]"
    with pytest.raises(PolicyDenied, match=conflict) as info:
        local_offer("topic", "/chatter", both, [_typed("/talker"), _typed("/other", "std_msgs/msg/Int32")],
                    grants=two, depth=10)
    assert info.value.reason == "type_conflict"


@pytest.mark.parametrize(("name", "types", "sources"), [
    ("/rosout", ["rcl_interfaces/msg/Log"], [_pub("/talker")]),  # ROS infrastructure stays local
    ("/talker/get_parameters", ["rcl_interfaces/srv/GetParameters"], [{"node": "/talker"}]),
    ("/chatter", [STRING], [_pub("/_NODE_NAME_UNKNOWN_")]),  # discovery not done: decided next round
    ("/chatter", [STRING], []),
])
def test_infrastructure_and_undecidable_entries_are_not_offered(name, types, sources):
    kind = "service" if types[0].count("/srv/") else "topic"
    assert local_offer(kind, name, types, sources, grants=A_GRANTS, depth=10) is None


def test_a_peer_learns_of_a_stream_only_when_it_may_receive_it():
    target = StreamTarget(kind="topic", name="/chatter", type=STRING, node="/talker")
    assert may_learn(Grants.from_claim({"*": {"subscribe": [["/chatter", STRING]]}}), target)
    assert not may_learn(Grants.from_claim({"*": {"subscribe": [["/other", STRING]]}}), target)
    assert not may_learn(Grants.from_claim({"*": {"publish": [["/chatter", STRING]]}}), target)


def _config(tmp_path, ros2: dict | None, roles=("ros2",)):
    raw = {"manager": "r", "roles": list(roles), "tls": {"ca": "ca", "cert": "c", "key": "k"},
           "authz": {"url": "https://127.0.0.1:1"}, "listen": {"public": "127.0.0.2:1"}}
    if ros2 is not None:
        raw["ros2"] = ros2
    return parse(raw, base=tmp_path)


def test_ros2_config_section(tmp_path):
    python = tmp_path / "python"
    for name in ("python", "ca", "c", "k"):
        (tmp_path / name).touch()
    cfg = _config(tmp_path, {"domain_id": 0, "python": "python", "peers": ["127.0.0.3:11400"], "depth": 5})
    assert cfg.ros2.domain_id == 0 and cfg.ros2.python == python and str(cfg.ros2.peers[0]) == "127.0.0.3:11400"
    for bad in ({"python": "python"}, {"domain_id": 300, "python": "python"}, {"domain_id": 1, "python": "nope"},
                {"domain_id": 1, "python": "python", "colour": "red"},
                {"domain_id": 1, "python": "python", "peers": ["x"]},
                {"domain_id": 1, "python": "python", "local": "/tf"},
                {"domain_id": 1, "python": "python", "local": ["tf"]},
                {"domain_id": 1, "python": "python", "local": [3]}):
        with pytest.raises(ConfigError):
            _config(tmp_path, bad)
    with pytest.raises(ConfigError):
        _config(tmp_path, {"domain_id": 1, "python": "python"}, roles=("master",))


def test_ros2_local_patterns_keep_names_on_the_robot(tmp_path):
    for name in ("python", "ca", "c", "k"):
        (tmp_path / name).touch()
    settings = _config(tmp_path, {"domain_id": 1, "python": "python", "local": ["/tf", "/r0/*"]}).ros2
    assert settings.local == ("/tf", "/r0/*")
    assert settings.is_local("/tf") and settings.is_local("/r0/pose") and settings.is_local("/r0/scan")
    assert not settings.is_local("/tf_static") and not settings.is_local("/team/map") and not settings.is_local("/r01")
    assert not _config(tmp_path, {"domain_id": 1, "python": "python"}).ros2.is_local("/tf")


def test_the_exposure_scan_finds_a_participant_bound_beyond_loopback_and_its_process(tmp_path):
    """A synthetic /proc: domain 55 is ports 21150..21399. Process 4242 has a metatraffic
    port on 0.0.0.0 (no profile), 4243 only loopback ones (the profile), and a socket of
    the domain's range on [::] belongs to nobody this user can read."""
    import os

    from cryptoros.ros2.exposure import ExposureScan, gid_pid16

    header = "  sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout inode\n"
    row = "   1: {addr}:{port:04X} 00000000:0000 07 00000000:00000000 00:00000000 00000000     0        0 {inode} 2\n"
    net = tmp_path / "net"
    net.mkdir()
    (net / "udp").write_text(header + "".join(row.format(addr=a, port=p, inode=i) for a, p, i in (
        ("00000000", 21160, 11), ("0100007F", 21162, 12), ("00000000", 46266, 13), ("0100007F", 21163, 14))))
    (net / "udp6").write_text(header + row.format(addr="0" * 32, port=21170, inode=15))
    for pid, inodes in ((4242, (11, 13)), (4243, (12, 14))):
        (tmp_path / str(pid) / "fd").mkdir(parents=True)
        (tmp_path / str(pid) / "cmdline").write_bytes(b"python3\0talker.py\0")
        for n, inode in enumerate(inodes):
            os.symlink(f"socket:[{inode}]", tmp_path / str(pid) / "fd" / str(n))
    found = ExposureScan(55, proc=tmp_path).scan()
    assert [(e.pid, e.sockets) for e in found] == [(4242, ("0.0.0.0:21160",)), (None, ("[::]:21170",))]
    assert found[0].command == "python3 talker.py" and found[0].pid16 == 4242
    assert ExposureScan(56, proc=tmp_path).scan() == ()
    # Fast DDS puts the pid's low 16 bits in bytes 4-5 of the GUID prefix (pid 27809 = 0x6ca1)
    assert gid_pid16("010f4037a16c13c0") == 27809
    assert gid_pid16("0000000000000000") is None and gid_pid16("zz") is None


def test_free_domains_skip_every_domain_with_a_bound_port(tmp_path):
    """Domains 10 and 12 have a socket bound (ports 9900 and 10400+): three consecutive
    free ids searched from 9 are 13..15; a start past the last fitting run wraps round to 0."""
    from cryptoros.ros2.exposure import free_domains

    header = "  sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout inode\n"
    row = "   1: 0100007F:{port:04X} 00000000:0000 07 00000000:00000000 00:00000000 00000000     0        0 {inode} 2\n"
    net = tmp_path / "net"
    net.mkdir()
    (net / "udp").write_text(header + row.format(port=7400 + 250 * 10, inode=1) + row.format(port=46266, inode=2))
    (net / "udp6").write_text(header + row.format(port=7400 + 250 * 12 + 249, inode=3))
    assert free_domains(3, 9, proc=tmp_path) == [13, 14, 15]
    assert free_domains(3, 0, proc=tmp_path) == [0, 1, 2]
    assert free_domains(3, 98, proc=tmp_path, top=101) == [98, 99, 100]
    assert free_domains(3, 99, proc=tmp_path, top=101) == [99, 100, 101]
    assert free_domains(3, 100, proc=tmp_path, top=101) == [0, 1, 2]  # 100..102 would pass the top: wraps
    assert free_domains(2, 10, proc=tmp_path) == [13, 14]
    # a worker's own part of the range (11..15): never a domain outside it
    assert free_domains(2, 11, proc=tmp_path, low=11, top=15) == [13, 14]
    assert free_domains(2, 14, proc=tmp_path, low=11, top=15) == [14, 15]
    assert free_domains(2, 15, proc=tmp_path, low=11, top=15) == [13, 14]  # 15..16 would pass the top: wraps


def test_the_shm_clean_tool_is_found_beside_the_ros2_python_then_on_path(tmp_path):
    from cryptoros.ros2.profile import segments_cleaned, shm_clean_command

    venv, elsewhere = tmp_path / "venv" / "bin", tmp_path / "elsewhere"
    venv.mkdir(parents=True)
    elsewhere.mkdir()
    (elsewhere / "fastdds").write_text("#!/bin/sh\n")
    (elsewhere / "fastdds").chmod(0o755)
    assert shm_clean_command(venv / "python", {"PATH": str(elsewhere)}) == [str(elsewhere / "fastdds"), "shm", "clean"]
    (venv / "fastdds").write_text("#!/bin/sh\n")
    assert shm_clean_command(venv / "python", {"PATH": str(elsewhere)}) == [str(venv / "fastdds"), "shm", "clean"]
    assert shm_clean_command(tmp_path / "python", {"PATH": str(tmp_path / "none")}) is None
    report = "shm.clean:\n0 ports in use\n1 segments in use\n115 zombie ports cleaned\n1270 zombie segments cleaned\n"
    assert segments_cleaned(report) == 1270
    assert segments_cleaned("usage: fastdds shm [<shm-command>]") == 0


def test_a_domain_whose_dds_ports_overlap_the_ephemeral_range_is_named_with_the_overlap():
    """ROS 2 audit: on domain 181 (ports 52650-52899, inside Linux's 32768-60999) a
    talker's own sending socket landed in the range now and then, and the talker was
    taken for a participant reachable from the network: its topic was never carried.
    Domains 0-101 stay below the default range."""
    from cryptoros.ros2.exposure import ephemeral_overlap, highest_private_domain

    linux = "32768\t60999\n"
    assert ephemeral_overlap(100, linux) is None  # 32400-32649
    assert ephemeral_overlap(101, linux) == range(32768, 32900)  # 32650-32899: its top 132 ports
    assert ephemeral_overlap(181, linux) == range(52650, 52900)
    assert ephemeral_overlap(232, linux) is None  # 65400-65649: above 60999
    assert highest_private_domain(linux) == 100
    assert highest_private_domain("40000 60999") == 129


def test_the_ros2_role_on_a_domain_over_the_ephemeral_ports_is_refused_or_warned():
    """deployment_problems (the start and --check): refused with require_private_domain
    (the default), a warning without it; a domain below the range is not mentioned."""
    from types import SimpleNamespace

    from cryptoros.ros2.exposure import highest_private_domain
    from interceptor.cli import ros2_domain_problem

    def cfg(domain: int, private: bool = True):
        return SimpleNamespace(roles=("node", "ros2"), ros2=SimpleNamespace(domain_id=domain,
                                                                             require_private_domain=private))

    top = highest_private_domain()
    assert ros2_domain_problem(cfg(top)) is None and ros2_domain_problem(cfg(0)) is None
    line = ros2_domain_problem(cfg(top + 1))
    assert line is not None and f"[ros2] domain_id {top + 1}" in line and f"use a domain_id from 0 to {top}" in line
    assert ros2_domain_problem(SimpleNamespace(roles=("node",), ros2=None)) is None


def test_a_withdrawn_offer_says_what_changed():
    """The interceptor's log line for a withdrawn offer gives its real cause (a retyped
    topic said "its publisher, its server or the grant that carried it is gone")."""
    from interceptor.ros2 import VANISHED_GRACE, Outbound, withdrawal_reason

    out = Outbound(target=StreamTarget(kind="topic", name="/chatter", type=STRING, node="/talker"), chan=1)
    key, int32 = ("topic", "/chatter", STRING), ("topic", "/chatter", "std_msgs/msg/Int32")
    assert withdrawal_reason(key, out, {int32: None}, {"/chatter"}, {}) == "its type is now std_msgs/msg/Int32"
    assert withdrawal_reason(key, out, {key: None}, {"/chatter"}, {}) == "its publisher's node or QoS changed"
    assert withdrawal_reason(key, out, {}, {"/chatter"}, {("topic", "/chatter"): "not_granted: ..."}) \
        == "not_granted: ..."
    assert "is gone" in withdrawal_reason(key, out, {}, set(), {})
    out.vanished_at = 1.0
    assert withdrawal_reason(key, out, {}, set(), {}) == \
        f"no named publisher or server in the graph for {VANISHED_GRACE:g} s"


def test_a_hint_for_a_node_it_cannot_name_says_where_the_name_comes_from():
    """ROS 2 audit: the NODE placeholder pointed at `ros2 node list`, which the rclpy
    wheels do not have."""
    from interceptor.ros2 import Ros2Role

    hint = Ros2Role._grant_hint("robot_b", "subscribe", None, "/status", "std_msgs/msg/Int32")
    assert hint.startswith("cryptoros-authz grant robot_b subscribe NODE /status std_msgs/msg/Int32  # NODE: ")
    assert "ros2 node list" not in hint and "create_node name" in hint


def test_the_inbound_half_reads_the_configuration_in_force():
    """A SIGHUP replaces the gateway's configuration, and ``[ros2] local``, ``depth``,
    ``transient_local`` and ``max_kept_bytes_per_peer`` apply to new streams: the inbound
    half reads the configuration in force, never a copy taken when it started."""
    from types import SimpleNamespace

    from interceptor.ros2_inbound import Ros2Inbound
    from interceptor.ros2_partial import PartialFrames

    before = SimpleNamespace(ros2=SimpleNamespace(python="/venv/bin/python", max_kept_bytes_per_peer=1))
    gw = SimpleNamespace(cfg=before, metrics=object())
    inbound = Ros2Inbound(gw, bridge=None, next_chan=lambda: 1, graph=dict, problem=lambda: None,
                          partial=PartialFrames())
    gw.cfg = SimpleNamespace(ros2=SimpleNamespace(python="/venv/bin/python", max_kept_bytes_per_peer=2))
    assert inbound.cfg.ros2.max_kept_bytes_per_peer == 2 and inbound.metrics is gw.metrics
