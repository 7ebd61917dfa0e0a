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
import os
import re
import signal
import socket
import ssl
import subprocess
import threading
import time
import urllib.request
import xmlrpc.client
from dataclasses import dataclass
from pathlib import Path

import pytest

from cryptoros.lab.network import clean_env
from tests.interceptor_harness import NODE, SYS_PY, got, read_lines
from tests.support import REPO, VENV_BIN, require, running

pytestmark = [pytest.mark.ros1]

RUNBOOK = REPO / "docs" / "runbook.md"
BLOCK = re.compile(r"^```sh\n(.*?)^```", re.S | re.M)
ROBOTS = ("robot_a", "robot_b")
HOSTS = ("master", *ROBOTS)
#: what a daemon still starting makes a readiness check print: a step's waits keep it quiet
WAIT_NOISE = ("Connection refused", "Unable to communicate with master")
PORTS = {"PUBLIC_PORT": 7400, "AUTHZ_PORT": 8443, "ROS_PORT": 11311, "PROBE_PORT": 8081, "METRICS_PORT": 9102}


@dataclass(frozen=True)
class Step:
    name: str
    hosts: tuple[str, ...]
    script: str


def steps() -> list[Step]:
    """Every ``sh`` block, in order: its step name, the hosts it runs on, its text."""
    out = []
    for script in BLOCK.findall(RUNBOOK.read_text()):
        lines = script.splitlines()
        assert lines[0].startswith("# step: "), f"a runbook block without '# step: NAME': {lines[0]!r}"
        assert len(lines) > 1 and lines[1].startswith("# on: "), f"a runbook block without '# on: HOST': {lines[:2]}"
        on = lines[1][len("# on: "):].strip()
        hosts = {"each robot": ROBOTS, "each host": HOSTS}.get(on, (on,))
        assert set(hosts) <= set(HOSTS), f"unknown host in {lines[1]!r}"
        out.append(Step(lines[0][len("# step: "):].strip(), hosts, script))
    return out


def stop_pid(pid: int, timeout: float = 15) -> None:
    """Stop a daemon the runbook started (by its pid file), bounded."""
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGTERM)
    deadline = time.monotonic() + timeout
    while Path(f"/proc/{pid}").exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGKILL)


def until(check, within: float, what: str):
    deadline = time.monotonic() + within
    while True:
        value = check()
        if value:
            return value
        assert time.monotonic() < deadline, what
        time.sleep(0.2)


