"""Which participants of a robot's DDS domain are reachable from the network.

rclpy (the PyPI wheels: Fast DDS, no DDS Security) tells nothing of a participant's
locators: the graph has node names, endpoint GIDs and QoS only, and Fast DDS's builtin
participant topic is not exposed. What the host does tell is where each process's
sockets are bound. A participant on domain ``d`` binds its RTPS ports in
``7400 + 250 d`` to ``7400 + 250 d + 249`` (the RTPS port mapping); with cryptoros's
localhost profile every one of them is on 127.0.0.1, and one started without it (the
built-in transports) binds them on every interface, which is also what it announces
in discovery. So a socket of that range bound to anything but loopback is a
participant of the domain that a stranger on the network can talk to.

The process is then matched to the graph through the endpoint GID: Fast DDS puts the
low 16 bits of its process id in bytes 4 and 5 (little-endian) of every GUID prefix
(measured on Fast DDS 2.14: pid 27809 = 0x6ca1, prefix ``010f 4037 a16c ...``). Two
processes sharing those 16 bits are both treated as reachable (fail closed).

Linux only (``/proc/net/udp``, ``/proc/<pid>/fd``); another user's processes are seen
by root only: an interceptor run as another user reports such a socket with pid None.
"""

from __future__ import annotations

import ipaddress
import os
from dataclasses import dataclass, field
from pathlib import Path

from cryptoros.exposure import ephemeral_ports, is_exposed, proc_net_address

PORT_BASE, DOMAIN_GAIN, PORTS_PER_DOMAIN = 7400, 250, 250
Address = ipaddress.IPv4Address | ipaddress.IPv6Address


@dataclass(frozen=True)
class Exposed:
    """One process with sockets of the domain bound beyond loopback."""

    pid: int | None
    command: str
    sockets: tuple[str, ...] = field(default_factory=tuple)

    @property
    def pid16(self) -> int | None:
        return None if self.pid is None else self.pid & 0xFFFF

    def describe(self) -> str:
        who = f"pid {self.pid} ({self.command})" if self.pid is not None else "a process of another user"
        return f"{who} bound to {', '.join(self.sockets)}"


def domain_ports(domain: int) -> range:
    base = PORT_BASE + DOMAIN_GAIN * domain
    return range(base, base + PORTS_PER_DOMAIN)


def ephemeral_overlap(domain: int, local_range: str | None = None) -> range | None:
    """The ports of ``domain``'s DDS range that lie in this host's ephemeral range (where
    the kernel puts every socket bound to port 0), or None. Fast DDS keeps sending sockets
    on such ports beside its participants', beyond loopback whatever its profile; one that
    lands in the domain's range is taken for a participant reachable from the network (a
    ROS 2 audit: a talker on domain 181 so flagged, and its topic not carried, in one
    start of a few). ``local_range``: the text of ``ip_local_port_range`` (read if None)."""
    low, high = ephemeral_ports(local_range)
    ports = domain_ports(domain)
    start, stop = max(ports.start, low), min(ports.stop, high + 1)
    return range(start, stop) if start < stop else None


