"""A small robot network on loopback (no pytest, no tests/ import), used by the
benchmarks, the demo and (through ``tests/interceptor_harness.py``) the interceptor
tests, built from the installed package: a PKI (:class:`certs.pki.PKI`), a registry filled by ``cryptoros-authz
import``, a real ``cryptoros-authz serve`` daemon, Debian's ``rosmaster``, and one
``cryptoros-interceptor --config`` per host:

==========  ============  ==========================================
host        address       interceptor role
==========  ============  ==========================================
master      127.0.0.4     master (fronts rosmaster)
robot_a     127.0.0.2     node (publishers live here)
robot_b     127.0.0.3     node (subscribers live here)
==========  ============  ==========================================

Extra certificates (``stunnel_a``, ``stunnel_b``) are issued from the same CA for
the stunnel comparison. Every process is stopped in a ``finally``.
"""

from __future__ import annotations

import contextlib
import urllib.request
import ssl
import json
import os
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any
from dataclasses import dataclass, field
from pathlib import Path

from certs.pki import PKI
from cryptoros.lab.processes import NetworkError, free_port, stop, wait_port
from cryptoros.ros1.uri import host_port

HOSTS = {"master": "127.0.0.4", "robot_a": "127.0.0.2", "robot_b": "127.0.0.3"}
SIGNING_PASSPHRASE = "bench-signing-passphrase"


def tool(name: str) -> str:
    """A console script of this package (next to the running interpreter) or on PATH."""
    sibling = Path(sys.executable).parent / name
    if sibling.exists():
        return str(sibling)
    found = shutil.which(name)
    if found is None:
        raise NetworkError(f"{name} is not installed (pip install the cryptoros package)")
    return found


def open_stream(ctx: ssl.SSLContext, token: str, host: str, port: int, purpose: str, target: str = "") -> ssl.SSLSocket:
    """A stream to an interceptor's public port opened by hand (mutual TLS with ``ctx``,
    a preamble with ``token``), as a peer interceptor or an insider would; NetworkError
    when the interceptor closes or refuses it."""
    from cryptoros.tunnel import Preamble, PreambleReader, PreambleReply, encode

    sock = ctx.wrap_socket(socket.create_connection((host, port), timeout=10), server_hostname=host)
    try:
        sock.sendall(encode(Preamble(token=token, purpose=purpose, target=target)))
        reader = PreambleReader(PreambleReply)
        while not isinstance(event := reader.next_event(), PreambleReply):
            data = sock.recv(65536)
            if not data:
                raise NetworkError(f"{host}:{port} closed the {purpose} stream before its preamble reply")
            reader.receive_data(data)
        if not event.ok:
            raise NetworkError(f"{host}:{port} refused the {purpose} stream")
    except BaseException:
        sock.close()
        raise
    return sock


def cpu_seconds(pid: int) -> float | None:
    """utime + stime of a process (all its threads) from /proc/<pid>/stat; None if gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[1].split()  # after "pid (comm)": state is fields[0], utime fields[11]
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


#: Names the network namespace of the host a process belongs on (netns mode).
NETNS_ENV = "CRYPTOROS_NETNS"


def clean_env(**extra: str) -> dict[str, str]:
    """The environment without ROS_* and PYTHONPATH, plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("ROS_") and not k.startswith("CRYPTOROS_AUTHZ")}
    env.pop("PYTHONPATH", None)
    env.update(extra)
    return env


@dataclass
class Host:
    name: str
    address: str
    public_port: int
    local_master_port: int
    config: Path
    proc: subprocess.Popen | None = None
    log: Path | None = None
    metrics_port: int | None = None
    roles: tuple[str, ...] = ("node",)

    @property
    def master_uri(self) -> str:
        return f"http://127.0.0.1:{self.local_master_port}/"

    def logs(self) -> str:
        return self.log.read_text() if self.log and self.log.exists() else ""


