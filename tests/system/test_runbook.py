"""docs/runbook.md, executed on separate hosts with a stranger watching.

Every fenced ``sh`` block runs as written, in order, in a fresh ``bash -e`` in one
working directory, on the host its ``# on:`` line names: a network namespace each
(:mod:`cryptoros.lab.netns`: its own loopback, one address on a shared bridge), so a
port bound to 127.0.0.1 on one host is out of every other host's reach, as on real
machines. After each block the effect of its step is checked; after the walkthrough a
stranger host with no certificate tries every port the others listen on beyond loopback.
"""

from __future__ import annotations

import contextlib
import json
import re
import subprocess
import time
import xmlrpc.client

import jwt
import pytest

from tests.interceptor_harness import NODE, SYS_PY, got, read_lines
from tests.runbook_support import (HOSTS, MASTER_CHECKS, PORTS, ROBOTS, ROS2_PREFIX, RUNBOOK, Hosts, Step,
                                   listed_ports, stop_pid_files, stranger_scan, steps)
from tests.support import REPO, VENV_BIN, require, running, until

pytestmark = [pytest.mark.ros1]


def ros1_steps() -> list[Step]:
    """Parts 1 to 4: every block but Part 5's (a ROS 2 fleet, tests/system/test_runbook_ros2.py)."""
    return [step for step in steps() if not step.name.startswith(ROS2_PREFIX)]


class Deployment(Hosts):
    """The hosts, the working directory every block starts in, and what the checks need."""

    def __init__(self, lab, work) -> None:
        super().__init__(lab, work, (*HOSTS, "robot_c"), ROS_HOME=str(work / "ros_home"))
        self.listener: subprocess.Popen | None = None

    def ros_env(self, host: str) -> dict[str, str]:
        """A node's environment on ``host`` (as the runbook's nodes have it)."""
        return {**self.env, "ROS_MASTER_URI": f"http://127.0.0.1:{PORTS['ROS_PORT']}", "ROS_IP": "127.0.0.1",
                "PYTHONUNBUFFERED": "1", "CRYPTOROS_NETNS": self.hosts[host].ns}

    def local_master(self, host: str) -> xmlrpc.client.ServerProxy:
        return xmlrpc.client.ServerProxy(f"http://127.0.0.1:{PORTS['ROS_PORT']}/")

    def registers(self, node: str) -> int:
        """Robot B's local master's answer to a subscription of ``node`` to /secret."""
        uri = "http://127.0.0.1:9/"
        with self.hosts["robot_b"].inside():
            local = self.local_master("robot_b")
            code = local.registerSubscriber(node, "/secret", "std_msgs/String", uri)[0]
            if code == 1:
                local.unregisterSubscriber(node, "/secret", uri)
        return code

    def grants(self, manager: str) -> str:
        """What the registry on the master host says of ``manager`` (its grants)."""
        return self.cli("show-manager", manager)

    def master_nodes(self) -> set[str]:
        with self.hosts["master"].inside():
            state = self.local_master("master").getSystemState("/test")[2]
        return {n for section in state for _name, nodes in section for n in nodes}

    def token_kid(self, manager: str) -> str | None:
        status, body = self.token_reply(manager)
        return jwt.get_unverified_header(body["access_token"])["kid"] if status == 200 else None

    def receives(self, within: float = 15) -> None:
        """Robot B's listener gets robot A's talker's messages (again)."""
        assert self.listener is not None
        read_lines(self.listener, None, 0.2)
        lines = read_lines(self.listener, "GOT", within)
        assert "hello from robot A" in got(lines), f"the listener on robot B stopped receiving: {lines[-5:]}"


#: what the walkthrough starts, by pid file (stopped after it)
PID_FILES = ["authz.pid", "rosmaster.pid", "interceptor.pid", "robot_a/talker.pid",
             *(f"{r}/interceptor.pid" for r in ROBOTS)]


# ------------------------------------------------------------------ the checks, one per step

def check_master_rosmaster(d: Deployment, outs):
    with d.hosts["master"].inside():
        code, _msg, _state = d.local_master("master").getSystemState("/t")
    assert code == 1


def check_master_interceptor(d: Deployment, outs):
    out = outs["master"]
    assert "manager master" in out and "token     subject master" in out, out


def check_master_processes(d: Deployment, outs):
    lines = outs["master"].strip().splitlines()
    assert len(lines) == 3, lines
    assert any("cryptoros-authz serve" in line for line in lines)
    assert any("rosmaster --core" in line for line in lines)
    assert any("cryptoros-interceptor --config master.toml" in line for line in lines), lines


