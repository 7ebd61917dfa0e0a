"""A small robot network on one machine for the interceptor tests (no tests here).

Hosts are loopback addresses: the master's interceptor on 127.0.0.4 in front of a
real Debian ``rosmaster``, robot A's interceptor on 127.0.0.2, robot B's on
127.0.0.3, each with its own certificate (IP SAN of its host) and its own manager in
the registry of a real ``cryptoros-authz`` daemon. Every process is real and is
stopped in a ``finally``.
"""

from __future__ import annotations

import contextlib
import queue
import subprocess
import threading
import time
import xmlrpc.client
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from cryptoros.lab.network import Network as BenchNetwork
from cryptoros.lab.network import lab_network
from cryptoros.lab.policy import policy_yaml
from tests.authz_support import AuthzDaemon, authz_here
from tests.pki_fixtures import TestPKIFactory
from tests.support import missing, require

SYS_PY = "/usr/bin/python3"
NODES = Path(__file__).parent / "ros1_nodes"
NODE = str(Path(__file__).parent / "interceptor_nodes" / "node.py")
STRING = "std_msgs/String"
STRING_MD5 = "992ce8a1687cec8c8bd883ec73ca41d1"

#: Policy of the default network: robot_a's talker publishes /chatter, robot_b's
#: listener subscribes to it; robot_b may call robot_a's service.
DEFAULT_GRANTS = {
    "master": {},
    "robot_a": {"publish": [("/rospy_talker", "/chatter", STRING), ("/roscpp_talker", "/chatter", STRING),
                            ("/talker_a", "/chatter", STRING), ("/talker_a", "/secret", STRING)],
                "subscribe": [("/victim", "/chatter", STRING)],
                "serve": [("/rospy_server", "/rospy_loggers", "roscpp/GetLoggers")]},
    "robot_b": {"subscribe": [("/rospy_listener", "/chatter", STRING), ("/victim", "/chatter", STRING),
                              ("*", "/chatter", STRING)],
                "call": [("/rospy_client", "/rospy_loggers", "roscpp/GetLoggers")]},
    "robot_c": {},
}
DEFAULT_POLICY = policy_yaml(DEFAULT_GRANTS)

HOSTS = {"master": "127.0.0.4", "robot_a": "127.0.0.2", "robot_b": "127.0.0.3", "robot_c": "127.0.0.5"}


@dataclass
class Network:
    """The network of :func:`cryptoros.lab.network.lab_network`, with what tests
    need on top: the PKI as a :class:`TestPKIFactory`, the daemon as an
    :class:`AuthzDaemon` (tokens over real mTLS), the admin CLI."""

    net: BenchNetwork
    pki: TestPKIFactory
    daemon: AuthzDaemon

    def __getattr__(self, name: str):  # workdir, hosts, rosmaster_uri, ros_env, start, stop
        return getattr(self.net, name)

    def cli(self, *args: str):
        return authz_here(*args, db=self.daemon.db)


def separate_hosts() -> bool:
    """Whether this run gives each test host its own network namespace (as real robots
    have their own loopback). As root they do; without root the tests that need it
    skip with the reason (and fail under CI=true, which runs as root)."""
    from cryptoros.lab.netns import netns_unavailable

    reason = netns_unavailable()
    if reason is not None:
        missing(f"separate hosts (network namespaces): {reason}")
    return True


@contextlib.contextmanager
def robot_network(workdir: Path, *, policy: str = DEFAULT_POLICY, start: tuple[str, ...] = ("master", "robot_a", "robot_b"),
                  extra: dict[str, str] | None = None, roles: dict[str, list[str]] | None = None,
                  netns: bool = False, limits: dict[str, float | bool] | None = None) -> Iterator[Network]:
    """PKI, registry, authz daemon, rosmaster and the interceptors named in ``start``
    (the others can be started with ``network.start(name)``). ``netns=True`` puts each
    host in its own network namespace (:func:`separate_hosts` decides whether it can)."""
    require("rosmaster")
    with lab_network(
        workdir, policy, hosts=HOSTS, master="rosmaster", metrics=True, log_level="debug", poll_interval=0.5,
        start=start, extra=extra, roles=roles, netns=netns, limits=limits,
    ) as net:
        pki = TestPKIFactory(net.pki.directory, pki=net.pki)
        host, port = net.authz_url[len("https://"):].rsplit(":", 1)
        daemon = AuthzDaemon(pki=pki, db=net.db, workdir=workdir, port=int(port), host=host, proc=net.authz_proc)
        yield Network(net=net, pki=pki, daemon=daemon)


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
    from cryptoros.tunnel import Preamble, encode

    sock.sendall(encode(Preamble(token=token, purpose=purpose, target=target)))
    return rogue_reply(sock)


def rogue_reply(sock):
    """The PreambleReply the peer sends, or None if it closed (or reset) first."""
    from cryptoros.tunnel import PreambleReader, PreambleReply

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


