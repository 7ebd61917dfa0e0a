"""The runtime monitor with real ROS 1 nodes: a model trained on a clean recording made
with Debian's ``rosbag record``, then robot B's interceptor with ``[monitor] action =
"quarantine"`` while robot A's nodes publish through it. Every publisher here holds a
grant for ``/r0/pose`` (``/pose_*``): authorization lets all of them in; the monitor
tells the misbehaving ones apart by what they send."""

from __future__ import annotations

import json
import signal
import time
import urllib.request
from pathlib import Path

import pytest

from tests.interceptor_harness import DEFAULT_POLICY, NODE, SYS_PY, got, read_lines, robot_network
from tests.support import run, running, script

pytestmark = [pytest.mark.ros1, pytest.mark.timeout(240)]

POSE_NODE = str(Path(NODE).parent / "pose.py")
POLICY = DEFAULT_POLICY.replace(
    "    - {{node: /talker_a, topic: /secret, type: std_msgs/String}}\n",
    "    - {{node: /talker_a, topic: /secret, type: std_msgs/String}}\n"
    "    - {{node: '/pose_*', topic: /r0/pose, type: geometry_msgs/PoseStamped}}\n",
).replace(
    "    subscribe:\n    - {{node: /victim, topic: /chatter, type: std_msgs/String}}\n",
    "    subscribe:\n    - {{node: /victim, topic: /chatter, type: std_msgs/String}}\n"
    "    - {{node: /monitor_recorder, topic: /r0/pose, type: geometry_msgs/PoseStamped}}\n",
    1,  # robot A's list (robot B's comes second)
).replace(
    "    - {{node: '*', topic: /chatter, type: std_msgs/String}}\n",
    "    - {{node: '*', topic: /chatter, type: std_msgs/String}}\n"
    "    - {{node: '*', topic: /r0/pose, type: geometry_msgs/PoseStamped}}\n",
)


def pose_pub(net, node: str, kind: str, hz: float, seconds: float):
    return running([SYS_PY, POSE_NODE, "pub", node, kind, str(hz), str(seconds)], env=net.ros_env("robot_a"))


def lines_until(proc, done, timeout: float, what: str) -> list[str]:
    """A process's output lines until ``done(lines)`` holds: a count waited for, bounded
    by ``timeout`` (AssertionError naming ``what``), never counted in a fixed window."""
    seen: list[str] = []
    deadline = time.monotonic() + timeout
    while not done(seen):
        left = deadline - time.monotonic()
        assert left > 0 and proc.poll() is None, f"{what}: not within {timeout} s; last lines {seen[-5:]}"
        seen += read_lines(proc, None, min(left, 0.5))
    return seen


def lines_with(text: str, count: int):
    """``done`` for :func:`lines_until`: ``count`` lines contain ``text``."""
    return lambda lines: sum(text in line for line in lines) >= count


def clean_after_attacks(lines: list[str]) -> bool:
    """15 clean poses arrived after the last one of an attacker (it was cut, not the stream)."""
    last = max((i for i, line in enumerate(lines) if "GOT /pose_spoof" in line or "GOT /pose_flood" in line),
               default=-1)
    return sum("GOT /pose_clean" in line for line in lines[last + 1:]) >= 15


def metrics(net, host: str) -> str:
    url = f"http://127.0.0.1:{net.hosts[host].metrics_port}/metrics"
    return urllib.request.urlopen(url, timeout=5).read().decode()