@dataclass
class Network:
    workdir: Path
    pki: PKI
    rosmaster_uri: str
    authz_url: str
    hosts: dict[str, Host] = field(default_factory=dict)
    procs: list[subprocess.Popen] = field(default_factory=list)
    db: str = ""
    authz_proc: subprocess.Popen | None = None
    log_level: str = "warning"
    popen_extra: dict = field(default_factory=dict)
    #: In network-namespace mode: the lab, and each host's namespace host.
    lab: Any = None
    ns_hosts: dict[str, Any] = field(default_factory=dict)

    def _ns_host(self, host: str | None) -> Any:
        """``host``'s namespace host; None without namespaces (or for None). A name the
        lab does not know is an error, never this machine's own namespace: a stranger's
        routes and sysctls must not land here (:meth:`add_host` makes one)."""
        if not host or self.lab is None:
            return None
        if host not in self.ns_hosts:
            raise NetworkError(f"no host {host!r} in this lab (hosts: {', '.join(self.ns_hosts)}; see add_host)")
        return self.ns_hosts[host]

    def add_host(self, name: str) -> Any:
        """A host of no robot on the lab's network (a stranger): its own namespace and
        address, known to :meth:`argv` and :meth:`inside`. Namespace mode only."""
        if self.lab is None:
            raise NetworkError("add_host needs network namespaces (netns=True)")
        self.ns_hosts[name] = self.lab.add_host(name)
        return self.ns_hosts[name]

    def argv(self, host: str | None, argv: Sequence[str]) -> list[str]:
        """A command line that runs on ``host`` (as it is, without namespaces)."""
        ns_host = self._ns_host(host)
        return ns_host.argv(argv) if ns_host is not None else list(argv)

    @contextlib.contextmanager
    def inside(self, host: str | None) -> Iterator[None]:
        """Sockets opened in the block are on ``host`` (a no-op without namespaces)."""
        ns_host = self._ns_host(host)
        if ns_host is None:
            yield
        else:
            with ns_host.inside():
                yield

    def start(self, name: str, timeout: float = 30) -> Host:
        """Start (or restart) the interceptor of host ``name`` and wait until it listens."""
        host = self.hosts[name]
        host.log = self.workdir / f"interceptor-{name}.log"
        host.proc = subprocess.Popen(
            self.argv(name, [tool("cryptoros-interceptor"), "--config", str(host.config), "--log-level", self.log_level]),
            stdout=host.log.open("w"), stderr=subprocess.STDOUT, env=clean_env(), **self.popen_extra,
        )
        self.procs.append(host.proc)
        wait_port(host.address, host.public_port, timeout, host.proc, f"interceptor {name}")
        if "node" in host.roles:
            with self.inside(name):
                wait_port("127.0.0.1", host.local_master_port, timeout, host.proc, f"interceptor {name}")
        return host

    def stop(self, name: str) -> None:
        stop(self.hosts[name].proc, timeout=10)

    def ros_env(self, host: str | None, **extra: str) -> dict[str, str]:
        """Environment of an unmodified ROS node on ``host`` (None: straight to rosmaster).
        In namespace mode it names the host's namespace in ``CRYPTOROS_NETNS``, so a
        launcher that reads it (tests/support.py) starts the node on that host."""
        uri = self.hosts[host].master_uri if host else self.rosmaster_uri
        home = self.workdir / "ros_home"
        home.mkdir(exist_ok=True)
        ns_host = self.ns_hosts.get(host or "master")
        if ns_host is not None:
            extra = {**extra, NETNS_ENV: ns_host.ns}
        return clean_env(ROS_MASTER_URI=uri, ROS_IP="127.0.0.1", ROS_HOME=str(home), PYTHONUNBUFFERED="1", **extra)

    def learn(self, manager: str, seconds: float, timeout: float = 30) -> None:
        """Put ``manager`` in learning mode (``cryptoros-authz learn start``) and wait until
        its interceptor's ``/status`` says so (it needs a metrics endpoint)."""
        done = subprocess.run([tool("cryptoros-authz"), "--db", self.db, "learn", "start", manager, "--for",
                               f"{seconds:.0f}s"], capture_output=True, text=True, timeout=30)
        if done.returncode != 0:
            raise NetworkError(f"cryptoros-authz learn start {manager}: {done.stderr.strip() or done.stdout.strip()}")
        host = self.hosts[manager]
        deadline = time.monotonic() + timeout
        while True:
            with self.inside(manager), urllib.request.urlopen(
                    f"http://127.0.0.1:{host.metrics_port}/status", timeout=5) as reply:
                if json.loads(reply.read()).get("learning"):
                    return
            if time.monotonic() > deadline:
                raise NetworkError(f"interceptor {manager} did not say LEARNING within {timeout:g} s")
            time.sleep(0.2)

    def cert(self, name: str) -> tuple[Path, Path]:
        return self.pki.cert_path_for(name), self.pki.key_path_for(name)

    @property
    def ca(self) -> Path:
        return self.pki.ca_cert_path

    def client_of(self, name: str) -> tuple[ssl.SSLContext, str]:
        """A by-hand client holding ``name``'s certificate: its TLS context (the test CA,
        no hostname check) and a genuine access token fetched with it."""
        cert, key = self.cert(name)
        ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
        ctx.check_hostname = False
        ctx.load_verify_locations(cafile=str(self.ca))
        ctx.load_cert_chain(str(cert), str(key))
        opener = urllib.request.build_opener(urllib.request.HTTPSHandler(context=ctx))
        request = urllib.request.Request(f"{self.authz_url}/token", data=b"grant_type=client_credentials")
        with opener.open(request, timeout=10) as reply:
            return ctx, json.loads(reply.read())["access_token"]


