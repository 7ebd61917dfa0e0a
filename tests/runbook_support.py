"""docs/runbook.md as the runbook tests execute it (no tests here).

Owns what the ROS 1 walkthrough (tests/system/test_runbook.py) and the ROS 2 fleet's
(tests/system/test_runbook_ros2.py) share: the page's fenced ``sh`` blocks read as steps
(:func:`steps`), the namespace hosts every block runs on with the page's variables
(:class:`Hosts`), stopping what the page started by its pid files (:func:`stop_pid`), a
token request with a manager's certificate, and the stranger's scan of a host's ports
(:func:`stranger_scan`), and the checks of Part 1's master-host steps both walkthroughs run.
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
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import pytest

from cryptoros.lab.network import clean_env
from tests.support import REPO, VENV_BIN

RUNBOOK = REPO / "docs" / "runbook.md"
BLOCK = re.compile(r"^```sh\n(.*?)^```", re.S | re.M)
ROBOTS = ("robot_a", "robot_b")
HOSTS = ("master", *ROBOTS)
#: Part 5's blocks (a ROS 2 fleet): their step names start with this
ROS2_PREFIX = "ros2-"
#: what a daemon still starting makes a readiness check print: a step's waits keep it quiet
WAIT_NOISE = ("Connection refused", "Unable to communicate with master")
PORTS = {"PUBLIC_PORT": 7400, "AUTHZ_PORT": 8443, "ROS_PORT": 11311, "PROBE_PORT": 8081, "METRICS_PORT": 9102}


@dataclass(frozen=True)
class Step:
    name: str
    hosts: tuple[str, ...]
    script: str


def steps() -> list[Step]:
    """Every ``sh`` block of the page, in order: its step name, the hosts it runs on, its text."""
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


def stop_pid(*pids: int, timeout: float = 15) -> None:
    """Stop daemons the runbook started (by their pid files): all signalled at once, each
    killed if it has not ended ``timeout`` seconds later."""
    for pid in pids:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGTERM)
    deadline = time.monotonic() + timeout
    while any(Path(f"/proc/{pid}").exists() for pid in pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    for pid in pids:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)


def stop_pid_files(work: Path, files: list[str]) -> None:
    """Stop every process whose pid file (relative to ``work``) the walkthrough wrote."""
    stop_pid(*(int((work / name).read_text().split()[0]) for name in files if (work / name).exists()))


class Hosts:
    """The namespace hosts (``names`` and a stranger), the working directory every block
    starts in, and the variables the page's blocks read (``extra``: more of them)."""

    def __init__(self, lab, work: Path, names: tuple[str, ...], **extra: str) -> None:
        self.lab = lab
        self.work = work
        self.hosts = {name: lab.add_host(name) for name in (*names, "stranger")}
        addr = {name: h.address for name, h in self.hosts.items()}
        self.env = clean_env(
            # the venv last, as the runbook says: ROS's own `#!/usr/bin/env python3` scripts
            # need Debian's python first
            PATH=f"{os.environ.get('PATH', '/usr/bin:/bin')}:{VENV_BIN}",
            CRYPTOROS_AUTHZ_DB=f"sqlite:///{work}/registry.db", CRYPTOROS_PKI_DIR=str(work / "pki"),
            **{f"{name.upper()}_ADDR": address for name, address in addr.items() if name != "stranger"},
            **{k: str(v) for k, v in PORTS.items()}, **extra)
        #: variables a block ``# on: each robot`` gets per robot, beyond ROBOT and ROBOT_ADDR
        self.per_robot: dict[str, dict[str, str]] = {robot: {} for robot in ROBOTS}

    def run(self, step: Step, timeout: float = 180) -> dict[str, str]:
        """The step on each of its hosts (a fresh ``bash -e`` each); their outputs by host."""
        outs = {}
        for host in step.hosts:
            env = dict(self.env)
            if host in ROBOTS:
                env.update(ROBOT=host, ROBOT_ADDR=self.hosts[host].address, **self.per_robot[host])
            result = subprocess.run(self.hosts[host].argv(["bash", "-e", "-c", step.script]), cwd=self.work, env=env,
                                    capture_output=True, text=True, timeout=timeout, stdin=subprocess.DEVNULL)
            assert result.returncode == 0, f"runbook step {step.name} on {host} failed ({result.returncode}):\n" \
                                           f"{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
            noise = [line for line in result.stderr.splitlines() if any(n in line for n in WAIT_NOISE)]
            assert not noise, f"runbook step {step.name} on {host} is not quiet while it waits:\n" + "\n".join(noise)
            outs[host] = result.stdout
        return outs

    def on(self, host: str, args: list[str], timeout: float = 60) -> subprocess.CompletedProcess:
        """A command on ``host`` with the page's variables (its output captured)."""
        return subprocess.run(self.hosts[host].argv(args), capture_output=True, text=True, timeout=timeout,
                              env=self.env, cwd=self.work)

    def cli(self, *args: str) -> str:
        """``cryptoros-authz ARGS`` on the master host's registry: its output (it must succeed)."""
        result = subprocess.run([str(VENV_BIN / "cryptoros-authz"), *args], capture_output=True, text=True,
                                timeout=60, env=self.env)
        assert result.returncode == 0, result.stderr
        return result.stdout

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


# ------------------------------------------------------------------ Part 1's master-host checks (both fleets)

def check_master_pki(d: Hosts, outs):
    assert all((d.work / "pki" / p).exists() for p in ("ca.crt", "crl.pem", "issued/authz.crt",
                                                          "issued/master.crt", "private/master.key"))


def check_master_registry(d: Hosts, outs):
    assert len(d.cli("list-keys").splitlines()) == 1
    assert (d.work / "signing.pass").stat().st_mode & 0o777 == 0o600


def check_master_authz(d: Hosts, outs):
    with d.hosts["master"].inside(), \
            urllib.request.urlopen(f"http://127.0.0.1:{PORTS['PROBE_PORT']}/healthz", timeout=5) as reply:
        assert reply.status == 200
    assert "chmod 600" not in (d.work / "authz.log").read_text()  # no secret file open to others


#: Part 1's master-host steps' checks, by step name
MASTER_CHECKS = {"master-pki": check_master_pki, "master-registry": check_master_registry,
                 "master-authz": check_master_authz}


def listed_ports(outs: dict[str, str]) -> dict[str, set[int]]:
    """The ports each host's ``exposure`` step listed (``ADDRESS:PORT`` words)."""
    return {host: {int(word.rsplit(":", 1)[1]) for word in out.split()} for host, out in outs.items()}


def stranger_scan(d: Hosts, listed: dict[str, set[int]]) -> None:
    """From the stranger's host: every TCP port of each host that accepts a connection is
    one the host listed, and each refuses a TLS client without a certificate."""
    stranger = d.hosts["stranger"]
    for host, ports in listed.items():
        address = d.hosts[host].address
        scanned = open_ports(stranger, address)
        assert scanned == ports, f"{host}: the stranger reaches ports {sorted(scanned)}, the host lists {sorted(ports)}"
        for port in ports:
            refuses_without_certificate(stranger, address, port)


def open_ports(stranger, address: str) -> set[int]:
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


def refuses_without_certificate(stranger, address: str, port: int) -> None:
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
