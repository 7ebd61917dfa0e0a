"""docs/runbook.md Part 5, a fleet of ROS 2 robots, executed on separate hosts.

Part 1's master-host blocks (``master-pki``, ``master-registry``, ``master-authz``) and
then every block of Part 5 (its steps start with ``ros2-``) run as written, in order,
on network-namespace hosts (:mod:`tests.runbook_support`): a master host, robot A with a
talker, robot B with a listener, and a stranger. After each block the effect of its
step is checked: messages flow from robot A's talker to robot B's listener through the
interceptors, stop when robot B's grant is removed and resume when it is given back,
resume after robot B's interceptor restarts, and stop when robot A's certificate is
revoked. The stranger finds no TCP port but the authorization server's and the robots'
public ports, each refusing a client without a certificate, and its rclpy participant
discovers no publisher on either robot's DDS domain.
"""

from __future__ import annotations

import contextlib
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.ros2_support import NODES, fresh_domains, ros2_env, ros2_python
from tests.runbook_support import (HOSTS, MASTER_CHECKS, PORTS, ROBOTS, ROS2_PREFIX, RUNBOOK, Hosts, Step,
                                   listed_ports, stop_pid_files, stranger_scan, steps)
from tests.support import REPO, require, until

#: Part 1's blocks a ROS 2 fleet runs as written, before Part 5's own
MASTER_STEPS = ("master-pki", "master-registry", "master-authz")
#: what the walkthrough starts, by pid file (stopped after it)
PID_FILES = ["authz.pid", "robot_a/talker.pid", "robot_b/listener.pid", *(f"{r}/interceptor.pid" for r in ROBOTS)]
#: a flow counts as stopped once the listener got nothing for this long while the talker (10 Hz) publishes
QUIET = 2.0


def ros2_steps() -> list[Step]:
    every = steps()
    return [s for s in every if s.name in MASTER_STEPS] + [s for s in every if s.name.startswith(ROS2_PREFIX)]


