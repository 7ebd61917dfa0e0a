"""`cryptoros demo --ros 2`: the demo's mission with the robots as real rclpy nodes.

Plain: all robots and attackers on one DDS domain. Protected: each robot on its own
localhost-only domain behind its own interceptor (``ros2`` role). Asserts on the JSON
the demo writes: every attack succeeds in plain mode and is blocked in protected mode
(judged from the victims' side), the protected mission reaches its coverage target,
the robots really were on separate domains, the interceptors' logs name what they
refused, and nothing outlives the demo.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from tests.ros2_support import ros2_python
from cryptoros.demo.session import free_after
from tests.support import processes_using

REPO = Path(__file__).resolve().parents[2]
CLI = Path(os.environ.get("VIRTUAL_ENV", REPO / ".venv")) / "bin" / "cryptoros"
pytestmark = [pytest.mark.timeout(420), pytest.mark.slow]


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("ROS_", "_ROS_WHEELS", "RMW_")) and k != "PYTHONPATH"}
    env.update(CRYPTOROS_ROS2_PYTHON=str(ros2_python()), PYTHONUNBUFFERED="1")
    return env


def _cryptoros() -> str:
    return str(CLI) if CLI.exists() else "cryptoros"


def test_ros2_demo_plain_attacks_succeed_protected_blocked_and_mission_completes(tmp_path):
    out = tmp_path / "out.json"
    r = subprocess.run([_cryptoros(), "demo", "--ros", "2", "--seconds", "45", "--json", str(out),
                        "--out", str(tmp_path / "report")],
                       cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=360)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "ROS 2 Jazzy" in r.stdout
    result = json.loads(out.read_text())
    assert result["config"]["ros"] == 2
    assert set(result["attacks"]) == {"spoof-pose", "scan-noise", "cmd-flood", "false-map", "eavesdrop"}
    for name, a in result["attacks"].items():
        assert a["plain"]["succeeded"] is True, (name, a["plain"]["evidence"])
        assert a["protected"]["succeeded"] is False, (name, a["protected"]["evidence"])
    plain, protected = result["modes"]["plain"], result["modes"]["protected"]
    # one shared domain in plain mode; a domain per robot (none of them the network's) when protected
    assert len(set(plain["domains"].values())) == 1
    robot_domains = [d for k, d in protected["domains"].items() if k != "network"]
    assert len(set(robot_domains)) == result["config"]["robots"]
    assert protected["domains"]["network"] not in robot_domains
    assert protected["target_reached"] is True, protected["coverage"]
    assert plain["coverage"] < protected["coverage"]
    # the team's traffic really crossed the interceptors, and the strangers met only TLS
    assert protected["messages"]["rx"] > 100 and protected["interceptors"]["bytes_relayed"] > 10_000
    assert protected["denials"].get("peer_did_not_return_a_certificate", 0) >= 1
    refused = [e for lines in protected["deny_log"].values() for e in lines]
    assert any("/vicon_bridge may not publish /r0/pose" in e for e in refused), refused
    # a robot's own /rN/* topics are [ros2] local: kept on its domain, not logged as denials
    assert not any("/r0_base may not publish" in e or "/r1 may not publish /r1/" in e for e in refused), refused
    assert protected["denials"].get("not_granted") == 1, protected["denials"]
    eaves = protected["attack_reports"]["eavesdrop"]
    assert eaves["positions_read"] == {} and eaves["map_cells_read"] == 0
    assert all(d["outcome"] != "accepted" for d in eaves["doors"])
    report = Path(result["report"])
    assert "ROS 2 Jazzy" in report.read_text() and (report.parent / "coverage_maps.png").exists()
    assert result["leftover_children"] == [] and result["ports_still_open"] == []
    assert processes_using(Path(result["workdir"])) == []
    assert free_after([p for m in result["modes"].values() for p in m["ports"]]) == []
    assert not Path(result["workdir"]).exists()


@pytest.mark.parametrize("args, message", [
    (["--attacks", "shutdown"], "no ROS 2 counterpart"),
    (["--master-uri", "http://127.0.0.1:11311"], "ROS 2 has no master"),
])
def test_ros2_demo_refuses_what_ros2_does_not_have(tmp_path, args, message):
    r = subprocess.run([_cryptoros(), "demo", "--ros", "2", *args], cwd=tmp_path, env=_env(), capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2 and message in r.stderr, r.stderr