# ------------------------------------------------------------------ helpers of the insider and day-2 tests

def token_of(network, name: str) -> str:
    """A genuine access token of manager ``name``, straight from the daemon."""
    status, body = network.daemon.token(name)
    assert status == 200, body
    return body["access_token"]


def rogue_to(network, host: str, as_name: str):
    """TLS to ``host``'s public port with ``as_name``'s valid certificate."""
    h = network.hosts[host]
    return rogue_tls(h.address, h.public_port, ca=network.pki.ca_cert, cert=network.pki.pki.cert_path_for(as_name),
                     key=network.pki.pki.key_path_for(as_name))


def denials(network, host: str) -> str:
    return "\n".join(line for line in network.hosts[host].logs().splitlines() if "DENY" in line)


def wait_registered(network, node: str, timeout: float = 20) -> None:
    """Until rosmaster itself lists ``node`` (as publisher, subscriber or server)."""
    import time
    import xmlrpc.client

    deadline = time.monotonic() + timeout
    while True:
        with network.inside("master"):
            state = xmlrpc.client.ServerProxy(network.rosmaster_uri).getSystemState("/test")[2]
        if node in {n for section in state for _name, nodes in section for n in nodes}:
            return
        assert time.monotonic() < deadline, f"{node} never registered"
        time.sleep(0.1)


def rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError(f"no VmRSS for {pid}")


def open_fds(pid: int) -> int:
    import os

    return len(os.listdir(f"/proc/{pid}/fd"))


def dribble(socks, data: bytes, steps: int = 20) -> set[int]:
    """Send ``data`` one byte a second on every socket (a preamble slowloris); returns
    the indexes of the sockets the other side had not closed after ``steps`` bytes."""
    import socket as socketmod
    import ssl
    import time

    open_ = set(range(len(socks)))
    for step in range(steps):
        for i in list(open_):
            try:
                socks[i].sendall(data[step:step + 1])
                socks[i].settimeout(0.01)
                if socks[i].recv(100) == b"":
                    open_.discard(i)
            except socketmod.timeout:
                pass
            except (OSError, ssl.SSLError):
                open_.discard(i)
        if not open_:
            break
        time.sleep(1)
    return open_


# ------------------------------------------------------------------ reading the nodes' output

def read_lines(proc: subprocess.Popen, until: str | None, timeout: float) -> list[str]:
    """A process's output lines until one contains ``until`` (None: until timeout or EOF).

    A thread drains stdout into a queue (a select() on a buffered pipe would miss lines
    already sitting in Python's buffer)."""
    lines = getattr(proc, "_line_queue", None)
    if lines is None:
        lines = proc._line_queue = queue.Queue()

        def pump() -> None:
            for line in proc.stdout:
                lines.put(line)
            lines.put(None)

        threading.Thread(target=pump, daemon=True).start()
    seen: list[str] = []
    deadline = time.monotonic() + timeout
    while (left := deadline - time.monotonic()) > 0:
        try:
            line = lines.get(timeout=left)
        except queue.Empty:
            break
        if line is None:
            lines.put(None)  # keep the end marker for later calls
            break
        seen.append(line)
        if until is not None and until in line:
            return seen
    if until is not None:
        raise AssertionError(f"no {until!r} within {timeout}s; output:\n{''.join(seen)}")
    return seen


def got(lines: list[str]) -> list[str]:
    return [line.split(" ", 1)[1].strip() for line in lines if line.startswith("GOT ")]


def master_state(network) -> list:
    """getSystemState straight from the real rosmaster (what it really holds)."""
    with network.inside("master"):
        return xmlrpc.client.ServerProxy(network.rosmaster_uri).getSystemState("/test")[2]


def nodes_in_state(state) -> set[str]:
    return {node for section in state for _name, nodes in section for node in nodes}


def run_on(network, host: str, args: list[str], **extra: str) -> subprocess.CompletedProcess:
    """``args`` run on lab host ``host`` (its namespace), ROS_HOME in the lab's work dir."""
    from cryptoros.lab.network import clean_env

    env = clean_env(ROS_HOME=str(network.workdir / "ros_home"), **extra)
    return subprocess.run(network.argv(host, args), capture_output=True, text=True, timeout=60, env=env)


def reaches(network, host: str, address: str, port: int) -> bool:
    """Whether a TCP connection from ``host`` to ``address:port`` is accepted."""
    import socket

    with network.inside(host):
        try:
            socket.create_connection((address, port), timeout=2).close()
            return True
        except OSError:
            return False


def status_text(network, host: str) -> str:
    """What ``cryptoros status`` prints on ``host`` about its interceptor."""
    from cryptoros.lab.network import tool

    return run_on(network, host, [tool("cryptoros"), "status", "--config", str(network.hosts[host].config)]).stdout