def check_robots_credentials(d: Deployment, outs):
    for robot in (*ROBOTS, "robot_c"):
        assert d.token(robot) == 200, f"{robot} gets no token"
        assert (d.work / robot / f"{robot}.key").exists()


def check_robot_interceptor(d: Deployment, outs):
    for robot in ROBOTS:
        assert f"manager {robot}" in outs[robot], outs[robot]


def check_robot_a_talker(d: Deployment, outs):
    until(lambda: "/talker" in d.master_nodes(), 30, "robot A's /talker never reached rosmaster")


def check_robot_b_listener(d: Deployment, outs):
    assert outs["robot_b"].count('data: "hello from robot A"') == 3, outs["robot_b"]
    # the listener that stays for the day-2 steps, as the robot's real node would
    d.listener = d.stack.enter_context(running([SYS_PY, NODE, "sub", "/listener", "/chatter", "900"],
                                               env=d.ros_env("robot_b")))
    read_lines(d.listener, "READY", 30)
    d.receives(30)


def check_add_grant(d: Deployment, outs):
    assert "/listener_new" in d.grants("robot_b")


def check_add_grant_live(d: Deployment, outs):
    until(lambda: d.registers("/listener_new") == 1, 10, "the new grant did not work within 10 s")


def check_remove_grant(d: Deployment, outs):
    assert "/listener_new" not in d.grants("robot_b")


def check_remove_grant_live(d: Deployment, outs):
    until(lambda: d.registers("/listener_new") == -1, 10, "the removed grant still works after 10 s")
    d.receives()


def check_stock_tools(d: Deployment, outs):
    grants = d.grants("robot_b")
    assert "/rosparam-*" in grants and "/rostopic_*" in grants, grants
    # the runbook's example grants one namespace, not every parameter (deployment audit)
    params = [line.split() for line in grants.splitlines() if line.split()[:1] == ["write_param"]]
    assert params and all(p[2] == "/runbook" for p in params), grants


def check_stock_tools_robot(d: Deployment, outs):
    lines = outs["robot_b"].splitlines()
    assert "1" in lines, lines  # rosparam get /runbook/x
    assert 'data: "hello from robot A"' in lines, lines  # rostopic echo
    assert "/talker" in lines and "/listener" in lines, lines  # rosnode list


def check_renew(d: Deployment, outs):
    out = outs["master"]
    assert re.search(r"^serial:\s+\S+", out, re.M) and re.search(r"^previous:", out, re.M), out
    d.receives()


def check_renew_reload(d: Deployment, outs):
    status = subprocess.run(d.hosts["robot_b"].argv([str(VENV_BIN / "cryptoros"), "status", "--config",
                                                     str(d.work / "robot_b" / "robot.toml"), "--json"]),
                            capture_output=True, text=True, timeout=30, env=d.env)
    new = re.search(r"^serial:\s+(\S+)", (d.work / "renew.txt").read_text(), re.M).group(1)
    assert json.loads(status.stdout)["certificate"]["serial"] == new
    d.receives()


def check_renew_revoke_old(d: Deployment, outs):
    assert "revoked serial" in outs["master"], outs["master"]
    d.receives(30)


def check_rotate_key(d: Deployment, outs):
    keys = [line for line in outs["master"].splitlines() if "created" in line]
    assert len(keys) == 2 and sum(" active" in line for line in keys) == 1, outs["master"]
    active = next(line.split()[0] for line in keys if " active" in line)
    until(lambda: d.token_kid("robot_a") == active, 30, "tokens are not signed with the new key 30 s after rotate-key")
    d.receives()


def check_restart_interceptor(d: Deployment, outs):
    d.receives(20)


def check_restart_master_interceptor(d: Deployment, outs):
    assert "/talker" in outs["master"].split(), outs["master"]
    d.receives(20)


def check_restart_authz(d: Deployment, outs):
    assert d.token("robot_a") == 200
    d.receives()


def check_restart_rosmaster(d: Deployment, outs):
    # the new rosmaster holds the talker again: the master's interceptor replayed it
    assert "/talker" in d.master_nodes()
    d.receives()


def check_revoke_cert(d: Deployment, outs):
    until(lambda: d.token("robot_c") != 200, 5, "robot C still gets tokens 5 s after its revocation")
    assert "revoked" in outs["master"]


def _crl_due(d: Deployment, host: str, config: str) -> float | None:
    status = subprocess.run(d.hosts[host].argv([str(VENV_BIN / "cryptoros"), "status", "--config",
                                                str(d.work / config), "--json"]),
                            capture_output=True, text=True, timeout=30, env=d.env)
    return (json.loads(status.stdout).get("crl") or {}).get("next_update") if status.stdout.startswith("{") else None


