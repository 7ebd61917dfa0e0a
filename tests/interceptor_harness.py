"""A small robot network on one machine for the interceptor tests (no tests here).

Hosts are loopback addresses: the master's interceptor on 127.0.0.4 in front of a
real Debian ``rosmaster``, robot A's interceptor on 127.0.0.2, robot B's on
127.0.0.3, each with its own certificate (IP SAN of its host) and its own manager in
the registry of a real ``cryptoros-authz`` daemon. Every process is real and is
stopped in a ``finally``.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import textwrap
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from tests.pki_fixtures import TestPKIFactory
from tests.support import free_port, require, script, stop, wait_for_port
from tests.authz_support import AuthzDaemon, authz, ok

SYS_PY = "/usr/bin/python3"
NODES = Path(__file__).parent / "ros1_nodes"
NODE = str(Path(__file__).parent / "interceptor_nodes" / "node.py")
STRING = "std_msgs/String"
STRING_MD5 = "992ce8a1687cec8c8bd883ec73ca41d1"

#: Policy of the default network: robot_a's talker publishes /chatter, robot_b's
#: listener subscribes to it; robot_b may call robot_a's service.
DEFAULT_POLICY = """\
version: 1
managers:
- name: master
  fingerprint_sha256: {master}
- name: robot_a
  fingerprint_sha256: {robot_a}
  grants:
    publish:
    - {{node: /rospy_talker, topic: /chatter, type: std_msgs/String}}
    - {{node: /roscpp_talker, topic: /chatter, type: std_msgs/String}}
    - {{node: /talker_a, topic: /chatter, type: std_msgs/String}}
    - {{node: /talker_a, topic: /secret, type: std_msgs/String}}
    subscribe:
    - {{node: /victim, topic: /chatter, type: std_msgs/String}}
    serve:
    - {{node: /rospy_server, service: /rospy_loggers, type: roscpp/GetLoggers}}
- name: robot_b
  fingerprint_sha256: {robot_b}
  grants:
    subscribe:
    - {{node: /rospy_listener, topic: /chatter, type: std_msgs/String}}
    - {{node: /victim, topic: /chatter, type: std_msgs/String}}
    - {{node: '*', topic: /chatter, type: std_msgs/String}}
    call:
    - {{node: /rospy_client, service: /rospy_loggers, type: roscpp/GetLoggers}}
- name: robot_c
  fingerprint_sha256: {robot_c}