class Deployment:
    """The hosts, the working directory every block starts in, and what the checks need."""

    def __init__(self, lab, work: Path) -> None:
        self.lab = lab
        self.work = work
        self.hosts = {name: lab.add_host(name) for name in (*HOSTS, "robot_c", "stranger")}
        addr = {name: h.address for name, h in self.hosts.items()}
        self.env = clean_env(
            PATH=f"{VENV_BIN}:{os.environ.get('PATH', '/usr/bin:/bin')}",
            MASTER_ADDR=addr["master"], ROBOT_A_ADDR=addr["robot_a"], ROBOT_B_ADDR=addr["robot_b"],
            ROBOT_C_ADDR=addr["robot_c"], CRYPTOROS_AUTHZ_DB=f"sqlite:///{work}/registry.db",
            CRYPTOROS_PKI_DIR=str(work / "pki"), ROS_HOME=str(work / "ros_home"),
            **{k: str(v) for k, v in PORTS.items()})
        self.listener: subprocess.Popen | None = None

    def run(self, step: Step, timeout: float = 180) -> dict[str, str]:
        """The step on each of its hosts; their outputs by host."""
        outs = {}
        for host in step.hosts:
            env = dict(self.env)
            if host in ROBOTS:
                env.update(ROBOT=host, ROBOT_ADDR=self.hosts[host].address)
            result = subprocess.run(self.hosts[host].argv(["bash", "-e", "-c", step.script]), cwd=self.work, env=env,
                                    capture_output=True, text=True, timeout=timeout, stdin=subprocess.DEVNULL)
            assert result.returncode == 0, f"runbook step {step.name} on {host} failed ({result.returncode}):\n" \
                                           f"{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
            noise = [line for line in result.stderr.splitlines() if any(n in line for n in WAIT_NOISE)]
            assert not noise, f"runbook step {step.name} on {host} is not quiet while it waits:\n" + "\n".join(noise)
            outs[host] = result.stdout
        return outs

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
        result = subprocess.run([str(VENV_BIN / "cryptoros-authz"), "show-manager", manager], capture_output=True,
                                text=True, timeout=60, env=self.env)
        assert result.returncode == 0, result.stderr
        return result.stdout

    def master_nodes(self) -> set[str]:
        with self.hosts["master"].inside():
            state = self.local_master("master").getSystemState("/test")[2]
        return {n for section in state for _name, nodes in section for n in nodes}

    def token_reply(self, manager: str) -> tuple[int, dict]:
        """(HTTP status, body) of a token request with ``manager``'s certificate
        (0: the handshake itself was refused)."""
        ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
        ctx.check_hostname = False
        ctx.load_verify_locations(cafile=str(self.work / "pki" / "ca.crt"))
        ctx.load_cert_chain(str(self.work / "pki" / "issued" / f"{manager}.crt"),
                            str(self.work / "pki" / "private" / f"{manager}.key"))
        url = f"https://{self.hosts['master'].address}:{PORTS['AUTHZ_PORT']}/token"
        opener = urllib.request.build_opener(urllib.request.HTTPSHandler(context=ctx))
        try:
            with opener.open(urllib.request.Request(url, data=b"grant_type=client_credentials"), timeout=10) as reply:
                return reply.status, json.loads(reply.read())
        except urllib.error.HTTPError as exc:
            return exc.code, {}
        except OSError:
            return 0, {}

    def token(self, manager: str) -> int:
        return self.token_reply(manager)[0]

    def token_kid(self, manager: str) -> str | None:
        import jwt

        status, body = self.token_reply(manager)
        return jwt.get_unverified_header(body["access_token"])["kid"] if status == 200 else None

    def receives(self, within: float = 15) -> None:
        """Robot B's listener gets robot A's talker's messages (again)."""
        assert self.listener is not None
        read_lines(self.listener, None, 0.2)
        lines = read_lines(self.listener, "GOT", within)
        assert "hello from robot A" in got(lines), f"the listener on robot B stopped receiving: {lines[-5:]}"

    def pids(self) -> list[int]:
        files = ["authz.pid", "rosmaster.pid", "interceptor.pid", "robot_a/talker.pid",
                 *(f"{r}/interceptor.pid" for r in ROBOTS)]
        return [int((self.work / f).read_text().split()[0]) for f in files if (self.work / f).exists()]


# ------------------------------------------------------------------ the checks, one per step

def check_master_pki(d: Deployment, outs):
    assert all((d.work / "pki" / p).exists() for p in ("ca.crt", "crl.pem", "issued/authz.crt",
                                                          "issued/master.crt", "private/master.key"))


def check_master_registry(d: Deployment, outs):
    listed = subprocess.run([str(VENV_BIN / "cryptoros-authz"), "list-keys"], capture_output=True, text=True,
                            timeout=60, env=d.env).stdout
    assert len(listed.splitlines()) == 1, listed
    assert (d.work / "signing.pass").stat().st_mode & 0o777 == 0o600