#: The roscpp programs the tests run behind robots' interceptors (tests/ros1_nodes/*.cpp,
#: rosbag record and play): roscpp binds its XML-RPC API to every address whatever ROS_IP
#: says, so a robot's interceptor serves them only when listed (``allow_exposed_nodes``,
#: docs/interceptor.md, "Deployment checks"); a real robot closes their ports with a firewall.
ROSCPP_NODES = ("/roscpp_talker", "/roscpp_udp_listener", "/record_*", "/play_*")


#: The ``limits`` of a network whose benches measure throughput: no per-peer message rate
#: (the interceptors' default throttles a peer at ``DEFAULT_MESSAGES_PER_SECOND``, which a
#: sender publishing as fast as it can exceeds); every bench that uses it says so.
UNTHROTTLED: dict[str, float | bool] = {"max_messages_per_second": 0}


def _interceptor_config(
    pki: PKI, name: str, address: str, *, public_port: int, local_master_port: int, master_endpoint: str | None,
    authz_url: str, upstream: str | None, metrics_port: int | None = None, limits: dict[str, float | bool] | None = None,
    roles: Sequence[str] = ("node",), extra: str = "", poll_interval: float | None = None,
    ros2: tuple[int, Sequence[str], Path | None, Sequence[str], int] | None = None,
) -> str:
    lines = [
        f'manager = "{name}"',
        "roles = [" + ", ".join(f'"{r}"' for r in roles) + "]",
        *([f"allow_exposed_nodes = [{', '.join(repr(n) for n in ROSCPP_NODES)}]"] if "node" in roles else []),
        extra,
        "[tls]",
        f'ca = "{pki.ca_cert_path}"',
        f'cert = "{pki.cert_path_for(name)}"',
        f'key = "{pki.key_path_for(name)}"',
        f'crl = "{pki.crl_path}"',
        "[authz]",
        f'url = "{authz_url}"',
        *([f"revocation_poll_interval = {poll_interval}"] if poll_interval else []),
        "[listen]",
        f'public = "{address}:{public_port}"',
    ]
    if "node" in roles:
        lines.append(f'local_master = "127.0.0.1:{local_master_port}"')
    if metrics_port:
        lines.append(f'metrics = "127.0.0.1:{metrics_port}"')
    if master_endpoint is not None:
        lines += ["[master]", 'manager = "master"', f'interceptor = "{master_endpoint}"']
        if upstream:
            lines.append(f'upstream = "{upstream}"')
    if ros2 is not None:
        domain, peers, python, local, depth = ros2
        lines += ["[ros2]", f"domain_id = {domain}", "peers = [" + ", ".join(f'"{p}"' for p in peers) + "]",
                  "local = [" + ", ".join(f'"{p}"' for p in local) + "]", f"depth = {depth}",
                  "graph_interval = 0.25", *([f'python = "{python}"'] if python else [])]
    if limits:
        lines.append("[limits]")
        lines += [f"{k} = {str(v).lower() if isinstance(v, bool) else v}" for k, v in limits.items()]
    return "\n".join(lines) + "\n"