class Fleet(Hosts):
    """The hosts, Part 5's variables (a fresh DDS domain per robot), and what the checks need."""

    def __init__(self, lab, work: Path, venv: Path) -> None:
        super().__init__(lab, work, HOSTS, REPO=str(REPO), ROS2_VENV=str(venv))
        self.python = venv / "bin" / "python"
        self.domains = dict(zip(ROBOTS, fresh_domains(len(ROBOTS)), strict=True))
        peer = {"robot_a": "robot_b", "robot_b": "robot_a"}
        self.per_robot = {r: {"DOMAIN_ID": str(self.domains[r]), "PEER_ADDR": self.hosts[peer[r]].address}
                          for r in ROBOTS}

    def received(self) -> list[int]:
        """The sequence numbers robot B's listener has printed (``GOT <seq>``)."""
        log = self.work / "robot_b" / "listener.log"
        text = log.read_text() if log.exists() else ""
        assert "BAD" not in text, f"robot B's listener got a broken message: {text[-500:]}"
        return [int(line.split()[1]) for line in text.splitlines() if line.startswith("GOT ")]

    def flows(self, count: int = 10, within: float = 30, what: str = "robot A's /chatter reaches robot B") -> None:
        """``count`` more messages of robot A's talker reach robot B's listener, in order."""
        before = len(self.received())
        until(lambda: len(self.received()) >= before + count, within, what)
        new = self.received()[before:before + count]
        assert new == list(range(new[0], new[0] + count)), f"messages lost or reordered: {new}"

    def stops(self, within: float = 15, what: str = "robot B's listener stops receiving") -> None:
        """Robot B's listener receives nothing for QUIET seconds while robot A's talker
        still publishes (within ``within`` seconds)."""
        seen = {"count": -1, "since": time.monotonic()}

        def quiet() -> bool:
            count = len(self.received())
            if count != seen["count"]:
                seen.update(count=count, since=time.monotonic())
            return time.monotonic() - seen["since"] >= QUIET

        until(quiet, within, what)
        self.running("robot_a", "talker")
        self.running("robot_b", "listener")
        assert "DONE" not in (self.work / "robot_a" / "talker.log").read_text(), "robot A's talker has published all"

    def logged(self, robot: str, *parts: str, within: float = 10) -> None:
        """A line of ``robot``'s interceptor log holds every one of ``parts`` (the line the page quotes)."""
        until(lambda: self.logged_any(robot, parts), within, f"{robot}'s interceptor logs {' ... '.join(parts)!r}")

    def logged_any(self, robot: str, *lines: tuple[str, ...]) -> bool:
        """Whether a line of ``robot``'s interceptor log holds every part of one of ``lines``."""
        log = (self.work / robot / "interceptor.log").read_text().splitlines()
        return any(all(p in line for p in parts) for parts in lines for line in log)

    def running(self, robot: str, node: str) -> None:
        """The node the page started on ``robot`` (its pid file ``ROBOT/NODE.pid``) still runs."""
        pid = int((self.work / robot / f"{node}.pid").read_text())
        log = self.work / robot / f"{node}.log"
        assert Path(f"/proc/{pid}").exists(), f"{robot}'s {node} ended: {log.read_text()[-500:]}"

    def probe(self, robot: str, *, stranger: bool, seconds: float) -> subprocess.Popen:
        """A fresh rclpy participant on ``robot``'s domain that prints each publisher of
        /chatter it discovers (tests/ros2_nodes/publishers.py): on the robot itself, with
        the robot's localhost-only profile, or on the stranger's host as a stranger would
        start it (no profile, the robot's address as its DDS static peer)."""
        env = ros2_env(self.domains[robot], localhost_profile=not stranger)
        if stranger:
            env["ROS_STATIC_PEERS"] = self.hosts[robot].address
        argv = [str(self.python), str(NODES / "publishers.py"), "/chatter", str(seconds)]
        return subprocess.Popen(self.hosts["stranger" if stranger else robot].argv(argv), env=env, cwd=str(NODES),
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


# ------------------------------------------------------------------ the checks, one per step

def check_ros2_credentials(d: Fleet, outs):
    for robot in ROBOTS:
        assert d.token(robot) == 200, f"{robot} gets no token"
        assert (d.work / robot / f"{robot}.key").exists()
    assert "std_msgs/msg/String" in d.cli("show-manager", "robot_a")


def check_ros2_venv(d: Fleet, outs):
    assert all("ros2 venv ready" in outs[r] for r in ROBOTS), outs


def check_ros2_robot_interceptor(d: Fleet, outs):
    for robot in ROBOTS:
        assert f"manager {robot}" in outs[robot], outs[robot]


def check_ros2_talker(d: Fleet, outs):
    log = d.work / "robot_a" / "talker.log"
    until(lambda: "READY" in log.read_text(), 30, "robot A's talker prints READY")


def check_ros2_listener(d: Fleet, outs):
    assert len([line for line in outs["robot_b"].splitlines() if line.startswith("GOT ")]) == 3, outs["robot_b"]
    d.flows()


def check_ros2_remove_grant(d: Fleet, outs):
    assert "/chatter" not in d.cli("show-manager", "robot_b")


def check_ros2_remove_grant_live(d: Fleet, outs):
    d.stops(what="robot B's listener stops receiving once its grant is removed")
    # each interceptor judges the stream again on the other's next token, which the grant
    # removed changed on both sides (a token is narrowed to its peer's names): whichever
    # is shown the other's first cuts it (robot B's cut first in a CI run)
    until(lambda: d.logged_any("robot_a", ("cutting off stream of manager=robot_b", "grant_removed: robot_b may not "
                                                                                   "subscribe /chatter"))
          or d.logged_any("robot_b", ("cutting off stream of manager=robot_a", "grant_removed: this robot's manager "
                                                                             "robot_b may not subscribe /chatter")),
          10, "robot A's or robot B's interceptor logs the cut: grant_removed")
    d.logged("robot_a", "DENY ros2_topic_out from robot_b@", "not offered to it")


def check_ros2_add_grant(d: Fleet, outs):
    assert "/chatter" in d.cli("show-manager", "robot_b")


def check_ros2_add_grant_live(d: Fleet, outs):
    d.flows(what="robot A's /chatter reaches robot B again after the grant is given back")


def check_ros2_restart_interceptor(d: Fleet, outs):
    assert "manager robot_b" in outs["robot_b"], outs["robot_b"]
    d.flows(what="robot A's /chatter reaches robot B after its interceptor restarted")


def check_ros2_exposure(d: Fleet, outs):
    """The stranger reaches the listed TCP ports only, each wanting a certificate; its
    rclpy participant, told each robot's address, discovers no publisher of /chatter on
    the robot's domain, where one on the robot itself (the control) discovers them."""
    listed = listed_ports(outs)
    assert listed["master"] == {PORTS["AUTHZ_PORT"]}, listed
    assert all(listed[r] == {PORTS["PUBLIC_PORT"]} for r in ROBOTS), listed
    seconds = 5.0
    probes = {(who, r): d.probe(r, stranger=who == "stranger", seconds=seconds)
              for who in ("robot", "stranger") for r in ROBOTS}
    try:
        stranger_scan(d, listed)  # meanwhile
        seen = {key: p.communicate(timeout=seconds + 60)[0] for key, p in probes.items()}
    finally:
        for p in probes.values():
            with contextlib.suppress(ProcessLookupError):
                p.kill()
    for r in ROBOTS:
        assert "DONE" in seen["robot", r] and "PUB " in seen["robot", r], f"control: on {r} itself: {seen['robot', r]}"
        assert "DONE" in seen["stranger", r], seen["stranger", r]
        assert "PUB " not in seen["stranger", r], f"the stranger discovered {r}'s DDS domain: {seen['stranger', r]}"
    d.flows()


def check_ros2_revoke_cert(d: Fleet, outs):
    assert "revoked" in outs["master"], outs["master"]
    until(lambda: d.token("robot_a") != 200, 5, "robot A still gets tokens 5 s after its revocation")
    d.stops(what="robot B's listener stops receiving once robot A is revoked")
    cut = "cutting off stream of manager=robot_a"
    until(lambda: d.logged_any("robot_b", (cut, "certificate_revoked"), (cut, "subject_disabled")), 10,
          "robot B cutting robot A's streams, its certificate revoked or its manager disabled")
    d.logged("robot_a", "our own certificate (serial", "was revoked by the CA")


CHECKS = {**MASTER_CHECKS, **{name[len("check_"):].replace("_", "-"): fn for name, fn in globals().items()
                              if name.startswith("check_")}}


def test_part5_has_every_step_a_check_and_a_host():
    names = [step.name for step in ros2_steps()]
    assert names[:3] == list(MASTER_STEPS)
    assert set(names) == set(CHECKS), set(names) ^ set(CHECKS)
    part = RUNBOOK.read_text().split("## Part 5: a fleet of ROS 2 robots", 1)[1]
    assert [s.name for s in steps() if s.name.startswith(ROS2_PREFIX)] == \
        [line[len("# step: "):] for line in part.splitlines() if line.startswith("# step: ")], \
        "Part 5 holds every ros2- step and no other"


@pytest.mark.timeout(400)  # the walkthrough and the stranger: ~50 s quiet
def test_runbook_part5_a_ros2_fleet_on_separate_hosts(tmp_path):
    """Part 1's master host, then Part 5 on two ROS 2 robots, then a stranger's scan."""
    require("curl", "ss")
    python = ros2_python()
    from tests.interceptor_harness import separate_hosts

    separate_hosts()
    from cryptoros.lab.netns import NetnsLab

    work = tmp_path / "runbook"
    work.mkdir()
    with NetnsLab() as lab:
        d = Fleet(lab, work, python.parent.parent)
        try:
            for step in ros2_steps():
                start = time.monotonic()
                outs = d.run(step)
                CHECKS[step.name](d, outs)
                print(f"{step.name}: {time.monotonic() - start:.1f} s")  # where the time goes (-s)
        finally:
            stop_pid_files(work, PID_FILES)


def test_the_ros2_robots_configuration_in_the_runbook_is_one_the_interceptor_accepts(tmp_path, monkeypatch):
    """Part 5's robot configuration (the heredoc of ``ros2-robot-interceptor``), its
    variables filled in as a robot's shell would, parses as a ros2-role interceptor's
    (the same loader as --check and the daemon): checked without the ROS 2 venv too."""
    from interceptor.config import parse, read_toml

    script = next(s.script for s in steps() if s.name == "ros2-robot-interceptor")
    toml = re.search(r"<<EOF\n(.*?)^EOF$", script, re.S | re.M).group(1)
    values = {"ROBOT": "robot_a", "MASTER_ADDR": "10.0.0.1", "AUTHZ_PORT": "8443", "ROBOT_ADDR": "10.0.0.2",
              "PUBLIC_PORT": "7400", "METRICS_PORT": "9102", "PEER_ADDR": "10.0.0.3", "DOMAIN_ID": "11"}
    filled = re.sub(r"\$([A-Z_]+)", lambda m: values[m.group(1)], toml)
    for name in ("ca.crt", "robot_a.crt", "robot_a.key", "crl.pem"):
        (tmp_path / name).write_text("")
    (tmp_path / "robot.toml").write_text(filled)
    monkeypatch.setenv("CRYPTOROS_ROS2_PYTHON", sys.executable)  # as the block exports it (any python: not run)
    cfg = parse(read_toml(tmp_path / "robot.toml"), base=tmp_path, source=tmp_path / "robot.toml")
    assert cfg.roles == ("ros2",) and cfg.ros2.domain_id == 11 and len(cfg.ros2.peers) == 1