def test_a_model_trained_on_a_clean_recording_quarantines_only_the_misbehaving_publishers(tmp_path):
    with robot_network(tmp_path / "net", policy=POLICY) as net:
        # 1. A clean recording, made on robot B through the interceptors.
        bag = tmp_path / "clean.bag"
        with pose_pub(net, "/pose_clean", "clean", 20, 9) as pub:
            read_lines(pub, "READY", 20)
            recorded = run([script("cryptoros"), "monitor", "record", "--topic", "/r0/pose", "--seconds", "6",
                            "-o", str(bag)], env=net.ros_env("robot_b"), timeout=60)
            read_lines(pub, "SENT", 40)
        assert recorded.returncode == 0, recorded.stderr
        assert "/pose_clean on /r0/pose" in recorded.stdout, recorded.stdout

        # 2. The model. Margin 3: the suite's machine is shared and slower than a robot.
        model = tmp_path / "model.json"
        trained = run([script("cryptoros"), "monitor", "train", str(bag), "-o", str(model), "--margin", "3"],
                      timeout=60)
        assert trained.returncode == 0, trained.stderr
        assert "pose" in trained.stdout and model.exists()
        clean_eval = run([script("cryptoros"), "monitor", "eval", str(bag), "--model", str(model), "--json"],
                         timeout=60)
        assert clean_eval.returncode == 0, clean_eval.stderr
        assert '"false_positive_rate": 0.0' in clean_eval.stdout, clean_eval.stdout

        # 3. Robot B's interceptor with the monitor.
        net.stop("robot_b")
        config = net.hosts["robot_b"].config
        config.write_text(f'state_dir = "{tmp_path / "state_b"}"\n' + config.read_text() +
                          f'\n[monitor]\nmodel = "{model}"\ntopics = ["/r0/pose"]\n'
                          'action = "quarantine"\nquarantine_seconds = 120.0\n')
        net.start("robot_b")

        # 4. Live: a clean pose publisher and a chatter stream, then a spoofer and a flooder,
        # all granted.
        with running([SYS_PY, POSE_NODE, "sub", "/pose_listener", "60"], env=net.ros_env("robot_b")) as listener, \
                running([SYS_PY, NODE, "sub", "/listener_b", "/chatter", "60"], env=net.ros_env("robot_b")) as chat:
            read_lines(listener, "READY", 20)
            read_lines(chat, "READY", 20)
            with pose_pub(net, "/pose_clean", "clean", 20, 40), \
                    running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "100000", "20"], env=net.ros_env("robot_a")):
                before = lines_until(listener, lines_with("GOT /pose_clean", 20), 60, "20 clean poses")
                # robot A records what its publishers send, attacks included (local: no monitor there)
                attacked = tmp_path / "attacked.bag"
                with running([script("cryptoros"), "monitor", "record", "--topic", "/r0/pose", "--seconds", "9",
                              "-o", str(attacked)], env=net.ros_env("robot_a")) as recorder:
                    read_lines(recorder, "recording", 20)
                    with pose_pub(net, "/pose_spoof", "spoof", 20, 3) as spoof:
                        read_lines(spoof, "SENT", 30)
                    with pose_pub(net, "/pose_flood", "flood", 300, 2) as flood:
                        read_lines(flood, "SENT", 30)
                    # only the offenders are cut: the clean poses flow on after the attacks
                    after = lines_until(listener, clean_after_attacks, 60, "15 clean poses after the attacks")
                    assert "bag:" in read_lines(recorder, "bag:", 20)[-1]
                # and so does the chatter stream
                lines_until(chat, lambda lines: len(got(lines)) >= 10, 60, "10 chatter messages")
                status_url = f"http://127.0.0.1:{net.hosts['robot_b'].metrics_port}/status"
                shown = json.loads(urllib.request.urlopen(status_url, timeout=5).read())
                watched = shown["peers"]
            log = net.hosts["robot_b"].logs()
            counted = metrics(net, "robot_b")
        # robot B's interceptor restarted (a crash, an operator): the quarantines stand
        net.stop("robot_b")
        net.start("robot_b")
        restarted = json.loads(urllib.request.urlopen(status_url, timeout=5).read())
        assert {q["publisher"] for q in restarted["monitor"]["quarantined"]} == {"/pose_spoof", "/pose_flood"}
        assert "MONITOR quarantines kept across the restart" in net.hosts["robot_b"].logs()
        # an operator lifts one of them (a false alert, say) without a restart
        lifted = run([script("cryptoros"), "unquarantine", "--config", str(net.hosts["robot_b"].config),
                      "robot_a", "/pose_flood"], timeout=30)
        assert lifted.returncode == 0 and "lifted: /pose_flood of robot_a" in lifted.stdout, lifted
        after_release = json.loads(urllib.request.urlopen(status_url, timeout=5).read())
        assert {q["publisher"] for q in after_release["monitor"]["quarantined"]} == {"/pose_spoof"}
        assert "MONITOR quarantines lifted by the operator: /pose_flood (robot_a)" in net.hosts["robot_b"].logs()
        again = run([script("cryptoros"), "unquarantine", "--config", str(net.hosts["robot_b"].config),
                     "robot_a", "/pose_flood"], timeout=30)
        assert again.returncode == 0 and "nothing to lift" in again.stdout, again

    # the same attacks, recorded on robot A and scored offline as the interceptor scores them
    scored = run([script("cryptoros"), "monitor", "eval", str(attacked), "--model", str(model), "--attacker",
                  "/pose_spoof", "--attacker", "/pose_flood", "--json"], timeout=60)
    assert scored.returncode == 0, scored.stderr
    figures = json.loads(scored.stdout)
    assert figures["attack_streams_detected"] == "2 of 2", figures
    # an --attacker has no onset: its delay counts from its stream's first message
    assert all(0.0 <= d < 2.0 for d in figures["delays_s"].values()), figures
    assert figures["false_positive_rate"] <= 0.005 and figures["clean_streams_alerted"] == [], figures
    alerts = [line for line in log.splitlines() if "MONITOR alert" in line]
    print("\n".join(["monitor live:", clean_eval.stdout, scored.stdout, *alerts,
                      f"spoofed poses the listener got: {sum('GOT /pose_spoof' in x for x in before + after)}",
                      f"flood poses the listener got: {sum('GOT /pose_flood' in x for x in before + after)}",
                      f"robot B watches: {watched}",
                      *[line for line in counted.splitlines() if "quarantined" in line]]))
    assert any("/pose_spoof" in a and "speed_mps" in a for a in alerts), alerts
    assert any("/pose_flood" in a and ("rate_hz" in a or "burst_hz" in a) for a in alerts), alerts
    assert not any("/pose_clean" in a for a in alerts), alerts  # quiet on clean traffic
    # the offenders were cut soon after their first messages: of the 60 spoofed poses,
    # the listener saw a handful (the alert needs three in a row, plus what was in flight)
    spoofed = sum("GOT /pose_spoof" in line for line in before + after)
    assert spoofed < 30, spoofed
    assert "DENY monitor from /pose_spoof (robot_a)" in log  # reported like a denial
    assert 'cryptoros_interceptor_denied_total{kind="monitor",reason="quarantined"} 2.0' in counted, counted
    assert 'cryptoros_monitor_alerts_total{feature="speed_mps",topic="/r0/pose"}' in counted
    assert 'cryptoros_interceptor_denied_total{kind="relay",reason="quarantined"}' in counted  # reconnections refused
    # refused reconnections leave nothing behind: robot B watches robot A's open streams only
    # (the clean pose stream and the chatter stream; a refused one is not watched)
    assert watched.get("robot_a") == 2, watched
    # cryptoros status shows who is in quarantine, and for how long
    assert {q["publisher"] for q in shown["monitor"]["quarantined"]} == {"/pose_spoof", "/pose_flood"}, shown
    assert "cryptoros_monitor_score_seconds_count" in counted