@contextlib.contextmanager
def lab_network(
    workdir: Path,
    policy: str,
    *,
    hosts: dict[str, str] | None = None,
    extra_certs: Sequence[tuple[str, str]] = (),
    log_level: str = "warning",
    progress: Callable[[str], None] = lambda _m: None,
    master: str = "rosmaster",
    metrics: bool = False,
    new_session: bool = False,
    limits: dict[str, float | bool] | None = None,
    roles: dict[str, Sequence[str]] | None = None,
    extra: dict[str, str] | None = None,
    start: Sequence[str] | None = None,
    poll_interval: float | None = None,
    ros2: dict[str, int] | None = None,
    ros2_python: Path | None = None,
    ros2_local: dict[str, Sequence[str]] | None = None,
    ros2_depth: int = 10,
    netns: bool = False,
) -> Iterator[Network]:
    """PKI, registry, authz daemon, rosmaster and the three interceptors.

    ``hosts`` maps host names to loopback addresses (default :data:`HOSTS`; ``master``
    is required and fronts rosmaster, every other host gets a node-role interceptor).
    ``policy`` is the registry YAML with one ``{name}`` placeholder per host for the
    certificate fingerprints. ``extra_certs`` are (name, address)
    pairs issued as interceptor certificates with an IP SAN (e.g. for stunnel).

    ``master``: ``"rosmaster"`` (Debian's, the default), ``"embedded"`` (``cryptoros
    master``: no ROS installation needed) or the ``http://`` URI of a master that is
    already running. ``metrics`` gives every interceptor a Prometheus port
    (:attr:`Host.metrics_port`); ``limits`` adds a ``[limits]`` table to every
    interceptor; ``new_session`` starts every child in its own process group.
    ``roles`` overrides a host's roles (default: ``master`` for the master host,
    ``node`` for the others), ``extra`` adds TOML lines to a host's configuration,
    ``start`` names the interceptors to start (default: all; the others can be
    started later with :meth:`Network.start`), ``poll_interval`` sets how often the
    interceptors poll the revocation feed.

    ``master="none"`` builds a network without ROS 1 (no master, no ``master`` host);
    ``ros2`` maps host names to ``ROS_DOMAIN_ID`` s: those hosts get the ``ros2`` role,
    each with every other ``ros2`` host as a peer, ``ros2_python`` as the bridge's
    python (default: the interceptor's, ``$CRYPTOROS_ROS2_PYTHON`` or ``.ros2-venv``) and
    ``ros2_local`` a host's ``[ros2] local`` patterns (names that never leave it), and
    ``ros2_depth`` their ``[ros2] depth``.

    ``netns=True`` (root only) puts every host in its own network namespace
    (:mod:`cryptoros.lab.netns`): its interceptor's public port on the host's bridge
    address (the ``hosts`` addresses are replaced), its local master, nodes and (on the
    master host) rosmaster on its own 127.0.0.1, and the authorization server on the
    lab's gateway address; :meth:`Network.argv` and :meth:`Network.inside` reach a
    host, ``net.lab.add_host`` adds one (a stranger).
    """
    rosmaster = None
    if master == "rosmaster":
        rosmaster = shutil.which("rosmaster")
        if rosmaster is None:
            raise NetworkError("rosmaster is not installed (scripts/install-system-parts)")
    elif master not in ("embedded", "none") and not master.startswith("http://"):
        raise NetworkError(f"master must be rosmaster, embedded, none or an http:// URI, not {master!r}")
    popen_extra = {"start_new_session": True} if new_session else {}
    hosts = dict(hosts or HOSTS)
    lab = None
    ns_hosts: dict[str, Any] = {}
    authz_host = "127.0.0.1"
    if netns:
        from cryptoros.lab.netns import NetnsLab, netns_unavailable

        reason = netns_unavailable()
        if reason is not None:
            raise NetworkError(f"network namespaces: {reason}")
        lab = NetnsLab()
        for name in hosts:
            ns_hosts[name] = lab.add_host(name)
            hosts[name] = ns_hosts[name].address
        authz_host = lab.gateway
    workdir.mkdir(parents=True, exist_ok=True)
    progress("PKI and registry")
    pki = PKI.init(workdir / "pki", unsafe_no_passphrase=True)
    fingerprints = {}
    for name, address in hosts.items():
        issued = pki.issue(name, kind="master" if name == "master" else "interceptor", sans=(f"IP:{address}",),
                           unsafe_no_passphrase=True)
        fingerprints[name] = issued.fingerprint_sha256
    for name, address in extra_certs:
        pki.issue(name, kind="interceptor", sans=(f"IP:{address}",), unsafe_no_passphrase=True)
    server = pki.issue("authz", kind="server", sans=("IP:127.0.0.1", "DNS:localhost", f"IP:{authz_host}"),
                       unsafe_no_passphrase=True)
    db = f"sqlite:///{workdir / 'registry.db'}"
    policy_file = workdir / "policy.yaml"
    policy_file.write_text(policy.format(**fingerprints))
    authz = tool("cryptoros-authz")
    env = clean_env()
    result = subprocess.run([authz, "--db", db, "import", str(policy_file)], capture_output=True, text=True,
                            timeout=60, env=env)
    if result.returncode != 0:
        if lab is not None:
            lab.close()
        raise NetworkError(f"cryptoros-authz import failed: {result.stderr.strip() or result.stdout.strip()}")
    procs: list[subprocess.Popen] = []
    net: Network | None = None
    try:
        progress("authorization server" + (" and rosmaster" if master == "rosmaster" else ""))
        taken: dict[str, set[int]] = {}  # ports handed out, per network namespace
        authz_port = free_port(authz_host, taken.setdefault("", set()))
        pass_file = workdir / "signing.pass"
        pass_file.unlink(missing_ok=True)
        pass_file.touch(mode=0o600)  # a secret: the server warns of one its group or others may read
        pass_file.write_text(SIGNING_PASSPHRASE + "\n")
        authz_log = (workdir / "authz.log").open("w")
        daemon = subprocess.Popen(
            [authz, "--db", db, "serve", "--host", authz_host, "--port", str(authz_port), "--ca", str(pki.ca_cert_path),
             "--cert", str(server.cert_path), "--key", str(server.key_path), "--crl", str(pki.crl_path),
             "--signing-key-passphrase-file", str(pass_file), "--log-level", "warning"],
            stdout=authz_log, stderr=subprocess.STDOUT, env=env, **popen_extra,
        )
        procs.append(daemon)
        master_proc = None
        ros_uri = ""
        if master.startswith("http://"):
            ros_uri = master.rstrip("/")
            ros_host, ros_port = host_port(ros_uri, ("http",))
        elif master != "none":
            ros_host = "127.0.0.1"
            # picked here, used in the master's namespace (fresh: free there too)
            ros_port = free_port(ros_host, taken.setdefault("master" if "master" in ns_hosts else "", set()))
            ros_uri = f"http://127.0.0.1:{ros_port}"
            if rosmaster is not None:
                master_env = clean_env(ROS_MASTER_URI=ros_uri, ROS_HOME=str(workdir), ROS_IP="127.0.0.1")
                master_cmd = [rosmaster, "--core", "-p", str(ros_port)]
            else:
                master_env = clean_env()
                master_cmd = [tool("cryptoros"), "master", "--host", "127.0.0.1", "--port", str(ros_port)]
            if "master" in ns_hosts:
                master_cmd = ns_hosts["master"].argv(master_cmd)
            master_proc = subprocess.Popen(master_cmd, env=master_env, stdout=subprocess.DEVNULL,
                                           stderr=subprocess.DEVNULL, **popen_extra)
            procs.append(master_proc)
        wait_port(authz_host, authz_port, 30, daemon, "cryptoros-authz", workdir / "authz.log")
        net = Network(workdir=workdir, pki=pki, rosmaster_uri=f"{ros_uri}/" if ros_uri else "",
                      authz_url=f"https://{authz_host}:{authz_port}", procs=procs, db=db, authz_proc=daemon,
                      log_level=log_level, popen_extra=popen_extra, lab=lab, ns_hosts=ns_hosts)
        if ros_uri:
            with net.inside("master"):
                wait_port(ros_host, ros_port, 15, master_proc, "ROS master")
        def port_on(name: str, address: str = "127.0.0.1") -> int:
            with net.inside(name):
                return free_port(address, taken.setdefault(name if name in ns_hosts else "", set()))

        master_public = port_on("master", hosts["master"]) if "master" in hosts else None
        interceptor = tool("cryptoros-interceptor")
        metrics_ports = {name: port_on(name) if metrics else None for name in hosts}
        publics = {name: master_public if name == "master" else port_on(name, address) for name, address in hosts.items()}
        ros2 = ros2 or {}
        for name, address in hosts.items():
            public = publics[name]
            local_master = port_on(name)
            default_roles = ["ros2"] if name in ros2 else ["master"] if name == "master" else ["node"]
            host_roles = tuple((roles or {}).get(name) or default_roles)
            peers = [f"{hosts[p]}:{publics[p]}" for p in ros2 if p != name]
            config = workdir / f"{name}.toml"
            config.write_text(_interceptor_config(
                pki, name, address, public_port=public, local_master_port=local_master,
                master_endpoint=f"{hosts['master']}:{master_public}" if master_public else None, authz_url=net.authz_url,
                upstream=ros_uri if "master" in host_roles else None,
                metrics_port=metrics_ports[name], limits=limits,
                roles=host_roles, extra=(extra or {}).get(name, ""), poll_interval=poll_interval,
                ros2=(ros2[name], peers, ros2_python, (ros2_local or {}).get(name, ()), ros2_depth) if name in ros2 else None,
            ))
            net.hosts[name] = Host(name, address, public, local_master, config, metrics_port=metrics_ports[name],
                                   roles=host_roles)
        progress("interceptors")
        started = list(net.hosts) if start is None else list(start)
        for name in started:  # start all, then wait for all: they come up in parallel
            host = net.hosts[name]
            host.log = workdir / f"interceptor-{name}.log"
            host.proc = subprocess.Popen(
                net.argv(name, [interceptor, "--config", str(host.config), "--log-level", log_level]),
                stdout=host.log.open("w"), stderr=subprocess.STDOUT, env=env, **popen_extra,
            )
            procs.append(host.proc)
        for name in started:
            host = net.hosts[name]
            # a ros2 interceptor listens once its DDS bridge is up (BRIDGE_START_TIMEOUT, 30 s)
            wait_port(host.address, host.public_port, 40, host.proc, f"interceptor {name}", host.log)
            if "node" in host.roles:
                with net.inside(name):
                    wait_port("127.0.0.1", host.local_master_port, 30, host.proc, f"interceptor {name}", host.log)
        yield net
    finally:
        for proc in reversed(net.procs if net is not None else procs):
            stop(proc, timeout=10)
        if lab is not None:
            lab.close()


__all__ = ["HOSTS", "Host", "Network", "NetworkError", "lab_network", "clean_env", "cpu_seconds", "free_port",
           "open_stream", "stop",
           "tool", "wait_port"]