def _signed_crl_due(d: Deployment) -> float:
    from cryptoros.pemfiles import load_crls

    return load_crls(d.work / "pki" / "crl.pem")[0].next_update_utc.timestamp()


def check_crl_refresh(d: Deployment, outs):
    assert "next update:" in outs["master"], outs["master"]
    due = _signed_crl_due(d)
    assert due > time.time() + 6 * 86400
    until(lambda: _crl_due(d, "master", "master.toml") == due, 30, "the master's interceptor on the new CRL")
    d.receives()


def check_crl_refresh_robot(d: Deployment, outs):
    due = _signed_crl_due(d)
    for robot in ROBOTS:
        until(lambda robot=robot: _crl_due(d, robot, f"{robot}/robot.toml") == due, 30, f"{robot} on the new CRL")
    d.receives()


def check_exposure(d: Deployment, outs):
    """What the stranger reaches: every listed port is a TLS port refusing a client without
    a certificate; rosmaster's API answers the stranger on no host at no port."""
    listed = listed_ports(outs)
    assert listed["master"] == {PORTS["AUTHZ_PORT"], PORTS["PUBLIC_PORT"]}, listed
    assert all(listed[r] == {PORTS["PUBLIC_PORT"]} for r in ROBOTS), listed
    # the scan, from the stranger's host: nothing else answers, each listed port wants a certificate
    stranger_scan(d, listed)
    stranger = d.hosts["stranger"]
    for host, ports in listed.items():
        address = d.hosts[host].address
        for port in sorted(ports | {PORTS["ROS_PORT"]}):
            uri = f"http://{address}:{port}/"
            env = {**d.env, "ROS_MASTER_URI": uri, "CRYPTOROS_NETNS": stranger.ns}
            for tool in (["rosnode", "list"], ["rosparam", "get", "/runbook/x"]):
                result = subprocess.run(stranger.argv(tool), capture_output=True, text=True, timeout=60, env=env)
                assert result.returncode != 0, f"the stranger's {' '.join(tool)} worked against {uri}: {result.stdout}"
            with stranger.inside(), pytest.raises((OSError, xmlrpc.client.ProtocolError)):
                xmlrpc.client.ServerProxy(uri).shutdown("/stranger", "scan")
    # and the deployment still works
    assert "/talker" in d.master_nodes()
    d.receives()


CHECKS = {**MASTER_CHECKS, **{name[len("check_"):].replace("_", "-"): fn for name, fn in globals().items()
                            if name.startswith("check_")}}


def test_runbook_has_every_step_a_check_and_a_host():
    names = [step.name for step in ros1_steps()]
    assert names[:6] == ["master-pki", "master-registry", "master-authz", "master-rosmaster", "master-interceptor",
                         "master-processes"]
    assert names[-1] == "exposure"
    assert set(names) == set(CHECKS), set(names) ^ set(CHECKS)
    text = RUNBOOK.read_text()
    for part in ("## Part 1: the master host", "## Part 2: robots join", "## Part 3: day-2 operations",
                 "## Part 4: what a stranger can reach"):
        assert part in text


def test_the_docs_create_passphrase_files_0600_from_the_start():
    """A passphrase file a walkthrough writes is created under ``umask 077``: written
    under the default umask (0644) and chmod-ed after, it could be read in between."""
    docs = [REPO / "README.md", REPO / "authz_server" / "README.md", *sorted((REPO / "docs").glob("*.md"))]
    writes = [(doc.name, line) for doc in docs for line in doc.read_text().splitlines()
              if re.search(r">\s*\S*\.pass\b", line)]
    assert len(writes) >= 3, writes  # README.md, authz_server/README.md, docs/runbook.md
    assert [w for w in writes if "umask 077" not in w[1]] == []


@pytest.mark.timeout(600)  # the whole deployment and every day-2 step: ~60 s quiet, ~160 s on a busy machine
def test_runbook_on_separate_hosts(tmp_path):
    """The whole runbook on a master host and two robots, then a stranger's scan."""
    require("rosmaster", "rostopic", "rosparam", "rosnode", "curl", "ss")
    from tests.interceptor_harness import separate_hosts

    if not separate_hosts():
        pytest.skip("network namespaces are not available here")
    from cryptoros.lab.netns import NetnsLab

    work = tmp_path / "runbook"
    work.mkdir()
    with NetnsLab() as lab, contextlib.ExitStack() as stack:
        d = Deployment(lab, work)
        d.stack = stack
        try:
            for step in ros1_steps():
                outs = d.run(step)
                CHECKS[step.name](d, outs)
        finally:
            stack.close()
            stop_pid_files(work, PID_FILES)