"""

HOSTS = {"master": "127.0.0.4", "robot_a": "127.0.0.2", "robot_b": "127.0.0.3", "robot_c": "127.0.0.5"}


@dataclass
class Host:
    name: str
    address: str
    public_port: int
    local_master_port: int
    metrics_port: int
    config: Path
    proc: subprocess.Popen | None = None
    log: Path | None = None

    @property
    def master_uri(self) -> str:
        return f"http://127.0.0.1:{self.local_master_port}/"

    def logs(self) -> str:
        return self.log.read_text() if self.log and self.log.exists() else ""


@dataclass
class Network:
    workdir: Path
    pki: TestPKIFactory
    daemon: AuthzDaemon
    rosmaster_uri: str
    hosts: dict[str, Host] = field(default_factory=dict)

    def ros_env(self, host: str | None) -> dict[str, str]:
        """Environment of an unmodified ROS node on ``host`` (None: straight to rosmaster)."""
        env = {k: v for k, v in os.environ.items() if not k.startswith("ROS_")}
        env.pop("PYTHONPATH", None)
        uri = self.hosts[host].master_uri if host else self.rosmaster_uri
        home = self.workdir / "ros_home"
        home.mkdir(exist_ok=True)
        env.update(ROS_MASTER_URI=uri, ROS_IP="127.0.0.1", ROS_HOME=str(home), PYTHONUNBUFFERED="1")
        return env

    def start(self, name: str) -> Host:
        host = self.hosts[name]
        host.log = self.workdir / f"interceptor-{name}.log"
        host.proc = subprocess.Popen(
            [script("cryptoros-interceptor"), "--config", str(host.config), "--log-level", "debug"],
            stdout=host.log.open("w"),
            stderr=subprocess.STDOUT,
        )
        wait_for_port(host.address, host.public_port, timeout=20, proc=host.proc)
        if "local_master" in host.config.read_text():  # the node role is configured
            wait_for_port("127.0.0.1", host.local_master_port, timeout=20, proc=host.proc)
        return host

    def stop(self, name: str) -> None:
        host = self.hosts[name]
        if host.proc is not None:
            stop(host.proc, timeout=10)

    def cli(self, *args: str):
        return authz(*args, db=self.daemon.db)


def interceptor_config(
    pki: TestPKIFactory, name: str, address: str, *, roles: list[str], public_port: int, local_master_port: int,
    metrics_port: int, master_endpoint: str, authz_url: str, upstream: str | None, extra: str = "",
) -> str:
    cert, key = pki.pki.cert_path_for(name), pki.pki.key_path_for(name)
    lines = [
        f'manager = "{name}"',
        f"roles = {roles!r}".replace("'", '"'),
        extra,
        "[tls]",
        f'ca = "{pki.ca_cert}"',
        f'cert = "{cert}"',
        f'key = "{key}"',
        f'crl = "{pki.crl}"',
        "[authz]",
        f'url = "{authz_url}"',
        "revocation_poll_interval = 0.5",
        "[listen]",
        f'public = "{address}:{public_port}"',
        f'metrics = "127.0.0.1:{metrics_port}"',
    ]
    if "node" in roles:
        lines.append(f'local_master = "127.0.0.1:{local_master_port}"')
    lines += ["[master]", 'manager = "master"', f'interceptor = "{master_endpoint}"']
    if upstream:
        lines.append(f'upstream = "{upstream}"')
    return "\n".join(lines) + "\n"


@contextlib.contextmanager
def robot_network(workdir: Path, *, policy: str = DEFAULT_POLICY, start: tuple[str, ...] = ("master", "robot_a", "robot_b"),
                  extra: dict[str, str] | None = None, roles: dict[str, list[str]] | None = None) -> Iterator[Network]:
    """PKI, registry, authz daemon, rosmaster and the interceptors named in ``start``."""
    rosmaster = require("rosmaster")["rosmaster"]
    pki = TestPKIFactory(workdir / "pki")
    fingerprints = {}
    for name, address in HOSTS.items():
        issued = pki.issue(name, kind="master" if name == "master" else "interceptor", sans=(f"IP:{address}",))
        fingerprints[name] = issued.fingerprint_sha256
    db = f"sqlite:///{workdir / 'registry.db'}"
    policy_file = workdir / "policy.yaml"
    policy_file.write_text(policy.format(**fingerprints))
    ok(authz("import", str(policy_file), db=db))
    daemon = AuthzDaemon(pki=pki, db=db, workdir=workdir)
    ros_port = free_port()
    master_proc = None
    net = None
    try:
        daemon.start()
        env = {k: v for k, v in os.environ.items() if not k.startswith("ROS_")}
        env.update(ROS_MASTER_URI=f"http://127.0.0.1:{ros_port}", ROS_HOME=str(workdir), ROS_IP="127.0.0.1")
        master_proc = subprocess.Popen([rosmaster, "--core", "-p", str(ros_port)], env=env,
                                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wait_for_port("127.0.0.1", ros_port, 15, master_proc)
        net = Network(workdir=workdir, pki=pki, daemon=daemon, rosmaster_uri=f"http://127.0.0.1:{ros_port}/")
        master_public = free_port(HOSTS["master"])
        for name, address in HOSTS.items():
            public = master_public if name == "master" else free_port(address)
            local_master, metrics = free_port(), free_port()
            config = workdir / f"{name}.toml"
            config.write_text(
                interceptor_config(
                    pki, name, address,
                    roles=(roles or {}).get(name) or (["master"] if name == "master" else ["node"]),
                    public_port=public, local_master_port=local_master, metrics_port=metrics,
                    master_endpoint=f"{HOSTS['master']}:{master_public}", authz_url=daemon.base,
                    upstream=f"http://127.0.0.1:{ros_port}" if "master" in ((roles or {}).get(name) or [name]) else None,
                    extra=(extra or {}).get(name, ""),
                )
            )
            net.hosts[name] = Host(name, address, public, local_master, metrics, config)
        for name in start:
            net.start(name)
        yield net
    finally:
        if net is not None:
            for name in net.hosts:
                net.stop(name)
        if master_proc is not None:
            stop(master_proc)
        daemon.stop()


def interceptor_toml_example() -> str:  # pragma: no cover - documentation aid
    return textwrap.dedent(interceptor_config.__doc__ or "")


# ------------------------------------------------------------------ a rogue peer
# What a compromised robot (or a stranger on the network) can do by hand: open TLS to
# an interceptor's public port with some certificate, send some preamble, then speak
# XML-RPC or TCPROS over the stream.

def rogue_tls(host: str, port: int, *, ca: Path, cert: Path | None, key: Path | None, timeout: float = 10):
    import socket
    import ssl

    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.check_hostname = False
    ctx.load_verify_locations(cafile=str(ca))
    if cert is not None:
        ctx.load_cert_chain(str(cert), str(key))
    raw = socket.create_connection((host, port), timeout=timeout)
    try:
        return ctx.wrap_socket(raw, server_hostname=host)
    except BaseException:
        raw.close()
        raise


def rogue_preamble(sock, token: str, purpose: str, target: str = ""):
    """Send a preamble; return the PreambleReply, or None if the peer just closed."""
    from cryptoros.tunnel import Preamble, PreambleReader, PreambleReply, encode

    sock.sendall(encode(Preamble(token=token, purpose=purpose, target=target)))
    reader = PreambleReader(PreambleReply)
    while True:
        data = sock.recv(65536)
        reader.receive_data(data)
        event = reader.next_event()
        if isinstance(event, PreambleReply):
            return event
        if not data:
            return None


def rogue_xmlrpc(sock, method: str, *params):
    from cryptoros.ros1.xmlrpc import NEED_DATA, Request, Role, XmlRpcConnection

    conn = XmlRpcConnection(Role.CLIENT)
    sock.sendall(conn.send(Request(method=method, params=params)))
    while (event := conn.next_event()) is NEED_DATA:
        conn.receive_data(sock.recv(65536))
    return event


def rogue_tcpros(sock, fields: dict[str, str]) -> dict[str, str]:
    from cryptoros.ros1.tcpros import ConnectionHeader, TCPROSConnection, encode_header

    sock.sendall(encode_header(fields))
    conn = TCPROSConnection()
    while True:
        event = conn.next_event()
        if isinstance(event, ConnectionHeader):
            return event.as_dict()
        data = sock.recv(65536)
        conn.receive_data(data)
        if not data:
            return {}


def signing_key(network: Network):
    """The daemon's real signing key (to forge tokens an attacker could not: expired...)."""
    from authz_server.db import open_registry
    from authz_server.keys import load_private, protection
    from authz_server.registry import Registry

    engine = open_registry(network.daemon.db)
    try:
        active = Registry(engine).active_key()
    finally:
        engine.dispose()
    key = load_private(active.private_pem, active.encrypted, protection(str(network.workdir / "signing.pass")),
                       active.kid)
    return key, active.kid
