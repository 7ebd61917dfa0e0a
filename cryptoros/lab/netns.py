"""Separate hosts on one machine: a Linux network namespace per host.

Every test host on one machine shares one loopback, so a node port bound to
127.0.0.1 on "robot A" is reachable by every other "host". Real robots do not share
a loopback. :class:`NetnsLab` gives each host its own namespace with its own loopback
and one address on a private bridge (``10.77.N.0/24``, N chosen per lab), as robots
on a LAN have: a service bound to 127.0.0.1 inside a host answers that host only.

Needs root and iproute2 (``ip``). Everything a lab makes is named with its own
prefix and deleted on :meth:`NetnsLab.close`, even after a failure. Processes run on
a host through :meth:`NetnsHost.argv` (``ip netns exec``); code in this process
opens sockets on a host inside :meth:`NetnsHost.inside` (the calling thread enters
the namespace for the block: a socket keeps the namespace it was made in).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import re
import shutil
import subprocess
import threading
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

from cryptoros.errors import CryptorosError

CLONE_NEWNET = 0x40000000
_NETNS_DIR = "/run/netns"


class NetnsError(CryptorosError):
    """A namespace could not be made or entered."""


def _ip(*args: str) -> None:
    result = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)
    if result.returncode != 0:
        raise NetnsError(f"ip {' '.join(args)}: {result.stderr.strip() or result.stdout.strip()}")


def _subnets_on_this_machine() -> set[int]:
    """The N of every 10.77.N.0/24 an interface of this namespace holds already: another
    process's lab (or one a killed run left behind) with the same subnet would take the
    route, and this lab's hosts would not reach the gateway (timeouts, not refusals)."""
    result = subprocess.run(["ip", "-4", "-o", "addr", "show"], capture_output=True, text=True, timeout=30)
    return {int(m) for m in re.findall(r"\binet 10\.77\.(\d+)\.\d+/", result.stdout)}


def netns_unavailable() -> str | None:
    """None when namespaces can be made here, else why not (one line)."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("ip") is None:
        return "iproute2 ('ip') is not installed"
    probe = f"crp{uuid.uuid4().hex[:8]}"
    try:
        _ip("netns", "add", probe)
    except NetnsError as exc:
        return f"cannot create a network namespace: {exc}"
    with contextlib.suppress(NetnsError):
        _ip("netns", "del", probe)
    return None


@dataclass(frozen=True)
class NetnsHost:
    """One host: its namespace and its address on the lab's bridge."""

    name: str
    ns: str
    address: str

    def argv(self, argv: Sequence[str]) -> list[str]:
        """A command line that runs ``argv`` on this host."""
        return ["ip", "netns", "exec", self.ns, *argv]

    @contextlib.contextmanager
    def inside(self) -> Iterator[None]:
        """Run the block with the calling thread in this host's namespace."""
        libc = ctypes.CDLL(None, use_errno=True)
        with open(f"/proc/self/task/{threading.get_native_id()}/ns/net") as home, open(os.path.join(_NETNS_DIR, self.ns)) as there:
            if libc.setns(there.fileno(), CLONE_NEWNET) != 0:
                raise NetnsError(f"cannot enter {self.ns}: {os.strerror(ctypes.get_errno())}")
            try:
                yield
            finally:
                if libc.setns(home.fileno(), CLONE_NEWNET) != 0:  # pragma: no cover - the kernel keeps ours
                    raise NetnsError(f"cannot leave {self.ns}: {os.strerror(ctypes.get_errno())}")


_SUBNETS_IN_USE: set[int] = set()


@dataclass
class NetnsLab:
    """A bridge and the hosts on it. Use as a context manager."""

    prefix: str = field(default_factory=lambda: f"cr{uuid.uuid4().hex[:5]}")
    subnet_index: int | None = None
    hosts: dict[str, NetnsHost] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if len(self.prefix) > 8:
            raise NetnsError("the prefix must be at most 8 characters (interface names are short)")
        if self.subnet_index is None:
            # a subnet no other lab of this process uses, spread over 20..219 by prefix
            index = 20 + int(uuid.uuid5(uuid.NAMESPACE_DNS, self.prefix).hex[:4], 16) % 200
            taken = _SUBNETS_IN_USE | _subnets_on_this_machine()  # no other lab of any process
            if len(taken) >= 200:
                raise NetnsError("every 10.77.N.0/24 (N 20..219) is in use: delete labs left behind "
                                 "(ip netns list; ip link show type bridge)")
            while index in taken:
                index = 20 + (index - 19) % 200
            self.subnet_index = index
        _SUBNETS_IN_USE.add(self.subnet_index)
        self._bridge = f"{self.prefix}br"
        self._made_bridge = False
        try:
            _ip("link", "add", self._bridge, "type", "bridge")
            self._made_bridge = True
            # a MAC of its own: a bridge otherwise takes the lowest of its ports' MACs, so a
            # host added later (a stranger) could change it, and every host's ARP entry of
            # the gateway (the authorization server's address) went stale: timeouts
            _ip("link", "set", self._bridge, "address", self._bridge_mac())
            _ip("addr", "add", f"{self.gateway}/24", "dev", self._bridge)
            _ip("link", "set", self._bridge, "up")
        except BaseException:
            self.close()
            raise

    def _bridge_mac(self) -> str:
        """A locally administered unicast MAC, one per lab (from its prefix)."""
        digest = uuid.uuid5(uuid.NAMESPACE_DNS, self.prefix).bytes
        return ":".join(f"{b:02x}" for b in (0x02, 0x77, *digest[:4]))

    @property
    def gateway(self) -> str:
        """The bridge's address in this (the root) namespace: every host reaches it."""
        return f"10.77.{self.subnet_index}.1"

    def add_host(self, name: str) -> NetnsHost:
        """A new host: own namespace, loopback up, one address on the bridge."""
        if name in self.hosts:
            raise NetnsError(f"host {name} exists already")
        n = len(self.hosts) + 2
        host = NetnsHost(name=name, ns=f"{self.prefix}{n}", address=f"10.77.{self.subnet_index}.{n}")
        veth = f"{self.prefix}v{n}"
        _ip("netns", "add", host.ns)
        self.hosts[name] = host
        _ip("link", "add", veth, "type", "veth", "peer", "name", "eth0", "netns", host.ns)
        _ip("link", "set", veth, "master", self._bridge, "up")
        _ip("-n", host.ns, "link", "set", "lo", "up")
        _ip("-n", host.ns, "addr", "add", f"{host.address}/24", "dev", "eth0")
        _ip("-n", host.ns, "link", "set", "eth0", "up")
        return host

    def close(self) -> None:
        """Delete every namespace and the bridge this lab made (by name only)."""
        for host in list(self.hosts.values()):
            with contextlib.suppress(NetnsError):
                _ip("netns", "del", host.ns)
        self.hosts.clear()
        if self._made_bridge:
            with contextlib.suppress(NetnsError):
                _ip("link", "del", self._bridge)
            self._made_bridge = False
        _SUBNETS_IN_USE.discard(self.subnet_index)

    def __enter__(self) -> NetnsLab:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["NetnsError", "NetnsHost", "NetnsLab", "netns_unavailable"]
