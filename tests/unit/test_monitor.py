"""The runtime monitor without sockets: features, the model and its file, the watched
stream's alerts and quarantine, the [monitor] configuration."""

from __future__ import annotations

import asyncio
import json
import math
import struct

import numpy as np
import pytest

from cryptoros.errors import ConfigError, PolicyDenied, RemoteProtocolError
from cryptoros.monitor.features import FEATURES, StreamFeatures
from cryptoros.monitor.model import FORMAT, AlertTracker, MonitorModel
from cryptoros.ros1 import msgs
from interceptor.monitor import Monitor, MonitorSettings
from tests.support import Clock

POSE, SCAN, TWIST = "geometry_msgs/PoseStamped", "sensor_msgs/LaserScan", "geometry_msgs/Twist"


def _time(t: float):
    return msgs.msg_class("builtin_interfaces/msg/Time")(sec=int(t), nanosec=int((t % 1) * 1e9))


def _header(t: float):
    return msgs.msg_class("std_msgs/Header")(seq=0, stamp=_time(t), frame_id="map")


def pose(x: float, y: float, t: float) -> bytes:
    C = msgs.msg_class
    body = C(POSE)(header=_header(t), pose=C("geometry_msgs/Pose")(
        position=C("geometry_msgs/Point")(x=x, y=y, z=0.0),
        orientation=C("geometry_msgs/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0)))
    return msgs.serialize(body, POSE)


def scan(ranges, t: float, range_min: float = 0.1, range_max: float = 10.0, angle_increment: float = 0.087) -> bytes:
    body = msgs.msg_class(SCAN)(header=_header(t), angle_min=0.0, angle_max=6.2, angle_increment=angle_increment,
                                time_increment=0.0, scan_time=0.2, range_min=range_min, range_max=range_max,
                                ranges=np.asarray(ranges, dtype=np.float32), intensities=np.zeros(0, np.float32))
    return msgs.serialize(body, SCAN)


def twist(linear: float, angular: float) -> bytes:
    vector = msgs.msg_class("geometry_msgs/Vector3")
    return msgs.serialize(msgs.msg_class(TWIST)(linear=vector(x=linear, y=0.0, z=0.0),
                                                angular=vector(x=0.0, y=0.0, z=angular)), TWIST)


def frame(body: bytes) -> bytes:
    return struct.pack("<I", len(body)) + body


def clean_poses(n: int, t0: float = 1000.0, hz: float = 20.0):
    """(body, arrival) of a robot driving at 0.3 m/s."""
    return [(pose(0.3 * i / hz, 1.0, t0 + i / hz), t0 + i / hz) for i in range(n)]


def named(kind: str, values: tuple[float, ...]) -> dict[str, float]:
    return dict(zip(FEATURES[kind], values))


def row(kind: str, **values: float) -> tuple[float, ...]:
    """A feature row of ``kind`` with ``values`` by name, every other feature 0."""
    assert set(values) <= set(FEATURES[kind])
    return tuple(values.get(name, 0.0) for name in FEATURES[kind])


# ------------------------------------------------------------------ features


def test_pose_features_show_a_jump_a_stamp_going_back_and_an_old_stamp():
    f = StreamFeatures(POSE)
    rows = [named("pose", f.observe(body, at, at)) for body, at in clean_poses(20)]
    assert max(r["speed_mps"] for r in rows) == pytest.approx(0.3, rel=0.01)
    assert max(r["rate_hz"] for r in rows) == 20 and all(r["malformed"] == 0 for r in rows)
    jump = named("pose", f.observe(pose(25.0, -3.0, 1001.0), 1001.0, 1001.0))
    assert jump["speed_mps"] > 100
    replay = named("pose", f.observe(pose(25.0, -3.0, 990.0), 1001.05, 1001.05))
    assert replay["stamp_back_s"] == pytest.approx(11.0) and replay["stamp_lag_s"] == pytest.approx(11.05)


def test_scan_noise_is_rough_and_changes_from_scan_to_scan():
    rng = np.random.default_rng(1)
    wall = 2.0 + np.sin(np.linspace(0, 6, 72))  # a smooth room
    f = StreamFeatures(SCAN)
    smooth = [named("scan", f.observe(scan(wall, 10 + i * 0.2), 10 + i * 0.2, 10 + i * 0.2)) for i in range(5)]
    noisy = [named("scan", f.observe(scan(rng.uniform(0.2, 9.0, 72), 11 + i * 0.2), 11 + i * 0.2, 11 + i * 0.2))
             for i in range(5)]
    assert max(r["roughness"] for r in smooth) < 0.1 < min(r["roughness"] for r in noisy)
    assert max(r["scan_change"] for r in smooth) < 0.01 < min(r["scan_change"] for r in noisy)


def test_scan_limits_that_change_or_hide_every_beam_are_suspicious():
    """seed 001's noise attack replaces every number of the scan, its range limits too:
    limits that leave no beam valid must not hide the ranges from scoring (they scored
    as a clean, empty scan), and a driver never changes its scan's geometry."""
    f = StreamFeatures(SCAN)
    steady = [named("scan", f.observe(scan(np.full(72, 2.0), 1000.0 + i / 5), 1000.0 + i / 5, 1000.0 + i / 5))
              for i in range(3)]
    assert all(v["geometry_change"] == 0.0 and v["malformed"] == 0.0 for v in steady)
    moved = named("scan", f.observe(scan(np.full(72, 2.0), 1001.0, range_max=8.0), 1001.0, 1001.0))
    assert moved["geometry_change"] == 1.0 and moved["malformed"] == 0.0
    for bad in (scan(np.full(72, 2.0), 1001.2, range_min=5.0, range_max=1.0),
                scan(np.full(72, 2.0), 1001.2, range_min=-3.0),
                scan(np.full(72, 2.0), 1001.2, angle_increment=0.0),
                scan(np.full(72, 2.0), 1001.2, range_max=float("nan"))):
        assert named("scan", f.observe(bad, 1001.2, 1001.2))["malformed"] == 1.0


def test_a_body_that_does_not_decode_is_malformed_and_any_type_has_rate_and_size():
    f = StreamFeatures(POSE)
    assert named("pose", f.observe(b"\x01\x02", 1.0, 1.0))["malformed"] == 1.0
    g = StreamFeatures("std_msgs/String")
    assert g.kind == "any" and len(g.observe(b"abcd", 1.0, 1.0)) == len(FEATURES["any"])
    assert named("any", g.observe(b"abcdefgh", 1.1, 1.1)) == {"rate_hz": 2.0, "burst_hz": 0.0, "size_change": 1.0,
                                                                "malformed": 0.0}


def test_a_flood_shows_in_burst_hz_within_a_few_messages_and_a_delayed_read_does_not():
    """``burst_hz`` is the rate over the last 3 arrivals: a 200 Hz flood added to a 10 Hz
    stream reads 200 Hz at its fourth message, while the second's count has hardly moved;
    messages read at once after a stall (the proxy's loop was busy) are one arrival."""
    from cryptoros.monitor.features import BURST_INTERVALS

    f = StreamFeatures(TWIST)
    clean = [named("twist", f.observe(twist(0.2, 0.0), 10 + i / 10, 10 + i / 10)) for i in range(20)]
    assert max(r["burst_hz"] for r in clean) == pytest.approx(10.0)
    flood = [named("twist", f.observe(twist(0.0, 0.0), 12.0 + i / 200, 12.0 + i / 200)) for i in range(1, 5)]
    assert flood[-1]["burst_hz"] == pytest.approx(200.0) and flood[-1]["rate_hz"] <= 14
    g = StreamFeatures(TWIST)
    for i in range(10):
        g.observe(twist(0.2, 0.0), 10 + i / 10, 10 + i / 10)
    stalled = [named("twist", g.observe(twist(0.2, 0.0), 11.5 + i * 1e-5, 11.5 + i * 1e-5)) for i in range(6)]
    assert max(r["burst_hz"] for r in stalled) < 10.0
    assert len(g._reads) == BURST_INTERVALS + 1


def test_the_warm_up_runs_every_known_kind_over_clean_messages():
    """The start-up warm-up (the first message of a kind costs ten times the next) runs
    each kind's content features over messages that decode: none comes out malformed."""
    from cryptoros.monitor.features import KIND_OF_TYPE, _warm_up_samples, warm_up

    warm_up()
    for typename, sample in _warm_up_samples().items():
        f = StreamFeatures(typename, topic="/r0/x")
        rows = [named(KIND_OF_TYPE[typename], f.observe(sample(t), t, t)) for t in (1.0, 1.1)]
        assert all(r["malformed"] == 0.0 for r in rows), (typename, rows)


def test_pose_and_twist_are_read_straight_from_the_bytes_as_the_full_decoder_reads_them():
    """The pose and twist features read the stamp and the few numbers they need straight
    from the serialized bytes (4-5x quicker than decoding the whole message); what they
    read is what the type's full decoder reads, and a body of another length is malformed."""
    from cryptoros.monitor.features import _decode_pose, _decode_twist

    C = msgs.msg_class
    rng = np.random.default_rng(3)
    for frame_id in ("", "map", "x" * 300):
        x, y = (float(v) for v in rng.uniform(-50, 50, 2))
        t = 1_700_000_000.123456789
        body = msgs.serialize(C(POSE)(header=msgs.msg_class("std_msgs/Header")(seq=7, stamp=_time(t), frame_id=frame_id),
                                      pose=C("geometry_msgs/Pose")(position=C("geometry_msgs/Point")(x=x, y=y, z=1.0),
                                      orientation=C("geometry_msgs/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0))), POSE)
        full = msgs.deserialize(body, POSE)
        stamp = full.header.stamp.sec + full.header.stamp.nanosec * 1e-9
        assert _decode_pose(body) == (stamp, full.pose.position.x, full.pose.position.y)
        for bad in (body[:-1], body + b"\0", body[:10]):
            with pytest.raises(RemoteProtocolError):
                _decode_pose(bad)
            assert named("pose", StreamFeatures(POSE).observe(bad, 1.0, 1.0))["malformed"] == 1.0
    vector = C("geometry_msgs/Vector3")
    twist = msgs.serialize(C(TWIST)(linear=vector(x=0.7, y=0.5, z=-0.5), angular=vector(x=0.1, y=0.2, z=-1.3)), TWIST)
    full = msgs.deserialize(twist, TWIST)
    assert _decode_twist(twist) == (full.linear.x, full.angular.z) == (0.7, -1.3)
    for bad in (twist[:-1], twist + b"\0"):
        assert named("twist", StreamFeatures(TWIST).observe(bad, 1.0, 1.0))["malformed"] == 1.0


def test_ros2_poses_and_twists_give_the_features_their_ros1_twins_give():
    """The ROS 2 role's samples (CDR) go through the type's full decoder, then the same
    feature code: one pose and one twist stream, fed the same values in both forms."""
    from cryptoros.ros2.cdr import _typestore

    store = _typestore()
    C = store.types
    ros1, ros2 = StreamFeatures(POSE), StreamFeatures("geometry_msgs/msg/PoseStamped", codec="cdr")
    for i, (x, t) in enumerate(((1.0, 100.0), (1.5, 100.1), (9.0, 99.5))):
        msg = C["geometry_msgs/msg/PoseStamped"](
            header=C["std_msgs/msg/Header"](stamp=C["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(t % 1 * 1e9)),
                                            frame_id="map"),
            pose=C["geometry_msgs/msg/Pose"](position=C["geometry_msgs/msg/Point"](x=x, y=2.0, z=0.0),
                                             orientation=C["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))
        sample = store.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped")
        assert ros2.observe(sample, 100 + i, 100 + i) == ros1.observe(pose(x, 2.0, t), 100 + i, 100 + i)
    vector = C["geometry_msgs/msg/Vector3"]
    sample = store.serialize_cdr(C["geometry_msgs/msg/Twist"](linear=vector(x=-0.4, y=0.0, z=0.0),
                                                              angular=vector(x=0.0, y=0.0, z=2.5)), "geometry_msgs/msg/Twist")
    assert named("twist", StreamFeatures("geometry_msgs/msg/Twist", codec="cdr").observe(sample, 1.0, 1.0))["angular"] == 2.5
    assert named("twist", StreamFeatures("geometry_msgs/msg/Twist", codec="cdr").observe(b"\0\1\0\0ab", 1.0, 1.0))[
        "malformed"] == 1.0


def test_a_team_map_patch_is_split_into_the_coarse_places_its_cells_lie_in():
    from cryptoros.monitor.features import _CELLS_PER_PLACE, REACH_CELL_M, TEAM_MAP_RESOLUTION_M, _places

    for origin in range(-23, 24):
        for n in range(1, 30):
            first, counts = _places(origin, n)
            place = np.floor((np.arange(n) + origin) * TEAM_MAP_RESOLUTION_M / REACH_CELL_M).astype(np.int64)
            assert (first, counts) == (place[0], np.bincount(place - place[0]).tolist()), (origin, n)
            assert sum(counts) == n and max(counts) <= _CELLS_PER_PLACE


def test_scan_means_count_only_beams_in_range_whatever_the_mix():
    """Roughness and change are means over valid beams only (NaN, inf and out-of-range
    beams left out, a step or a change only between two valid beams): checked against
    numpy's nan-aware means on scans with every mix of invalid beams."""
    rng = np.random.default_rng(5)
    f = StreamFeatures(SCAN)
    prev = None
    for i in range(40):
        ranges = rng.uniform(0.2, 9.5, 72)
        bad = rng.random(72) < (i % 5) / 5  # from none to most beams invalid
        ranges[bad] = rng.choice([np.inf, np.nan, 0.01, 50.0], size=int(bad.sum()))
        got = named("scan", f.observe(scan(ranges, 10 + i / 5), 10 + i / 5, 10 + i / 5))
        kept = np.where((ranges >= 0.1) & (ranges <= 10.0), ranges.astype(np.float32).astype(np.float64), np.nan)
        scale = max(float(np.nanmean(kept)) if np.isfinite(kept).any() else 0.0, 1e-3)
        steps = np.abs(np.diff(kept))
        rough = float(np.nanmean(steps)) / scale if np.isfinite(steps).any() else 0.0
        change = 0.0
        if prev is not None:
            delta = np.abs(kept - prev)
            change = float(np.nanmean(delta)) / scale if np.isfinite(delta).any() else 0.0
        assert got["roughness"] == pytest.approx(rough, rel=1e-9, abs=1e-12), i
        assert got["scan_change"] == pytest.approx(change, rel=1e-9, abs=1e-12), i
        assert got["malformed"] == 0.0
        prev = kept


def test_twist_features_are_the_commanded_speeds():
    C = msgs.msg_class
    vec = C("geometry_msgs/Vector3")
    body = msgs.serialize(C(TWIST)(linear=vec(x=-0.5, y=0.0, z=7.0), angular=vec(x=0.0, y=0.0, z=-1.5)), TWIST)
    values = named("twist", StreamFeatures(TWIST).observe(body, 1.0, 1.0))
    assert values["linear"] == 0.5 and values["angular"] == 1.5


# ------------------------------------------------------------------ the model


def fitted(consecutive: int = 3) -> MonitorModel:
    f = StreamFeatures(POSE)
    rows = [f.observe(body, at, at) for body, at in clean_poses(400)]
    return MonitorModel.fit({"pose": rows}, consecutive=consecutive)


def test_fit_sets_limits_above_clean_traffic_and_scores_excursions():
    model = fitted()
    limits = model.limits["pose"]
    assert 0.3 < limits["speed_mps"] < 1.0 and limits["rate_hz"] > 20
    assert "any" in model.limits and model.trained_on == {"pose": 400, "any": 400}
    f = StreamFeatures(POSE)
    clean = [model.score("pose", f.observe(body, at, at)).value for body, at in clean_poses(50, t0=5000.0)]
    assert max(clean) < 1.0
    jump = model.score("pose", f.observe(pose(40.0, 40.0, 5002.6), 5002.6, 5002.6))
    assert jump.value > 10 and jump.feature == "speed_mps"


def test_nan_or_infinite_content_is_never_clean_and_a_stamp_ahead_of_the_clock_shows():
    model = fitted()
    f = StreamFeatures(POSE)
    for body, at in clean_poses(5, t0=7000.0):
        f.observe(body, at, at)
    nan = model.score("pose", f.observe(pose(math.nan, 1.0, 7000.3), 7000.3, 7000.3))
    assert nan.value == math.inf and nan.feature == "speed_mps"
    ahead = model.score("pose", f.observe(pose(1.0, 1.0, 7100.0), 7000.35, 7000.35))
    assert ahead.value > 1 and named("pose", f.observe(pose(1.0, 1.0, 7200.0), 7000.4, 7000.4))["stamp_lag_s"] > 199


def test_the_model_file_round_trips_and_bad_files_are_one_clear_error(tmp_path):
    model = fitted()
    path = tmp_path / "m.json"
    model.save(path)
    assert MonitorModel.load(path) == MonitorModel.from_json(json.loads(path.read_text()))
    assert MonitorModel.load(path).limits == model.limits
    bad = {
        "not json": "{",
        "other format": json.dumps({"format": "x", "limits": {}}),
        "unknown kind": json.dumps({"format": FORMAT, "limits": {"lidar": {"rate_hz": 1}}}),
        "unknown feature": json.dumps({"format": FORMAT, "limits": {"pose": {"colour": 1}}}),
        "negative limit": json.dumps({"format": FORMAT, "limits": {"pose": {"rate_hz": -1}}}),
        "infinite limit": '{"format": "%s", "limits": {"pose": {"rate_hz": Infinity}}}' % FORMAT,
        "bad consecutive": json.dumps({"format": FORMAT, "limits": {"any": {"rate_hz": 5}}, "consecutive": 0}),
    }
    for what, text in bad.items():
        path.write_text(text)
        with pytest.raises(ConfigError):
            MonitorModel.load(path)
        assert what
    with pytest.raises(ConfigError, match="not found"):
        MonitorModel.load(tmp_path / "missing.json")


def test_alerts_need_a_run_of_suspicious_messages_and_fire_once_per_run():
    t = AlertTracker(3)
    assert [t.update(s) for s in (True, True, False, True, True, True, True, False, True, True, True)] == \
        [False, False, False, False, False, True, False, False, False, False, True]


def test_a_severe_message_alerts_alone_once_and_the_model_keeps_the_setting(tmp_path):
    t = AlertTracker(3)
    # a severe message completes the run at once; the run goes on without a second alert
    assert [t.update(s, v) for s, v in ((True, False), (True, True), (True, False), (False, False), (True, True))] == \
        [False, True, False, False, True]
    model = fitted()
    assert model.severe == 5.0
    assert model.is_severe(model.score("pose", row("pose", rate_hz=1.0, speed_mps=1000.0)))
    assert not model.is_severe(model.score("pose", row("pose", rate_hz=1.0, speed_mps=0.4)))
    model.save(tmp_path / "m.json")
    assert MonitorModel.load(tmp_path / "m.json").severe == 5.0
    raw = json.loads((tmp_path / "m.json").read_text())
    for bad in (0.5, -1, True, "5"):
        (tmp_path / "bad.json").write_text(json.dumps({**raw, "severe": bad}))
        with pytest.raises(ConfigError, match="severe"):
            MonitorModel.load(tmp_path / "bad.json")
    del raw["severe"]  # a model written before the setting: the default
    (tmp_path / "old.json").write_text(json.dumps(raw))
    assert MonitorModel.load(tmp_path / "old.json").severe == 5.0
    off = MonitorModel.fit({"pose": [row("pose", rate_hz=1.0, speed_mps=0.3)]}, severe=0)
    assert not off.is_severe(off.score("pose", row("pose", rate_hz=1.0, speed_mps=1e9)))


def test_the_lstm_threshold_for_a_false_positive_rate_flags_at_most_that_share_of_clean_messages():
    from cryptoros.monitor.lstm import Sequence, threshold_for

    rng = np.random.default_rng(0)
    seqs, outputs = [], []
    for _ in range(3):
        attack = rng.random(400) < 0.3
        out = np.where(attack, rng.uniform(0.3, 1.0, 400), rng.uniform(0.0, 0.95, 400)).astype(np.float32)
        seqs.append(Sequence(np.zeros((400, 1), np.float32), attack, np.arange(400.0), 0.0, "s"))
        outputs.append((out, 0.0))
    clean = np.concatenate([o[~s.attack] for s, (o, _) in zip(seqs, outputs)])
    for fpr in (0.0, 0.005, 0.1):
        t = threshold_for(seqs, outputs, fpr)
        assert (clean > t).sum() <= fpr * clean.size
        below = clean[clean <= t]  # the lowest such threshold: one clean output lower and more are flagged
        assert below.size == 0 or (clean >= below.max()).sum() > fpr * clean.size


# ------------------------------------------------------------------ the watched stream


def monitor_for(tmp_path, *, action="quarantine", clock=None, state_path=None, **extra) -> tuple[Monitor, list]:
    from prometheus_client import CollectorRegistry

    fitted().save(tmp_path / "m.json")
    denials: list = []
    extra.setdefault("batch_seconds", 0.0)  # scored on the loop's next turn: drain() sees it
    settings = MonitorSettings(model=tmp_path / "m.json", action=action, quarantine_seconds=30.0, **extra)
    kw = {"clock": clock, "wall": clock} if clock else {}
    return Monitor(settings, CollectorRegistry(), deny=lambda k, e, w: denials.append((k, e.reason, w)),
                   state_path=state_path, **kw), denials


async def drain() -> None:
    for _ in range(5):
        await asyncio.sleep(0)


async def test_a_spoofing_publisher_is_quarantined_and_only_it_is_cut(tmp_path):
    clock = Clock()
    monitor, denials = monitor_for(tmp_path, clock=clock)
    cuts: list[str] = []
    honest = monitor.watch(manager="robot_a", publisher="/base", topic="/r0/pose", typename=POSE,
                           cut=lambda: cuts.append("honest"))
    evil = monitor.watch(manager="robot_a", publisher="/evil", topic="/r0/pose", typename=POSE,
                         cut=lambda: cuts.append("evil (monitor gave up)"))
    monitor.register("robot_a", "/base", lambda: cuts.append("honest"))  # every topic stream is registered
    monitor.register("robot_a", "/evil", lambda: cuts.append("evil"))
    monitor.register("robot_a", "/evil", lambda: cuts.append("evil other topic"))  # an unwatched one too
    for body, at in clean_poses(40):
        clock.t = at
        data = frame(body)
        honest.feed(data[:9])  # frames split across reads
        honest.feed(data[9:])
        await drain()
    assert cuts == [] and denials == []
    rng = np.random.default_rng(3)
    for i in range(5):
        clock.t += 0.005
        evil.feed(frame(pose(*rng.uniform(-50, 50, 2), clock.t)))
    await drain()
    assert sorted(cuts) == ["evil", "evil other topic"]
    assert denials == [("monitor", "quarantined", "/evil (robot_a)")]
    with pytest.raises(PolicyDenied, match="quarantined") as info:
        monitor.check_admission("robot_a", "/evil")
    assert info.value.reason == "quarantined"
    monitor.check_admission("robot_a", "/base")  # the honest publisher is not refused
    clock.t += 31.0
    monitor.check_admission("robot_a", "/evil")  # quarantine over


async def test_quarantines_are_kept_across_a_restart_for_the_time_left(tmp_path, caplog):
    """A restarted interceptor (a crash, an operator's restart) still refuses what it had
    quarantined, for the time left (wall clock: the monotonic one starts again); an
    unreadable file is logged and puts nothing in force."""
    state = tmp_path / "state" / "robot_b.quarantine.json"
    clock = Clock()
    monitor, _denials = monitor_for(tmp_path, clock=clock, state_path=state)
    evil = monitor.watch(manager="robot_a", publisher="/evil", topic="/r0/pose", typename=POSE, cut=lambda: None)
    rng = np.random.default_rng(3)
    for _ in range(5):
        clock.t += 0.005
        evil.feed(frame(pose(*rng.uniform(-50, 50, 2), clock.t)))
    await drain()
    assert monitor.quarantined_for("robot_a", "/evil") == pytest.approx(30.0, abs=0.1)
    assert state.exists() and oct(state.stat().st_mode & 0o777) == "0o600"

    clock.t += 10.0  # restarted 10 s later
    again, _ = monitor_for(tmp_path, clock=clock, state_path=state)
    assert again.quarantined_for("robot_a", "/evil") == pytest.approx(20.0, abs=0.1)
    with pytest.raises(PolicyDenied, match="quarantined"):
        again.check_admission("robot_a", "/evil")
    again.check_admission("robot_a", "/base")
    clock.t += 21.0  # over: restarted again, nothing is refused
    monitor_for(tmp_path, clock=clock, state_path=state)[0].check_admission("robot_a", "/evil")

    good = {"manager": "robot_a", "publisher": "/evil", "until": clock.t + 20.0}
    for bad in ("{not json", '{"version": 2, "quarantined": []}', '{"version": 1, "quarantined": [{"manager": 1}]}',
                json.dumps({"version": 1, "quarantined": [good, {"manager": "robot_a", "publisher": 7, "until": 1}]})):
        state.write_text(bad)
        caplog.clear()
        fresh, _ = monitor_for(tmp_path, clock=clock, state_path=state)
        fresh.check_admission("robot_a", "/evil")
        assert "were not read" in caplog.text


async def test_an_operator_lifts_one_quarantine_or_a_managers_and_the_request_is_used_once(tmp_path, caplog):
    """``cryptoros unquarantine`` writes a release request beside the quarantine file;
    the monitor applies it (on SIGHUP, or at start), keeps the rest, and removes it."""
    from interceptor.monitor import WHOLE_MANAGER, release_path_for

    state = tmp_path / "state" / "robot_b.quarantine.json"
    clock = Clock()
    state.parent.mkdir()
    kept = [("robot_a", "/a"), ("robot_a", "/b"), ("robot_a", WHOLE_MANAGER), ("robot_c", "/c")]
    state.write_text(json.dumps({"version": 1, "quarantined": [{"manager": m, "publisher": p, "until": clock.t + 30.0}
                                                                for m, p in kept]}))
    monitor, _ = monitor_for(tmp_path, clock=clock, state_path=state)  # as a restarted interceptor has them

    def quarantined(m) -> set:
        return {(q["manager"], q["publisher"]) for q in m.status()["quarantined"]}

    assert quarantined(monitor) == set(kept)
    release = release_path_for(state)
    release.write_text(json.dumps({"version": 1, "release": [{"manager": "robot_a", "publisher": "/a"}]}))
    assert monitor.apply_releases() == ["/a (robot_a)"]
    assert not release.exists() and monitor.apply_releases() == []
    assert quarantined(monitor) == set(kept) - {("robot_a", "/a")}
    release.write_text(json.dumps({"version": 1, "release": [{"manager": "robot_a", "publisher": None}]}))
    restarted, _ = monitor_for(tmp_path, clock=clock, state_path=state)  # applied at start too
    assert restarted.quarantined_for("robot_a", "/b") == 0 and restarted.quarantined_for("robot_a", "/x") == 0
    assert restarted.quarantined_for("robot_c", "/c") > 0
    assert "lifted by the operator: /b (robot_a), every publisher of robot_a" in caplog.text
    release.write_text("{not json")
    assert restarted.apply_releases() == [] and not release.exists()
    assert restarted.quarantined_for("robot_c", "/c") > 0 and "nothing lifted" in caplog.text


async def test_action_log_alerts_but_cuts_nothing(tmp_path):
    clock = Clock()
    monitor, denials = monitor_for(tmp_path, action="log", clock=clock)
    cuts: list[str] = []
    evil = monitor.watch(manager="m", publisher="/evil", topic="/r0/pose", typename=POSE, cut=lambda: cuts.append("x"))
    for i in range(6):
        clock.t = 1000 + i / 20
        evil.feed(frame(pose(100.0 * (i % 2), 0.0, clock.t)))
        await drain()
    assert cuts == [] and denials == []
    assert monitor.metrics.alerts.labels("/r0/pose", "speed_mps")._value.get() == 1
    monitor.check_admission("m", "/evil")


async def test_an_alerting_stream_is_logged_once_a_second_and_counted_every_time(tmp_path, caplog):
    clock = Clock()
    monitor, _ = monitor_for(tmp_path, action="log", clock=clock)
    evil = monitor.watch(manager="m", publisher="/evil", topic="/r0/pose", typename=POSE, cut=lambda: None)
    x = 0.0
    for i in range(80):  # three jumps, one calm message: an alert every four messages, 5 per second
        clock.t = 1000 + i / 20
        x = x if i % 4 == 3 else 100.0 - x
        evil.feed(frame(pose(x, 0.0, clock.t)))
        await drain()
    alerts = monitor.metrics.alerts.labels("/r0/pose", "speed_mps")._value.get()
    lines = [r for r in caplog.records if "MONITOR alert" in r.getMessage()]
    # 100 m in 0.05 s is severe: each run of jumps alerts at its first (the very first message has no step)
    assert alerts == 20 and len(lines) == 4, (alerts, len(lines))


async def test_a_stream_it_cannot_follow_is_let_through_unless_fail_closed(tmp_path):
    for fail_closed in (False, True):
        monitor, _ = monitor_for(tmp_path, max_backlog_bytes=1000, fail_closed=fail_closed)
        cuts: list[str] = []
        big = monitor.watch(manager="m", publisher="/p", topic="/t", typename="std_msgs/String",
                            cut=lambda: cuts.append("cut"))
        big.feed(b"\x00" * 2000)  # more than the backlog before the loop scored anything
        assert big.closed and cuts == (["cut"] if fail_closed else [])
        # one frame larger than the backlog, arriving slowly: its partial body counts too
        slow = monitor.watch(manager="m", publisher="/p", topic="/u", typename=POSE, cut=lambda: cuts.append("slow"))
        cuts.clear()
        slow.feed(struct.pack("<I", 5000) + b"x" * 500)
        await drain()
        assert not slow.closed
        for _ in range(3):
            slow.feed(b"x" * 300)
            await drain()
        assert slow.closed and cuts == (["slow"] if fail_closed else [])
        assert monitor.metrics.given_up.labels("backlog")._value.get() == 2


def test_unwatched_topics_and_the_stream_cap(tmp_path):
    monitor, _ = monitor_for(tmp_path, topics=("/r*/pose",), max_streams=1)
    assert monitor.watch(manager="m", publisher="/p", topic="/chatter", typename=POSE, cut=lambda: None) is None
    assert monitor.watch(manager="m", publisher="/p", topic="/r0/pose", typename=POSE, cut=lambda: None) is not None
    assert monitor.watch(manager="m", publisher="/q", topic="/r1/pose", typename=POSE, cut=lambda: None) is None


# ------------------------------------------------------------------ configuration


def test_monitor_settings_are_checked_at_start(tmp_path):
    from interceptor.config import _parse_monitor

    fitted().save(tmp_path / "m.json")
    s = _parse_monitor({"model": "m.json", "action": "quarantine", "topics": ["/team/*"]}, tmp_path)
    assert s.action == "quarantine" and s.watches("/team/map") and not s.watches("/r0/pose")
    with pytest.raises(ConfigError, match="model is required"):
        _parse_monitor({}, tmp_path)
    with pytest.raises(ConfigError, match="action"):
        _parse_monitor({"model": "m.json", "action": "shoot"}, tmp_path)
    with pytest.raises(ConfigError, match="not found"):
        _parse_monitor({"model": "nope.json"}, tmp_path)
    with pytest.raises(ConfigError, match="topics"):
        _parse_monitor({"model": "m.json", "topics": ["chatter"]}, tmp_path)
    gated = _parse_monitor({"model": "m.json", "topics": ["/r0/*"], "gate": ["/team/map"]}, tmp_path)
    assert gated.gates("/team/map") and gated.watches("/team/map") and not gated.gates("/r0/pose")
    for bad in (["map"], "/team/map", [1]):
        with pytest.raises(ConfigError, match="gate"):
            _parse_monitor({"model": "m.json", "gate": bad}, tmp_path)


async def test_reconfigure_scores_open_streams_with_the_new_model_and_keeps_quarantines(tmp_path):
    clock = Clock()
    monitor, _ = monitor_for(tmp_path, clock=clock)
    monitor.register("m", "/evil", lambda: None)
    stream = monitor.watch(manager="m", publisher="/p", topic="/r0/pose", typename=POSE, cut=lambda: None)
    monitor._alert(stream, "speed_mps", 9.0)  # quarantined under the old model
    strict = MonitorModel(limits={"pose": {"speed_mps": 0.0001}}, consecutive=1)
    monitor.reconfigure(MonitorSettings(model=tmp_path / "m.json", action="log", batch_seconds=0.0), strict)
    assert stream.alerts.needed == 1 and monitor.settings.action == "log"
    with pytest.raises(PolicyDenied):
        monitor.check_admission("m", "/p")  # a quarantine outlives a reload
    for i in range(2):
        clock.t = 1000 + i / 20
        stream.feed(frame(pose(0.01 * i, 0.0, clock.t)))
        await drain()
    assert monitor.metrics.alerts.labels("/r0/pose", "speed_mps")._value.get() == 2  # the old one and a new one


async def test_a_backlog_is_scored_in_turns_that_hand_the_loop_back(tmp_path):
    from interceptor.monitor import MESSAGES_PER_TURN

    monitor, _ = monitor_for(tmp_path, action="log")
    stream = monitor.watch(manager="m", publisher="/p", topic="/t", typename="std_msgs/String", cut=lambda: None)
    for i in range(3 * MESSAGES_PER_TURN):
        stream.feed(frame(b"\x04\x00\x00\x00abcd"))
    counted = monitor.metrics.messages.labels("/t")
    await asyncio.sleep(0)  # one turn of the loop: one share of the backlog
    assert counted._value.get() == MESSAGES_PER_TURN
    await drain()
    assert counted._value.get() == 3 * MESSAGES_PER_TURN


async def test_what_the_streams_queue_within_batch_seconds_is_scored_in_one_pass(tmp_path):
    """The default: chunks wait up to ``batch_seconds`` and every stream's are scored in
    one pass (one timer, one busy measurement), not one wake-up per chunk."""
    clock = Clock()
    monitor, _ = monitor_for(tmp_path, action="log", clock=clock, batch_seconds=0.2)
    streams = [monitor.watch(manager="m", publisher=f"/p{i}", topic=f"/r{i}/pose", typename=POSE, cut=lambda: None)
               for i in range(3)]
    loop = asyncio.get_running_loop()
    fed_at = loop.time()
    for k in range(4):
        for stream in streams:
            stream.feed(frame(pose(0.01 * k, 0.0, clock.t)))
    await drain()
    counted = [monitor.metrics.messages.labels(f"/r{i}/pose") for i in range(3)]
    assert [c._value.get() for c in counted] == [0, 0, 0]  # waiting for the batch
    assert monitor._batch is not None and len(monitor._due) == 3  # one timer for the three streams
    deadline = fed_at + 5
    while any(c._value.get() < 4 for c in counted):
        assert loop.time() < deadline, [c._value.get() for c in counted]
        await asyncio.sleep(0.02)
    assert loop.time() - fed_at >= 0.2 * 0.9  # not before its time (the loop's clock rounds)
    assert [c._value.get() for c in counted] == [4, 4, 4] and monitor._batch is None and not monitor._due
    assert monitor.metrics.busy._value.get() > 0


async def test_a_stream_that_queues_a_burst_has_the_batch_scored_at_once(tmp_path):
    """A flood does not wait out batch_seconds: the stream's BATCH_EARLY_CHUNKS-th chunk
    has every due stream scored on the loop's next turn."""
    from interceptor.monitor import BATCH_EARLY_CHUNKS

    clock = Clock()
    monitor, _ = monitor_for(tmp_path, action="log", clock=clock, batch_seconds=1.0)
    quiet = monitor.watch(manager="m", publisher="/q", topic="/r1/pose", typename=POSE, cut=lambda: None)
    flood = monitor.watch(manager="m", publisher="/f", topic="/r0/pose", typename=POSE, cut=lambda: None)
    quiet.feed(frame(pose(0.0, 0.0, clock.t)))
    for k in range(BATCH_EARLY_CHUNKS - 1):
        flood.feed(frame(pose(0.01 * k, 0.0, clock.t)))
    await drain()
    counted = monitor.metrics.messages
    assert counted.labels("/r0/pose")._value.get() == 0  # still waiting for the timer
    flood.feed(frame(pose(0.1, 0.0, clock.t)))
    await drain()  # the next turn of the loop, not a second later
    assert counted.labels("/r0/pose")._value.get() == BATCH_EARLY_CHUNKS
    assert counted.labels("/r1/pose")._value.get() == 1  # the quiet stream went in the same batch
    assert monitor._batch is None and not monitor._due


def test_batch_seconds_is_checked_at_start(tmp_path):
    from interceptor.config import _parse_monitor

    fitted().save(tmp_path / "m.json")
    assert _parse_monitor({"model": "m.json"}, tmp_path).batch_seconds == 0.25
    assert _parse_monitor({"model": "m.json", "batch_seconds": 0}, tmp_path).batch_seconds == 0.0
    for bad in (-0.1, 2.0, "0.1", True, float("nan")):
        with pytest.raises(ConfigError, match="batch_seconds"):
            _parse_monitor({"model": "m.json", "batch_seconds": bad}, tmp_path)


# ------------------------------------------------------------------ the demo's compromised robot


def test_a_compromised_robot_changes_what_it_publishes_from_its_onset_on():
    from cryptoros.demo.compromise import DRIFT_M_PER_S, REPLAY_DELAY_S, Compromise

    spoof = Compromise("spoof-pose", onset=100.0, seed=1, arena_m=(12.0, 12.0))
    assert spoof.pose(1.0, 2.0, 99.0) == (1.0, 2.0, 99.0)  # before the onset: the truth
    x, y, t = spoof.pose(1.0, 2.0, 100.5)
    assert (x, y) != (1.0, 2.0) and 0 <= x <= 12 and 0 <= y <= 12 and t == 100.5
    drift = Compromise("drift", onset=100.0, seed=1, arena_m=(12.0, 12.0))
    assert drift.pose(1.0, 2.0, 110.0) == pytest.approx((1.0 + 10 * DRIFT_M_PER_S, 2.0, 110.0))
    replay = Compromise("replay", onset=100.0, seed=1, arena_m=(12.0, 12.0))
    for i in range(200):  # 20 Hz for 10 s, moving 0.01 m per message
        out = replay.pose(0.01 * i, 0.0, 95.0 + i / 20)
    assert out[2] == pytest.approx(95.0 + 199 / 20 - REPLAY_DELAY_S, abs=0.06) and out[0] < 0.01 * 199
    noise = Compromise("scan-noise", onset=0.0, seed=1, arena_m=(12.0, 12.0))
    ranges = np.full(72, 2.0, dtype=np.float32)
    noisy = noise.ranges(ranges, 0.12, 3.5)
    assert noisy.shape == ranges.shape and noisy.std() > 0.5 and noisy.min() >= 0.12 and noisy.max() <= 3.5
    with pytest.raises(ValueError, match="unknown compromise"):
        Compromise("teleport", onset=0.0, seed=1, arena_m=(1.0, 1.0))


def test_a_manager_whose_publishers_keep_getting_quarantined_is_quarantined_whole(tmp_path):
    """A compromised robot granted a node pattern (/pose_*) renames its node after each
    quarantine: at the third, every publisher of that manager is cut and refused."""
    clock = Clock()
    monitor, denials = monitor_for(tmp_path, clock=clock)
    cuts: list[str] = []
    monitor.register("robot_a", "/honest", lambda: cuts.append("robot_a /honest"))
    monitor.register("robot_c", "/other", lambda: cuts.append("robot_c /other"))
    for name in ("/pose_1", "/pose_2"):
        stream = monitor.watch(manager="robot_a", publisher=name, topic="/r0/pose", typename=POSE, cut=lambda: None)
        monitor._alert(stream, "speed_mps", 50.0)
        clock.t += 1
    monitor.check_admission("robot_a", "/honest")  # two: still per publisher
    assert cuts == []
    stream = monitor.watch(manager="robot_a", publisher="/pose_3", topic="/r0/pose", typename=POSE, cut=lambda: None)
    monitor._alert(stream, "speed_mps", 50.0)
    assert cuts == ["robot_a /honest"]  # the third: the whole manager, and nothing of robot_c
    for name in ("/honest", "/pose_4"):
        with pytest.raises(PolicyDenied, match="quarantined"):
            monitor.check_admission("robot_a", name)
    monitor.check_admission("robot_c", "/other")
    assert ("monitor", "quarantined", "every publisher of robot_a") in denials
    shown = monitor.status()
    assert shown["action"] == "quarantine" and {q["publisher"] for q in shown["quarantined"]} == \
        {"/pose_1", "/pose_2", "/pose_3", "*"}
    from interceptor.status import render

    lines = render({"manager": "robot_b", "roles": ["node"], "public": "127.0.0.3:1", "health": "ok", "token": None,
                    "certificate": {"serial": "1", "not_after": "2030-01-01T00:00:00", "days_left": 1.0},
                    "feed": {"age": 0.1, "revoked_tokens": 0, "disabled_managers": []}, "crl": None, "peers": {},
                    "open_streams": 0, "monitor": shown})
    assert any(line.startswith("monitor   quarantine") and "/pose_3 of robot_a" in line for line in lines), lines
    clock.t += 31
    monitor.check_admission("robot_a", "/pose_5")  # over after quarantine_seconds


# ------------------------------------------------------------------ across streams, team packets

HELLO, MAP = "cryptoros_sim/Hello", "cryptoros_sim/MapUpdate"


def beacon(source: str, x: float, y: float, t: float) -> bytes:
    from cryptoros.sim import packets as P

    return P.encode(P.make(HELLO, source=source, seq=1, timestamp=t, position=P.Point(x, y), residual_energy=1.0,
                           buffer_free=1.0, state=0), HELLO)


def team_map(x: float, y: float, origin: tuple[int, int], cells: np.ndarray, *, count: int | None = None) -> bytes:
    from cryptoros.sim import packets as P

    h, w = cells.shape
    body = P.encode(P.make(MAP, source="r0", seq=1, timestamp=0.0, position=P.Point(x, y), goal=P.Point(x, y),
                           exploration_complete=False, origin_x=origin[0], origin_y=origin[1], width=w, height=h,
                           data=cells.reshape(-1).astype(np.int8)), MAP)
    if count is not None:  # a length field that lies about the cells
        body = body[:-(h * w) - 4] + struct.pack("<I", count) + body[-(h * w):]
    return body


def drive(crosscheck, *, drift_from: float | None, seconds: float = 10.0, robot: str = "r0",
          beacons_to=None, honest_too: list | None = None) -> list[tuple[float, float]]:
    """A robot at 0.3 m/s: its pose stream (drifting by 0.1 m/s from ``drift_from``) and its
    beacons (8 a second, the truth, into ``beacons_to`` or the same cross-check); returns
    (t, beacon_gap_m) per pose. ``honest_too``: a second, honest pose stream of the robot
    runs beside, its gaps appended there."""
    poses = StreamFeatures(POSE, topic=f"/{robot}/pose", crosscheck=crosscheck)
    honest = StreamFeatures(POSE, topic=f"/{robot}/pose", crosscheck=crosscheck)
    hello = StreamFeatures(HELLO, topic="/team/hello", crosscheck=beacons_to or crosscheck)
    out = []
    for i in range(int(seconds * 40)):  # 40 ticks a second: a pose every other, a beacon every fifth
        t = 1000.0 + i / 40
        truth = 0.3 * (t - 1000.0)
        if i % 5 == 0:
            hello.observe(beacon(robot, truth, 1.0, t), t, t)
        if i % 2 == 0:
            x = truth + (0.1 * (t - 1000.0 - drift_from) if drift_from is not None and t - 1000.0 >= drift_from else 0.0)
            out.append((t - 1000.0, named("pose", poses.observe(pose(x, 1.0, t), t, t))["beacon_gap_m"]))
            if honest_too is not None:
                honest_too.append(named("pose", honest.observe(pose(truth, 1.0, t), t, t))["beacon_gap_m"])
    return out


def test_a_pose_drifting_away_from_the_robots_own_beacons_shows_a_growing_gap():
    from cryptoros.monitor.features import Crosscheck

    clean = drive(Crosscheck(), drift_from=None)
    assert max(g for _, g in clean) <= 0.1  # a beacon is matched with the pose nearest in time
    beside: list[float] = []
    drifting = drive(Crosscheck(), drift_from=4.0, honest_too=beside)
    assert max(g for t, g in drifting if t < 4.0) <= 0.1
    assert max(beside) <= 0.1  # the robot's honest pose stream beside the drifting one is not blamed
    late = [g for t, g in drifting if t >= 9.0]
    assert min(late) > 0.45  # 0.1 m/s for 5 s, less the 0.4 s of poses a beacon is matched against
    # another manager's beacons (another trust domain) say nothing about this robot's pose
    elsewhere = drive(Crosscheck(), drift_from=4.0, beacons_to=Crosscheck())
    assert max(g for _, g in elsewhere) == 0.0
    # beacons of another robot name are not this robot's reference
    other = Crosscheck()
    drive(other, drift_from=None, robot="r1")
    assert named("pose", StreamFeatures(POSE, topic="/r0/pose", crosscheck=other).observe(
        pose(50.0, 50.0, 1010.0), 1010.0, 1010.0))["beacon_gap_m"] == 0.0


def test_a_team_map_claiming_cells_its_sender_cannot_have_seen():
    f = StreamFeatures(MAP, topic="/team/map")
    assert f.kind == "team_map"
    unseen = []
    for i in range(10):  # honest: cells within 3 m (15 cells) of a robot driving along y = 5 m
        x = 2.0 + 0.5 * i
        col = int(x / 0.2)
        patch = np.zeros((30, 30), dtype=np.int8)
        patch[:5] = 100  # a wall
        unseen.append(named("team_map", f.observe(team_map(x, 5.0, (col - 15, 10), patch), 1000.0 + i, 1000.0 + i)))
    assert all(u["unseen_claim"] == 0.0 and u["walls_erased"] == 0.0 and u["malformed"] == 0.0 for u in unseen)
    false = named("team_map", f.observe(team_map(0.0, 0.0, (0, 0), np.zeros((100, 100), np.int8)), 1010.5, 1010.5))
    assert false["unseen_claim"] > 0.5  # a 20 m x 20 m map "explored" from a path along 2..7 m
    assert false["walls_erased"] == 1.0  # and the wall it reported before is now free
    honest = named("team_map", f.observe(team_map(7.0, 5.0, (20, 10), np.zeros((30, 30), np.int8)), 1011.0, 1011.0))
    assert honest["unseen_claim"] == false["unseen_claim"]  # held: the honest update between false ones stays flagged
    later = named("team_map", f.observe(team_map(7.0, 5.0, (20, 10), np.zeros((30, 30), np.int8)), 1016.0, 1016.0))
    assert later["unseen_claim"] == 0.0
    # a liar that had seen the whole arena still erases walls: an update that frees a seen wall
    near = StreamFeatures(MAP, topic="/team/map")
    walled = np.zeros((30, 30), np.int8)
    walled[:, 0] = 100
    assert named("team_map", near.observe(team_map(3.0, 3.0, (0, 0), walled), 1000.0, 1000.0))["walls_erased"] == 0.0
    erasing = named("team_map", near.observe(team_map(3.0, 3.0, (0, 0), np.zeros((30, 30), np.int8)), 1001.0, 1001.0))
    assert erasing["unseen_claim"] == 0.0 and erasing["walls_erased"] == 1.0
    bad = named("team_map", f.observe(team_map(7.0, 5.0, (20, 10), np.zeros((30, 30), np.int8), count=10**6),
                                      1017.0, 1017.0))
    assert bad["malformed"] == 1.0
    # the team types are ROS 1's own: in the ROS 2 role they are any type
    from cryptoros.monitor.features import kind_of
    assert kind_of(MAP, "cdr") == "any" and kind_of(HELLO) == "beacon"


async def test_the_monitor_checks_a_pose_against_the_robots_own_beacons_only(tmp_path):
    """A motion-capture bridge on an operations host (manager ``ops``) publishes robot r0's
    pose into r0's host; r0's own explorer sends its beacons out through the same
    interceptor (a reference stream: read, never scored). Robot r1 claiming to be r0 in its
    beacons changes nothing: a beacon counts only from the manager of its robot's name."""
    clock = Clock()
    monitor, denials = monitor_for(tmp_path, clock=clock)
    cuts: list[str] = []
    mocap = monitor.watch(manager="ops", publisher="/mocap", topic="/r0/pose", typename=POSE,
                          cut=lambda: cuts.append("mocap"))
    framing = monitor.watch(manager="r1", publisher="/r1", topic="/team/hello", typename=HELLO,
                            cut=lambda: cuts.append("r1"))
    own = monitor.watch_reference(manager="r0", publisher="/r0", topic="/team/hello", typename=HELLO)
    assert monitor.watch_reference(manager="r0", publisher="/r0", topic="/team/map", typename=MAP) is None
    # the same beacons on their way to a second peer are not read twice
    assert monitor.watch_reference(manager="r0", publisher="/r0", topic="/team/hello", typename=HELLO) is None
    monitor.register("ops", "/mocap", lambda: cuts.append("mocap"))
    clock.t = 999.0
    own.feed(frame(beacon("r0", 0.0, 1.0, clock.t)))
    await drain()
    assert not own.features._arrivals  # no pose of r0 followed yet: its own beacons are not read
    for i in range(40):
        clock.t = 1000 + i / 20
        framing.feed(frame(beacon("r0", 40.0, 40.0, clock.t)))  # robot r1 says r0 is elsewhere
        mocap.feed(frame(pose(0.3 * i / 20, 1.0, clock.t)))
        await drain()
    assert cuts == [] and denials == []  # another robot cannot frame r0's pose
    for i in range(40, 80):
        clock.t = 1000 + i / 20
        own.feed(frame(beacon("r0", 0.3 * i / 20 - 3.0, 1.0, clock.t)))  # r0 itself is 3 m from the bridge's pose
        await drain()
        mocap.feed(frame(pose(0.3 * i / 20, 1.0, clock.t)))
        await drain()
    assert cuts == ["mocap"] and denials == [("monitor", "quarantined", "/mocap (ops)")]
    assert monitor.metrics.alerts.labels("/r0/pose", "beacon_gap_m")._value.get() == 1
    assert monitor.metrics.alerts.labels("/team/hello", "rate_hz")._value.get() == 0  # the reference is not scored
    own.close()  # its stream to that peer ends: the next one to another peer is read
    assert monitor.watch_reference(manager="r0", publisher="/r0", topic="/team/hello", typename=HELLO) is not None


async def test_a_batch_scores_the_streams_in_arrival_order_so_beacons_meet_the_poses_around_them(tmp_path):
    """Two seconds of a bridge's poses and of r0's own beacons, 3 m apart, queued before
    one batch is scored: scored stream after stream, every beacon would come after every
    pose (no pose around it: no gap, no alert); scored in arrival order, the gap is seen."""
    clock = Clock()
    monitor, denials = monitor_for(tmp_path, clock=clock)
    cuts: list[str] = []
    mocap = monitor.watch(manager="ops", publisher="/mocap", topic="/r0/pose", typename=POSE,
                          cut=lambda: cuts.append("mocap"))
    own = monitor.watch_reference(manager="r0", publisher="/r0", topic="/team/hello", typename=HELLO)
    monitor.register("ops", "/mocap", lambda: cuts.append("mocap"))
    mocap.feed(frame(pose(0.0, 1.0, clock.t)))  # r0's pose is followed: its own beacons are read
    await drain()
    for i in range(1, 40):
        clock.t = 1000 + i / 20
        mocap.feed(frame(pose(0.3 * i / 20, 1.0, clock.t)))
        clock.t += 0.01
        own.feed(frame(beacon("r0", 0.3 * i / 20 - 3.0, 1.0, clock.t)))
    await drain()
    assert cuts == ["mocap"] and denials == [("monitor", "quarantined", "/mocap (ops)")]
    assert monitor.metrics.alerts.labels("/r0/pose", "beacon_gap_m")._value.get() == 1


async def test_a_gated_topic_drops_a_false_claim_before_it_is_forwarded_and_quarantines_its_sender(tmp_path):
    """The team map is gated: each update is scored as it arrives. An honest one goes on; the
    first false "explored" claim is dropped (it is severe: its sender is quarantined at once)."""
    clock = Clock()
    honest = [team_map(2.0 + 0.5 * i, 5.0, (int((2.0 + 0.5 * i) / 0.2) - 15, 10), np.zeros((30, 30), np.int8))
              for i in range(6)]
    clean = StreamFeatures(MAP, topic="/team/map")
    model = MonitorModel.fit({"team_map": [clean.observe(body, 1000.0 + i, 1000.0 + i) for i, body in enumerate(honest)],
                              "pose": [row("pose", rate_hz=1.0, speed_mps=0.3)]})
    model.save(tmp_path / "m.json")
    from prometheus_client import CollectorRegistry

    denials: list = []
    monitor = Monitor(MonitorSettings(model=tmp_path / "m.json", action="quarantine", gate=("/team/map",)),
                      CollectorRegistry(), deny=lambda k, e, w: denials.append((k, e.reason, w)), clock=clock, wall=clock)
    cuts: list[str] = []
    stream = monitor.watch(manager="r1", publisher="/r1", topic="/team/map", typename=MAP, cut=lambda: cuts.append("r1"))
    monitor.register("r1", "/r1", lambda: cuts.append("r1"))
    passed = []
    for i, body in enumerate(honest):
        clock.t = 1000.0 + i
        passed.append(stream.gate(body))
    assert passed == [True] * 6 and cuts == []
    clock.t += 0.5
    assert stream.gate(team_map(0.0, 0.0, (0, 0), np.zeros((100, 100), np.int8))) is False
    assert cuts == ["r1"] and denials == [("monitor", "quarantined", "/r1 (r1)")]
    assert monitor.metrics.dropped.labels("/team/map")._value.get() == 1
    stream.close()  # what the cut does to the stream in the relay
    assert stream.gate(honest[0]) is False  # a cut stream lets nothing more through


@pytest.mark.parametrize("numpy_from", [None, 0])
def test_the_team_map_features_match_a_cell_by_cell_count(numpy_from, monkeypatch):
    """The grids are integers (a byte a place); the features they give are the shares
    counted cell by cell: known cells out of reach of every reported position, and walls
    claimed before that an update calls free, over a robot's honest updates (a growing
    patch around its path) mixed with random patches, a false claim and an erasure. The
    same with every patch checked as a big one (numpy arrays, ``numpy_from=0``)."""
    from cryptoros.monitor import features as F

    if numpy_from is not None:
        monkeypatch.setattr(F, "NUMPY_FROM_CELLS", numpy_from)
    rng = np.random.default_rng(7)
    f = StreamFeatures(MAP, topic="/team/map")
    visited: set[tuple[int, int]] = set()
    walls: set[tuple[int, int]] = set()
    claims: list[tuple[float, float, float]] = []
    radius, k = F._REACH_RADIUS, F._CELLS_PER_PLACE
    x, y = 3.0, 3.0
    for i in range(120):
        t = 1000.0 + 0.7 * i
        x, y = min(max(x + rng.uniform(-0.8, 1.0), 0.5), 30.0), min(max(y + rng.uniform(-0.8, 1.0), 0.5), 30.0)
        if i % 7 == 3:  # anywhere, any size
            origin = (int(rng.integers(-40, 160)), int(rng.integers(-40, 160)))
            shape = (int(rng.integers(1, 70)), int(rng.integers(1, 70)))
        else:  # the honest robot: a patch around where it is
            origin = (int(x / 0.2) - 20, int(y / 0.2) - 18)
            shape = (40 + i % 5, 36 + i % 3)
        cells = rng.choice(np.array([-1, 0, 100], np.int8), size=shape, p=[0.4, 0.45, 0.15])
        if i in (60, 90):  # a false "explored" claim; an update that frees every wall it saw
            origin, cells = (0, 0), np.zeros((150, 150), np.int8)
        got = named("team_map", f.observe(team_map(x, y, origin, cells), t, t))
        visited.add((math.floor(y), math.floor(x)))
        known = out_of_reach = before = erased = 0
        for (r, c), v in np.ndenumerate(cells):
            row, col = origin[1] + r, origin[0] + c
            if v != -1:
                known += 1
                place = (row // k, col // k)
                out_of_reach += not any((place[0] - a) ** 2 + (place[1] - b) ** 2 <= radius ** 2 for a, b in visited)
            if (row, col) in walls:
                before += 1
                erased += v == 0
        walls |= {(origin[1] + r, origin[0] + c) for (r, c), v in np.ndenumerate(cells) if v > 0}
        claims = [c for c in claims if c[0] >= t - F.CLAIM_HOLD_S] + [(t, out_of_reach / known if known else 0.0,
                                                                     erased / before if before else 0.0)]
        assert got["unseen_claim"] == pytest.approx(max(c[1] for c in claims), abs=1e-12), i
        assert got["walls_erased"] == pytest.approx(max(c[2] for c in claims), abs=1e-12), i
        if i in (60, 90):  # both features are exercised, not only zeros
            assert got["unseen_claim"] > 0.4 and (i == 60 or got["walls_erased"] > 0.5), (i, got)


def test_a_team_map_stream_keeps_bounded_grids_whatever_it_claims():
    """What a team-map stream remembers (places in reach, walls) grows with what it
    reports, never past its bounds: a claim far away or huge costs no memory."""
    from cryptoros.monitor import features as F

    f = StreamFeatures(MAP, topic="/team/map")
    walled = np.full((40, 40), 100, np.int8)
    f.observe(team_map(3.0, 3.0, (0, 0), walled), 1000.0, 1000.0)
    for i in range(1, 51):  # walls claimed all over a 400 km line: only what fits the bound is kept
        far = named("team_map", f.observe(team_map(3.0, 3.0, (i * 20_000, 0), walled), 1001.0 + i, 1001.0 + i))
        assert far["unseen_claim"] == 1.0  # nobody at (3, 3) saw cells 4 km away
    assert f._walls.size <= F.MAX_WALL_CELLS and f._reach.size <= F.MAX_REACH_CELLS
    for i in range(200):  # positions reported all over: the places in reach stay bounded too
        f.observe(team_map(i * 1000.0, 0.0, (0, 0), np.zeros((1, 1), np.int8)), 1100.0 + i, 1100.0 + i)
    assert f._reach.size <= F.MAX_REACH_CELLS and len(f._visited) <= F.MAX_VISITED
    huge = named("team_map", f.observe(team_map(3.0, 3.0, (0, 0), np.zeros((2100, 2100), np.int8)), 1400.0, 1400.0))
    assert huge["malformed"] == 1.0  # too many cells to check: malformed, not checked at a cost
    far_off = named("team_map", f.observe(team_map(3.0, 3.0, (2 ** 21, 0), walled), 1401.0, 1401.0))
    assert far_off["malformed"] == 1.0


async def test_a_gated_message_has_the_queued_batch_scored_right_after_it(tmp_path):
    """A gate's scoring is followed by the batch on the loop's next turn (the monitor's
    code is still warm), not by a wake-up of its own after batch_seconds."""
    clock = Clock()
    monitor, _ = monitor_for(tmp_path, action="log", clock=clock, batch_seconds=1.0, gate=("/r9/pose",))
    queued = monitor.watch(manager="m", publisher="/q", topic="/r1/pose", typename=POSE, cut=lambda: None)
    gated = monitor.watch(manager="m", publisher="/g", topic="/r9/pose", typename=POSE, cut=lambda: None)
    queued.feed(frame(pose(0.0, 0.0, clock.t)))
    await drain()
    counted = monitor.metrics.messages
    assert counted.labels("/r1/pose")._value.get() == 0 and monitor._due  # waiting for its timer (1 s)
    assert gated.gate(pose(0.0, 0.0, clock.t))
    assert counted.labels("/r9/pose")._value.get() == 1 and counted.labels("/r1/pose")._value.get() == 0
    await drain()  # the next turn of the loop, not a second later
    assert counted.labels("/r1/pose")._value.get() == 1
    assert monitor._batch is None and not monitor._due


@pytest.mark.parametrize("content", [bytes(range(200, 256)) * 8, b"#ROSBAG V2.0\n" + b"\x07" * 300, b""])
def test_a_file_that_is_no_bag_is_one_line_naming_it(tmp_path, content):
    """Operator audit: ``cryptoros monitor train`` of a file of random bytes ended in a
    UnicodeDecodeError traceback from rosbags."""
    from cryptoros.errors import ConfigError
    from cryptoros.monitor.dataset import train

    bag = tmp_path / "g.bag"
    bag.write_bytes(content)
    with pytest.raises(ConfigError, match=f"cannot read bag {bag}: not a readable ROS 1 bag") as info:
        train([bag])
    assert "\n" not in str(info.value)


def test_status_while_learning_says_a_peer_that_is_not_learning_still_refuses():
    """ROS 2 audit: robot C's status said a call was let through while robot A, not
    learning, refused it."""
    from interceptor.status import render

    lines = render({"manager": "robot_c", "roles": ["ros2"], "public": "127.0.0.4:1", "health": "ok", "token": None,
                    "certificate": {"serial": "1", "not_after": "2030-01-01T00:00:00", "days_left": 1.0},
                    "feed": {"age": 0.1, "revoked_tokens": 0, "disabled_managers": []}, "crl": None, "peers": {},
                    "open_streams": 0, "learning": {"left": 563, "learned": 1}})
    assert lines[1].startswith("LEARNING  563 s left: 1 requests no grant covers let through here and recorded, "
                               "each still refused by a peer that is not learning"), lines