# ------------------------------------------------------------------ ROS 2: the ros2 role's monitor


def wait_for_line(log: Path, text: str, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while text not in log.read_text():
        assert time.monotonic() < deadline, f"no {text!r} in {log} within {timeout} s"
        time.sleep(0.1)


@pytest.mark.slow
def test_the_ros2_role_quarantines_a_flooded_topic_stream_and_keeps_the_others(tmp_path):
    """Robot A's rclpy talker holds the grants for /chatter and /twist; robot B's
    interceptor (role ros2, [monitor] on /chatter, action quarantine) cuts robot A's
    /chatter stream once it floods, and only that stream. In ROS 2 the receiver sees one
    stream per topic from each peer (the sender's bridge merges its publishers), so a
    quarantine names the peer's manager and the stream's node. The model is written
    out here (a rate limit of 40 Hz): this test is about the role, not the fitting."""
    from cryptoros.monitor.model import MonitorModel
    from tests.ros2_support import collect, got, ros2_network

    model = tmp_path / "model.json"
    MonitorModel(limits={"any": {"rate_hz": 40.0, "size_change": 10.0, "malformed": 0.5}}).save(model)
    monitor = (f'[monitor]\nmodel = "{model}"\ntopics = ["/chatter"]\naction = "quarantine"\n'
               'quarantine_seconds = 120.0\n')
    with ros2_network(tmp_path / "net", start=("robot_a", "robot_b"), extra={"robot_b": monitor}) as net:
        with net.node("robot_b", "listener.py", "string", "/chatter", "60") as chatter, \
                net.node("robot_b", "listener.py", "twist", "/twist", "60") as twist:
            chatter.until("READY", 30)
            twist.until("READY", 30)
            with net.node("robot_a", "talker.py", "twist", "/twist", "100000", "10"):
                collect(twist, 5, 40)
                with net.node("robot_a", "talker.py", "string", "/chatter", "100000", "10"):
                    collect(chatter, 10, 40)  # at 10 Hz: watched, no alert
                    assert "MONITOR alert" not in net.robots["robot_b"].log.read_text()
                with net.node("robot_a", "talker.py", "string", "/chatter", "100000", "400", "--offset", "1000"):
                    deadline = time.monotonic() + 30
                    while "MONITOR alert" not in net.robots["robot_b"].log.read_text():
                        assert time.monotonic() < deadline, "no alert within 30 s of the flood"
                        time.sleep(0.2)
                    chatter.until(None, 1.5)  # what was in flight at the cut
                    assert got(chatter.until(None, 3.0)) == []  # the flooded stream is cut and refused
                    assert len(got(collect(twist, 10, 20))) >= 10  # robot A's other stream flows on
            log = net.robots["robot_b"].log.read_text()
            counted = net.metrics("robot_b")
            # SIGHUP with a model that does not load keeps the old state; a good one is taken
            robot_b = net.robots["robot_b"]
            model.write_text("{not json")
            robot_b.proc.send_signal(signal.SIGHUP)
            wait_for_line(robot_b.log, "reload failed, keeping the old state")
            MonitorModel(limits={"any": {"rate_hz": 80.0}}, consecutive=5).save(model)
            robot_b.proc.send_signal(signal.SIGHUP)
            wait_for_line(robot_b.log, "and the monitor's model")
            assert robot_b.proc.poll() is None
    alerts = [line for line in log.splitlines() if "MONITOR alert" in line]
    assert len(alerts) == 1 and "(robot_a) on /chatter" in alerts[0] and "rate_hz" in alerts[0], alerts
    assert 'cryptoros_interceptor_denied_total{kind="monitor",reason="quarantined"} 1.0' in counted
    assert 'cryptoros_interceptor_denied_total{kind="ros2",reason="quarantined"}' in counted  # reconnections


@pytest.mark.slow
def test_the_ros2_role_gates_a_topic_each_suspicious_sample_dropped_before_it_is_republished(tmp_path):
    """Robot B's interceptor (role ros2) gates /twist: each of robot A's samples is scored
    before robot B's domain sees it. The talkers' twists carry linear.x = seq + offset; the
    model allows |linear.x| up to 50,000. Robot A's honest talker (offset 0) and a
    compromised one (offset 100,000; both named /talker, the name the grant gives) publish
    on /twist: robot A's bridge merges them into one stream, and robot B's listener gets
    the honest samples and not one of the others (each dropped and counted), while the
    stream stays up (action "log")."""
    from cryptoros.monitor.model import MonitorModel
    from tests.ros2_support import collect, got, ros2_network

    model = tmp_path / "model.json"
    MonitorModel(limits={"twist": {"rate_hz": 1000.0, "size_change": 10.0, "malformed": 0.5, "linear": 50_000.0,
                                   "angular": 1e9}}).save(model)
    monitor = f'[monitor]\nmodel = "{model}"\ntopics = ["/none"]\ngate = ["/twist"]\naction = "log"\n'
    with ros2_network(tmp_path / "net", start=("robot_a", "robot_b"), extra={"robot_b": monitor}) as net:
        with net.node("robot_b", "listener.py", "twist", "/twist", "60") as twist:
            twist.until("READY", 30)
            with net.node("robot_a", "talker.py", "twist", "/twist", "100000", "10"):
                received = got(collect(twist, 3, 40))  # the path is up
                with net.node("robot_a", "talker.py", "twist", "/twist", "100000", "10",
                              "--offset", "100000"):
                    deadline = time.monotonic() + 30
                    while True:  # until the gate has dropped 10 of the compromised talker's samples
                        counted = net.metrics("robot_b")
                        dropped = [float(line.rsplit(" ", 1)[1]) for line in counted.splitlines()
                                   if line.startswith('cryptoros_monitor_dropped_total{topic="/twist"}')]
                        if dropped and dropped[0] >= 10:
                            break
                        assert time.monotonic() < deadline, f"the gate dropped {dropped} within 30 s"
                        received += got(twist.until(None, 0.5))
                    received += got(collect(twist, 5, 20))  # the honest talker's go on
    assert len(received) >= 8 and all(seq < 100_000 for seq in received), received
    assert received == sorted(received)  # the honest ones in order


@pytest.mark.slow
def test_ros2_traffic_is_recorded_per_publisher_node_and_trains_a_model_that_flags_a_flood(tmp_path):
    """`cryptoros monitor record --ros 2`: unmodified rclpy talkers on a robot's domain,
    recorded by an rclpy node of the ROS 2 venv into a ROS 1 bag (one connection per
    publisher node, samples converted to the ROS 1 serialization): a clean recording
    trains a model, and in a second recording the node that floods is flagged, the other
    not."""
    from rosbags.rosbag1 import Reader

    from cryptoros.ros1 import msgs
    from tests.ros2_support import NODES, fresh_domains, ros2_env, ros2_python

    python = ros2_python()
    domain = fresh_domains(1)[0]
    env = {**ros2_env(domain), "CRYPTOROS_ROS2_PYTHON": str(python)}
    cryptoros = script("cryptoros")

    def talker(*args: str):
        return running([str(python), str(NODES / "talker.py"), *args], env=ros2_env(domain), cwd=str(NODES))

    def record(out: Path) -> str:
        r = run([cryptoros, "monitor", "record", "--ros", "2", "--topic", "/r0/cmd_vel", "--topic", "/r0/scan",
                 "--seconds", "4", "-o", str(out)], env=env, timeout=90)
        assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
        return r.stdout

    clean, flooded = tmp_path / "clean.bag", tmp_path / "flooded.bag"
    with talker("scan", "/r0/scan", "100000", "5", "--node", "base"), \
            talker("twist", "/r0/cmd_vel", "100000", "20", "--node", "teleop"):
        out = record(clean)
    assert "/teleop on /r0/cmd_vel" in out and "/base on /r0/scan" in out, out
    with Reader(clean) as bag:
        streams = {(c.topic, c.ext.callerid, c.msgtype) for c in bag.connections}
        assert streams == {("/r0/cmd_vel", "/teleop", "geometry_msgs/msg/Twist"),
                           ("/r0/scan", "/base", "sensor_msgs/msg/LaserScan")}, streams
        twists = [msgs.deserialize(raw, "geometry_msgs/Twist") for c, _t, raw in bag.messages()
                  if c.topic == "/r0/cmd_vel"]
    assert len(twists) >= 40  # 20 Hz for 4 s, in the ROS 1 serialization
    model = tmp_path / "model.json"
    r = run([cryptoros, "monitor", "train", str(clean), "-o", str(model)], timeout=60)
    assert r.returncode == 0 and "twist" in r.stdout and "scan" in r.stdout, r.stdout + r.stderr
    with talker("scan", "/r0/scan", "100000", "5", "--node", "base"), \
            talker("twist", "/r0/cmd_vel", "100000", "300", "--node", "teleop"):
        record(flooded)
    r = run([cryptoros, "monitor", "eval", str(flooded), "--model", str(model), "--attacker", "/teleop", "--json"],
            timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
    figures = json.loads(r.stdout)
    assert figures["recall"] > 0.5 and figures["false_positive_rate"] == 0, figures  # /base's scans: never flagged
    assert figures["clean_streams_alerted"] == [], figures