def highest_private_domain(local_range: str | None = None) -> int:
    """The highest domain whose DDS ports all lie below this host's ephemeral range
    (100 with Linux's default 32768-60999)."""
    low, _high = ephemeral_ports(local_range)
    return max(-1, (low - PORT_BASE - PORTS_PER_DOMAIN) // DOMAIN_GAIN)


def parse_udp(text: str) -> list[tuple[Address, int, int]]:
    """``(address, port, inode)`` of every socket in a ``/proc/net/udp`` or ``udp6`` text."""
    out = []
    for line in text.splitlines()[1:]:
        fields = line.split()
        if len(fields) < 10 or ":" not in fields[1]:
            continue
        addr, port = fields[1].rsplit(":", 1)
        out.append((proc_net_address(addr), int(port, 16), int(fields[9])))
    return out


def _pretty(address: Address) -> str:
    if isinstance(address, ipaddress.IPv6Address):
        return str(address.ipv4_mapped) if address.ipv4_mapped is not None else f"[{address}]"
    return str(address)


def exposed_inodes(sockets: list[tuple[Address, int, int]], domain: int) -> dict[int, str]:
    """inode -> ``address:port`` of the sockets of ``domain``'s RTPS ports not on loopback."""
    ports = domain_ports(domain)
    return {inode: f"{_pretty(addr)}:{port}" for addr, port, inode in sockets if port in ports and is_exposed(addr)}


def socket_owners(inodes: set[int], proc: Path) -> dict[int, int]:
    """inode -> pid of the processes (that this user may read) holding those sockets."""
    wanted = {f"socket:[{i}]": i for i in inodes}
    owners: dict[int, int] = {}
    for entry in os.scandir(proc):
        if not entry.name.isdigit():
            continue
        try:
            for fd in os.scandir(f"{entry.path}/fd"):
                inode = wanted.get(os.readlink(fd.path))
                if inode is not None:
                    owners[inode] = int(entry.name)
        except OSError:  # gone, or another user's
            continue
    return owners


def _command(pid: int, proc: Path) -> str:
    try:
        argv = (proc / str(pid) / "cmdline").read_bytes().split(b"\0")
    except OSError:
        return "?"
    return " ".join(a.decode(errors="replace") for a in argv if a)[:120]


class ExposureScan:
    """The domain's participants reachable from the network, read from ``proc``. The
    socket tables are read on every :meth:`scan` (a few KB); processes' descriptors only
    when the set of exposed sockets changed."""

    def __init__(self, domain: int, proc: Path = Path("/proc")) -> None:
        self.domain = domain
        self.proc = proc
        self._last: dict[int, str] = {}
        self._found: tuple[Exposed, ...] = ()

    def scan(self) -> tuple[Exposed, ...]:
        sockets: list[tuple[Address, int, int]] = []
        for name in ("udp", "udp6"):
            try:
                sockets += parse_udp((self.proc / "net" / name).read_text())
            except OSError:
                continue
        inodes = exposed_inodes(sockets, self.domain)
        if inodes != self._last:
            self._last = inodes
            owners = socket_owners(set(inodes), self.proc) if inodes else {}
            by_pid: dict[int | None, list[str]] = {}
            for inode, where in sorted(inodes.items(), key=lambda kv: kv[1]):
                by_pid.setdefault(owners.get(inode), []).append(where)
            self._found = tuple(Exposed(pid, _command(pid, self.proc) if pid is not None else "?", tuple(where))
                                for pid, where in sorted(by_pid.items(), key=lambda kv: (kv[0] is None, kv[0] or 0)))
        return self._found


def busy_domains(sockets: list[tuple[Address, int, int]]) -> set[int]:
    """Domains (0..232) with at least one socket bound in their RTPS port range."""
    return {(port - PORT_BASE) // DOMAIN_GAIN for _, port, _ in sockets
            if PORT_BASE <= port < PORT_BASE + DOMAIN_GAIN * 233}


def bound_domains(proc: Path = Path("/proc")) -> set[int]:
    """Domains with a socket bound in their RTPS port range on this host now."""
    sockets: list[tuple[Address, int, int]] = []
    for name in ("udp", "udp6"):
        try:
            sockets += parse_udp((proc / "net" / name).read_text())
        except OSError:
            continue
    return busy_domains(sockets)


def free_domains(count: int, start: int, proc: Path = Path("/proc"), top: int | None = None,
                 low: int = 0) -> list[int]:
    """``count`` consecutive domain ids in ``low``..``top`` (default: the highest below the
    ephemeral ports, :func:`highest_private_domain`) none of whose ports is bound now,
    searched from ``start`` (wrapping): a benchmark or test on a shared host then does
    not join another session's domain, whose endpoints would match its own (a reader that
    stopped taking blocks a reliable KEEP_ALL writer). Falls back to ``start``'s run."""
    top = highest_private_domain() if top is None else top
    busy = bound_domains(proc)
    span = top + 2 - low - count
    first = (start - low) % span
    for offset in range(span):
        base = low + (first + offset) % span
        if not busy & set(range(base, base + count)):
            return list(range(base, base + count))
    return list(range(low + first, low + first + count))


def gid_pid16(gid_hex: str) -> int | None:
    """The low 16 bits of the process id a Fast DDS endpoint GID carries (bytes 4-5)."""
    try:
        raw = bytes.fromhex(gid_hex)
    except ValueError:
        return None
    if len(raw) < 6 or raw[:2] != b"\x01\x0f":  # eProsima's vendor id: only Fast DDS lays it out so
        return None
    return int.from_bytes(raw[4:6], "little")


__all__ = ["Exposed", "ExposureScan", "bound_domains", "busy_domains", "domain_ports", "ephemeral_overlap", "free_domains", "highest_private_domain", "exposed_inodes", "gid_pid16", "parse_udp"]