def check_master_authz(d: Deployment, outs):
    with d.hosts["master"].inside(), \
            urllib.request.urlopen(f"http://127.0.0.1:{PORTS['PROBE_PORT']}/healthz", timeout=5) as reply:
        assert reply.status == 200
    assert "chmod 600" not in (d.work / "authz.log").read_text()  # no secret file open to others


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
    listed = {host: {int(line.rsplit(":", 1)[1]) for line in out.split()} for host, out in outs.items()}
    assert listed["master"] == {PORTS["AUTHZ_PORT"], PORTS["PUBLIC_PORT"]}, listed
    assert all(listed[r] == {PORTS["PUBLIC_PORT"]} for r in ROBOTS), listed
    # the scan, from the stranger's host: nothing else answers, each listed port wants a certificate
    stranger = d.hosts["stranger"]
    for host, ports in listed.items():
        address = d.hosts[host].address
        scanned = _open_ports(stranger, address)
        assert scanned == ports, f"{host}: the stranger reaches ports {sorted(scanned)}, the host lists {sorted(ports)}"
        for port in ports:
            _refuses_without_certificate(stranger, address, port)
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


def _open_ports(stranger, address: str) -> set[int]:
    """Every TCP port of ``address`` that accepts a connection from the stranger's host
    (all 65,535: what a scan would find, not what the runbook meant to open)."""
    found: set[int] = set()

    def scan(ports: range) -> None:
        with stranger.inside():
            for port in ports:
                with socket.socket() as s:
                    s.settimeout(1.0)
                    if s.connect_ex((address, port)) == 0:
                        found.add(port)

    # refused connects on a bridge answer in microseconds; four threads keep a full scan short
    chunks = [range(start, min(start + 16384, 65536)) for start in range(1, 65536, 16384)]
    threads = [threading.Thread(target=scan, args=(chunk,)) for chunk in chunks]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=300)
    assert not any(t.is_alive() for t in threads), f"the scan of {address} did not finish"
    return found


def _refuses_without_certificate(stranger, address: str, port: int) -> None:
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.check_hostname = False
    ctx.verify_mode = ssl.CERT_NONE
    with stranger.inside(), socket.create_connection((address, port), timeout=10) as raw:
        raw.settimeout(10)
        with pytest.raises((ssl.SSLError, ConnectionError)):
            with ctx.wrap_socket(raw) as tls:
                # TLS 1.3: the server's refusal of a missing certificate arrives after the
                # client's handshake returns, on the first read
                tls.sendall(b"GET / HTTP/1.0\r\n\r\n")
                if not tls.recv(1):
                    raise ConnectionError("closed without an answer")


CHECKS = {name[len("check_"):].replace("_", "-"): fn for name, fn in globals().items() if name.startswith("check_")}


def test_runbook_has_every_step_a_check_and_a_host():
    names = [step.name for step in steps()]
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
            for step in steps():
                outs = d.run(step)
                CHECKS[step.name](d, outs)
        finally:
            stack.close()
            for pid in d.pids():
                stop_pid(pid)


def test_the_ros2_robots_configuration_in_the_runbook_is_one_the_interceptor_accepts(tmp_path):
    """Part 5's configuration, its variables filled in as a robot's shell would, parses
    as a ros2-role interceptor's (the same loader as --check and the daemon)."""
    from interceptor.config import parse, read_toml

    text = RUNBOOK.read_text()
    part = text[text.index("## Part 5: a fleet of ROS 2 robots"):]
    toml = re.search(r"^```toml\n(.*?)^```", part, re.S | re.M).group(1)
    values = {"ROBOT": "robot_a", "MASTER_ADDR": "10.0.0.1", "AUTHZ_PORT": "8443", "ROBOT_ADDR": "10.0.0.2",
              "PUBLIC_PORT": "7400", "METRICS_PORT": "9102", "PEER_ADDR": "10.0.0.3", "DOMAIN_ID": "11"}
    filled = re.sub(r"\$([A-Z_]+)", lambda m: values[m.group(1)], toml)
    for name in ("ca.crt", "robot_a.crt", "robot_a.key", "crl.pem"):
        (tmp_path / name).write_text("")
    (tmp_path / "robot.toml").write_text(filled)
    cfg = parse(read_toml(tmp_path / "robot.toml"), base=tmp_path, source=tmp_path / "robot.toml")
    assert cfg.roles == ("ros2",) and cfg.ros2.domain_id == 11 and len(cfg.ros2.peers) == 1
