"""`cryptoros attack` against a real rospy robot (Debian ROS 1), unprotected then behind
interceptors: the victim node itself reports what reached it.

Unprotected, every attacker talks to rosmaster directly and the victim sees the spoofed
pose, the noise scans, the flood of stop commands and the shutdown. Protected, the
victim runs behind robot_a's interceptor; the attackers are a node on robot_c (an
insider whose manager has no grant for the victim's topics) and a stranger without a
certificate talking to the master interceptor's public port: the victim sees none of it.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cryptoros.lab.policy import policy_yaml
from tests.interceptor_harness import SYS_PY, robot_network, separate_hosts
from tests.support import on_host, require, running

pytestmark = pytest.mark.timeout(300)

VICTIM = str(Path(__file__).parents[1] / "attack_nodes" / "victim.py")
CRYPTOROS = str(Path(sys.executable).parent / "cryptoros")

VICTIM_TOPICS = [("/victim", "/victim/pose", "geometry_msgs/PoseStamped"),
                 ("/victim", "/victim/scan", "sensor_msgs/LaserScan"),
                 ("/victim", "/victim/cmd_vel", "geometry_msgs/Twist")]
POLICY = policy_yaml({
    "master": {},
    "robot_a": {"publish": [*VICTIM_TOPICS, ("/victim", "/rosout", "rosgraph_msgs/Log")], "subscribe": VICTIM_TOPICS},
    "robot_b": {},
    "robot_c": {},
})


@pytest.fixture(scope="module")
def network(tmp_path_factory):
    require("rosmaster")
    with robot_network(tmp_path_factory.mktemp("net"), policy=POLICY, start=("master", "robot_a", "robot_c"),
                       netns=separate_hosts()) as net:
        yield net


def attack(env: dict[str, str], *args: str, timeout: float = 60) -> tuple[str, dict]:
    out = Path(env["ROS_HOME"]) / f"attack-{time.monotonic_ns()}.json"
    r = subprocess.run(on_host([CRYPTOROS, "attack", *args, "--json", str(out)], env), env=env, capture_output=True,
                       text=True, timeout=timeout)
    assert r.returncode == 0, r.stderr
    return r.stdout, json.loads(out.read_text())


def victim_run(victim_env: dict[str, str], attacks: list[tuple[dict[str, str], list[str]]], seconds: float = 240,
               *, shut_down_expected: bool = False):
    """Start the victim, run the attacks one after the other, then close the victim's
    stdin (it ends there: however slow a cold machine starts each attack, every attack
    meets a running victim); return its output lines. With ``shut_down_expected`` the
    victim is first given time (bounded) to end by itself: rospy runs its shutdown after
    the call has been answered, so closing stdin at once could end it first."""
    with running([SYS_PY, VICTIM, str(seconds), "--until-stdin-closes"], env=victim_env,
                 stdin=subprocess.PIPE) as victim:
        first = victim.stdout.readline()
        assert first.strip() == "READY", first
        time.sleep(1.0)
        reports = [attack(env, *args) for env, args in attacks]
        deadline = time.monotonic() + 20
        while shut_down_expected and victim.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        out, _ = victim.communicate(timeout=60)
    return [first, *out.splitlines()], reports


def shut_down(lines: list[str]) -> bool:
    """A shutdown before the victim's own end (rospy also reports its atexit): the
    victim's pre-shutdown hook, or rospy's own "shutdown request:" line (the hook can
    lose the race with the victim's end; rospy logs the request when it receives it)."""
    end = lines.index("END") if "END" in lines else len(lines)
    return any(x.startswith(("SHUTDOWN", "shutdown request:")) and "atexit" not in x for x in lines[:end])


def counts(lines: list[str]) -> dict[str, int]:
    line = next((x for x in lines if x.startswith("COUNTS")), None)
    assert line is not None, "the victim printed no COUNTS:\n" + "\n".join(lines)
    return {k: int(v) for k, v in (p.split("=") for p in line.split()[1:])}


def attacks_for(env_insider: dict[str, str], env_stranger: dict[str, str]) -> list[tuple[dict[str, str], list[str]]]:
    return [
        (env_insider, ["spoof-publish", "/victim/pose", "geometry_msgs/PoseStamped", "--random", "--rate", "200",
                       "--seconds", "2", "--name", "/vicon_bridge"]),
        (env_stranger, ["manipulate", "/victim/scan", "sensor_msgs/LaserScan", "--noise", "--scale", "3.5",
                        "--seconds", "2"]),
        (env_insider, ["flood", "/victim/cmd_vel", "geometry_msgs/Twist", "--rate", "2000", "--seconds", "2"]),
        (env_stranger, ["shutdown", "/victim"]),
    ]


def test_unprotected_victim_sees_spoof_noise_flood_and_shutdown(network):
    env = network.ros_env(None)
    lines, reports = victim_run(env, attacks_for(env, env), shut_down_expected=True)
    c = counts(lines)
    assert c["pose"] > 0, lines
    assert c["scan"] > 0, lines
    assert c["cmd"] > 0, lines
    assert shut_down(lines), lines
    spoof, noise, flood, shut = (r for _, r in reports)
    assert spoof["sent"] > 100 and spoof["subscribers_max"] >= 1
    assert noise["read"] > 0 and noise["republished"] > 0
    assert flood["sent"] > 1000
    assert shut.get("sent") is True and not shut.get("refused")  # rospy exits while answering


def test_protected_victim_sees_none_of_them(network):
    victim_env = network.ros_env("robot_a")
    insider = network.ros_env("robot_c")
    stranger = network.ros_env(None)
    master = network.hosts["master"]
    stranger["ROS_MASTER_URI"] = f"http://{master.address}:{master.public_port}/"
    lines, reports = victim_run(victim_env, attacks_for(insider, stranger))
    assert counts(lines) == {"pose": 0, "scan": 0, "cmd": 0}, lines
    assert not shut_down(lines), lines
    for _, rep in reports:
        assert rep.get("refused"), rep
        assert not rep.get("accepted")
        assert rep.get("sent", 0) == 0 or rep.get("subscribers_max", 0) == 0
    assert "denied" in network.hosts["robot_c"].logs() or "not_granted" in network.hosts["robot_c"].logs()


def test_eavesdrop_records_a_rosbag_unprotected_and_nothing_protected(network, tmp_path):
    from rosbags.rosbag1 import Reader

    bag = tmp_path / "plain.bag"
    env = network.ros_env(None)
    with running([SYS_PY, VICTIM, "8"], env=network.ros_env(None)) as victim:
        assert victim.stdout.readline().strip() == "READY"
        time.sleep(1.0)
        text, rep = attack(env, "eavesdrop", "--seconds", "2", "--bag", str(bag))
        victim.communicate(timeout=40)
    assert rep["messages"] > 0 and "/victim/pose" in rep["topics"], text
    with Reader(bag) as reader:
        topics = {c.topic for c in reader.connections}
        n = sum(1 for _ in reader.messages())
    assert "/victim/scan" in topics and n == rep["messages"]

    stranger = network.ros_env(None)
    master = network.hosts["master"]
    stranger["ROS_MASTER_URI"] = f"http://{master.address}:{master.public_port}/"
    with running([SYS_PY, VICTIM, "6"], env=network.ros_env("robot_a")) as victim:
        assert victim.stdout.readline().strip() == "READY"
        _, rep = attack(stranger, "eavesdrop", "--seconds", "2", "--bag", str(tmp_path / "protected.bag"))
        _, rep_insider = attack(network.ros_env("robot_c"), "eavesdrop", "--seconds", "2", "--bag",
                                str(tmp_path / "insider.bag"))
        victim.communicate(timeout=40)
    assert rep["messages"] == 0 and rep.get("refused")
    assert rep_insider["messages"] == 0, rep_insider


def test_hijack_name_unprotected_takes_the_name_protected_is_refused(network):
    env = network.ros_env(None)
    with running([SYS_PY, VICTIM, "8"], env=env) as victim:
        assert victim.stdout.readline().strip() == "READY"
        _, rep = attack(env, "hijack-name", "/victim", "--seconds", "1")
        out, _ = victim.communicate(timeout=40)
    assert rep["name_taken"] is True
    assert shut_down(out.splitlines()) and "same name" in out
    with running([SYS_PY, VICTIM, "8"], env=network.ros_env("robot_a")) as victim:
        assert victim.stdout.readline().strip() == "READY"
        time.sleep(0.5)
        _, rep = attack(network.ros_env("robot_c"), "hijack-name", "/victim", "--seconds", "1")
        out, _ = victim.communicate(timeout=40)
    assert not rep.get("name_taken") and rep.get("refused")
    assert not shut_down(out.splitlines())
