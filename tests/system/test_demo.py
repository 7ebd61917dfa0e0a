"""`cryptoros demo` as a new user runs it: a fresh venv, the package installed from the
repository, no ROS anywhere on PATH or in the environment.

Asserts on the JSON it writes: in plain mode every attack succeeded (judged from what
the victims received), in protected mode every attack was blocked and the mission
still reached its coverage target; no child process and no port outlives the demo,
including when it is interrupted with Ctrl-C (SIGINT).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cryptoros.demo.session import free_after
from tests.support import processes_using

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.timeout(420)


@pytest.fixture(scope="session")  # one per test worker, however the tests are scheduled
def venv(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("fresh") / "venv"
    # The suite's pip installs into a venv without a pip of its own, and compiles nothing:
    # the demo's processes compile what they import, once (_no_ros_env lets them write the
    # .pyc). A venv with its own pip, every installed module compiled, took 38 s of CPU on
    # the loaded two-core machine, measured; this takes about 10.
    subprocess.run(["python3", "-m", "venv", "--without-pip", str(root)],
                   check=True, timeout=120, env=_no_ros_env(None))
    r = subprocess.run([sys.executable, "-m", "pip", "--python", str(root / "bin" / "python"), "install", "-q",
                        "--disable-pip-version-check", "--no-compile", str(REPO)],
                       capture_output=True, text=True, timeout=300, env=_no_ros_env(None))
    assert r.returncode == 0, r.stderr[-3000:]
    return root


def _no_ros_env(venv: Path | None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("ROS") and k not in ("PYTHONPATH", "CMAKE_PREFIX_PATH", "LD_LIBRARY_PATH", "VIRTUAL_ENV",
                                                    "PYTHONDONTWRITEBYTECODE")}
    env["PATH"] = f"{venv}/bin" if venv else "/usr/local/bin:/usr/bin:/bin"
    env["PYTHONUNBUFFERED"] = "1"
    return env


CLASSIC = {"spoof-pose", "scan-noise", "cmd-flood", "false-map", "map-erase", "eavesdrop", "shutdown", "hijack"}
HELD = {"held-spoof-pose", "held-replay", "held-drift", "held-scan-noise", "held-cmd-flood", "held-false-map"}


def test_demo_plain_attacks_succeed_protected_blocked_and_mission_completes(venv, tmp_path):
    """The README's demo: plain ROS, the interceptors, the interceptors with the runtime
    monitor (its model trained on a clean calibration mission first). Strangers and
    insiders without a grant are blocked by the interceptors; attackers misusing a grant
    they hold pass the interceptors (honestly: they hold it) and the monitor cuts them."""
    out = tmp_path / "out.json"
    # A generous budget: a mission ends as soon as its target is reached (about 12 s on
    # a quiet machine), but the robots run in wall time and a loaded CI machine is slower.
    r = subprocess.run([str(venv / "bin" / "cryptoros"), "demo", "--seconds", "45", "--json", str(out),
                        "--out", str(tmp_path / "report")],
                       cwd=tmp_path, env=_no_ros_env(venv), capture_output=True, text=True, timeout=400)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "Report:" in r.stdout and "plain ROS" in r.stdout and "cryptoros + monitor" in r.stdout
    result = json.loads(out.read_text())
    assert set(result["attacks"]) == CLASSIC | HELD
    assert Path(result["calibration"]["model"]).name == "monitor-model.json"
    for name in CLASSIC:
        a = result["attacks"][name]
        r0 = result["modes"]["plain"]["robots"]["r0"]
        if name == "cmd-flood" and r0["state"] == "done" and r0["stats"]["cmd_foreign_stop"] > 0:
            # Plain ROS runs every attack in one mission: a robot the others already made stop
            # exploring (the false map) has no motion for a stop to halt, and the judge goes
            # by effect. The flood reached it and was obeyed (`--isolate`: a mission per attack).
            assert "foreign stop commands" in a["plain"]["evidence"], a["plain"]["evidence"]
        else:
            assert a["plain"]["succeeded"] is True, (name, a["plain"]["evidence"])
        assert a["protected"]["succeeded"] is False, (name, a["protected"]["evidence"])
        assert a["monitored"]["succeeded"] is False, (name, a["monitored"]["evidence"])
        assert a["protected_attacker"].startswith(("stranger", "insider"))
    for name in HELD - {"held-false-map"}:  # (the false map needs robots free to stop: plain ROS's are halted or dead)
        a = result["attacks"][name]
        assert a["plain"]["succeeded"] is True, (name, a["plain"]["evidence"])
        assert a["protected"]["succeeded"] is True, (name, a["protected"]["evidence"])
    for name in ("held-spoof-pose", "held-replay", "held-scan-noise", "held-cmd-flood"):
        a = result["attacks"][name]
        assert a["monitored"]["succeeded"] is False, (name, a["monitored"]["evidence"])
    assert result["attacks"]["held-false-map"]["protected"]["succeeded"] is True
    # the team map is gated: the first false claim is dropped before any robot believes it
    false_map = result["attacks"]["held-false-map"]["monitored"]
    assert false_map["succeeded"] is False, false_map["evidence"]
    assert result["modes"]["monitored"]["monitor"]["dropped"] >= 1
    drift = result["attacks"]["held-drift"]["monitored"]  # against r0's beacons, or cut with its manager's other nodes
    assert drift["succeeded"] is False or drift.get("cut_after_s") is not None, drift["evidence"]
    monitored = result["modes"]["monitored"]
    assert monitored["monitor"]["quarantines"] >= 1 and monitored["denials"].get("quarantined", 0) >= 1
    flood = result["attacks"]["held-cmd-flood"]["monitored"]  # cut within 2 s, or none of it reached the robot
    assert flood.get("cut_after_s", 0.0) < 2.0, flood["evidence"]
    assert result["modes"]["plain"]["coverage"] < min(result["modes"][m]["coverage"] for m in ("protected", "monitored"))
    for mode in ("protected", "monitored"):
        assert result["modes"][mode]["denials"], f"the interceptors counted no denial ({mode})"
        assert result["modes"][mode]["interceptors"]["cpu_s_total"] > 0
    report = Path(result["report"])
    assert report.exists() and (report.parent / "coverage_over_time.png").exists()
    assert (report.parent / "coverage_maps.png").exists()
    assert "cryptoros + monitor" in report.read_text()
    # hygiene: nothing left running, every port free, the throwaway work directory gone
    assert result["leftover_children"] == [] and result["ports_still_open"] == []
    assert processes_using(venv) == []
    assert free_after([p for m in result["modes"].values() for p in m["ports"]]) == []
    assert not Path(result["workdir"]).exists()


def test_the_strangers_attacks_fail_while_every_robot_learns(tmp_path):
    """`cryptoros demo --learn`: every robot's manager in learning mode for the whole
    protected mission (each interceptor said LEARNING before it started); learning widens
    grants only, so the stranger (no certificate) still reaches nothing."""
    from tests.support import script

    out = tmp_path / "out.json"
    stranger = ("scan-noise", "cmd-flood", "false-map", "eavesdrop")
    r = subprocess.run([script("cryptoros"), "demo", "--mode", "protected", "--learn", "--seconds", "30",
                        "--attacks", ",".join(stranger), "--json", str(out), "--out", str(tmp_path / "report")],
                       cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    result = json.loads(out.read_text())
    assert result["modes"]["protected"]["learning"] == ["r0", "r1", "r2"]
    for name in stranger:
        a = result["attacks"][name]
        assert a["protected_attacker"].startswith("stranger"), a
        assert a["protected"]["succeeded"] is False, (name, a["protected"]["evidence"])
    assert result["modes"]["protected"]["coverage"] > 0


def test_demo_isolate_runs_each_attack_in_its_own_missions(tmp_path):
    """`--isolate`: a mission per attack and mode, so that effects do not mix; each
    attack is judged from its own mission."""
    from tests.support import script

    out = tmp_path / "out.json"
    r = subprocess.run([script("cryptoros"), "demo", "--mode", "plain", "--isolate", "--seconds", "6",
                        "--attacks", "held-cmd-flood,shutdown", "--json", str(out), "--keep",
                        "--workdir", str(tmp_path / "work"), "--out", str(tmp_path / "report")],
                       cwd=tmp_path, capture_output=True, text=True, timeout=200)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    result = json.loads(out.read_text())
    assert set(result["isolated"]) == {"held-cmd-flood", "shutdown"} and result["modes"] == {}
    for name in ("held-cmd-flood", "shutdown"):
        assert (tmp_path / "work" / name / "plain" / "r0.status.json").exists()
        assert result["attacks"][name]["plain"]["succeeded"] is True, result["attacks"][name]
        assert 0 < result["attacks"][name]["plain"]["coverage"] <= 1
    # the flood halted r0 in its own mission; the shutdown's mission had no flood
    assert result["isolated"]["shutdown"]["plain"]["robots"]["r0"]["halted_s"] == 0
    assert result["isolated"]["held-cmd-flood"]["plain"]["robots"]["r0"]["halted_s"] > 1
    assert "held-cmd-flood" in (tmp_path / "report" / "report.md").read_text()


def test_demo_monitor_stays_quiet_on_a_clean_mission(tmp_path):
    """Trained on its calibration mission, the monitor watches a whole clean mission (every
    topic, the team map gated) without one alert or one dropped message, and says what it
    cost."""
    from tests.support import script

    out = tmp_path / "out.json"
    r = subprocess.run([script("cryptoros"), "demo", "--mode", "monitored", "--attacks", "none", "--seconds", "15",
                        "--json", str(out), "--out", str(tmp_path / "report")],
                       cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    monitored = json.loads(out.read_text())["modes"]["monitored"]
    assert monitored["monitor"]["alerts"] == 0 and monitored["monitor"]["quarantines"] == 0, monitored["monitor"]
    assert monitored["monitor"]["dropped"] == 0 and monitored["denials"] == {}
    assert monitored["coverage"] > 0.3
    assert 0 < monitored["monitor"]["busy_s"] < monitored["interceptors"]["cpu_s_total"]
    assert "monitor's share of interceptor CPU" in r.stdout


def test_demo_ctrl_c_stops_every_child(venv, tmp_path):
    """Ctrl-C stops every child; the throwaway work directory (the demo's PKI with its
    private keys, the registry, the logs) goes too (newcomer audit: it stayed in /tmp)."""
    # --scale 1: the mission needs minutes of wall time, so it is surely still running when
    # interrupted (at the default scale it can reach its target before the SIGINT lands)
    tmp = tmp_path / "tmp"  # where the demo makes its work directory (TMPDIR)
    tmp.mkdir()
    proc = subprocess.Popen([str(venv / "bin" / "cryptoros"), "demo", "--mode", "protected", "--seconds", "60",
                             "--scale", "1"], cwd=tmp_path, env={**_no_ros_env(venv), "TMPDIR": str(tmp)},
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:  # interrupt once robots run behind the interceptors
            if list(tmp.glob("cryptoros-demo-*/protected/r*.status.json")):
                break
            time.sleep(0.2)
        # its children are up (authz, master, interceptors, robots): seen, not slept for
        while len(children := [p for p in processes_using(venv) if not p.startswith(f"{proc.pid}:")]) < 5:
            assert time.monotonic() < deadline, children
            time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        try:
            out, _ = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate(timeout=10)
            raise AssertionError("the demo did not exit within 60 s of SIGINT:\n" + out[-3000:]) from None
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, out[-2000:]
    deadline = time.monotonic() + 10
    while processes_using(venv) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert processes_using(venv) == []
    assert list(tmp.glob("cryptoros-demo-*")) == [], out[-2000:]


def test_demo_netns_runs_the_protected_mission_on_separate_hosts(tmp_path):
    """`cryptoros demo --netns`: the master, every robot and the stranger each in its own
    network namespace: the mission reaches its target, every attack fails."""
    from tests.interceptor_harness import separate_hosts
    from tests.support import script

    separate_hosts()
    out = tmp_path / "out.json"
    r = subprocess.run([script("cryptoros"), "demo", "--netns", "--mode", "protected", "--seconds", "45",
                        "--attacks", "spoof-pose,eavesdrop,shutdown,hijack", "--json", str(out),
                        "--out", str(tmp_path / "report")], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    result = json.loads(out.read_text())
    assert result["config"]["netns"] is True
    protected = result["modes"]["protected"]
    assert protected["target_reached"] is True, protected["coverage"]
    for name, verdict in protected["judged"].items():
        assert verdict["succeeded"] is False, (name, verdict["evidence"])
    assert result["leftover_children"] == []
