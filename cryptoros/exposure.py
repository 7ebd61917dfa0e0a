"""Which TCP ports of this host answer other hosts: the kernel's listening sockets.

The deployment invariant of cryptoros is that rosmaster and every ROS node of a host
listen on loopback only (docs/interceptor.md, "Deployment checks"). Whether they do is
read from the kernel, not guessed from an environment variable: the TCP sockets in
LISTEN of the reading process's network namespace. One bound to ``0.0.0.0``, ``::`` or
any non-loopback address is reachable from outside this host.

Two views of the same kernel table, each with a pure parser unit-tested on sample input:

- ``sock_diag`` netlink (what ``ss -lt`` asks): a dump of the LISTEN sockets only,
  :func:`parse_sock_diag` (bytes in, listeners out). Measured on this project's
  2-core machines: 0.25 ms for both families.
- ``/proc/net/tcp`` and ``/proc/net/tcp6``: :func:`parse_proc_net_tcp` (text in,
  listeners out). The kernel walks every socket hash bucket to write them: measured
  here, 21 ms per file (42 ms both), so it is only the fallback where netlink is
  refused (some sandboxes).

:func:`read_listeners` is the thin reader over both.

A socket bound to loopback answers other hosts too when the kernel accepts packets for
``127.0.0.0/8`` from the network: ``net.ipv4.conf.<interface>.route_localnet`` (set by
kube-proxy, and by Docker with ``--userland-proxy=false``). :func:`localnet_routed`
judges the settings (pure), :func:`read_route_localnet` reads them from
``/proc/sys/net/ipv4/conf``. IPv6 has no such setting: the kernel drops a packet for
``::1`` that arrives on a non-loopback interface, whatever any sysctl says
(``ip6_rcv_core``, RFC 4291 2.5.3).
"""

from __future__ import annotations

import ipaddress
import os
import socket
import struct
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from cryptoros.errors import CryptorosError

#: the ``st`` column of a socket in LISTEN (include/net/tcp_states.h: TCP_LISTEN = 10)
_LISTEN = "0A"
PROC_NET = Path("/proc/net")
#: one directory per interface, and ``all`` and ``default``, each with a ``route_localnet``
PROC_SYS_CONF = Path("/proc/sys/net/ipv4/conf")


class ExposureError(CryptorosError):
    """The listening sockets could not be read or parsed: whether a port is exposed is
    unknown (callers fail closed)."""


@dataclass(frozen=True, kw_only=True)
class Listener:
    """One TCP socket in LISTEN: the address it is bound to, its port and its inode (which
    socket it is: another bound to the same port later has another)."""

    address: ipaddress.IPv4Address | ipaddress.IPv6Address
    port: int
    inode: int = 0

    @property
    def exposed(self) -> bool:
        """Reachable from other hosts: bound to a wildcard or a non-loopback address."""
        return is_exposed(self.address)


def is_exposed(address: ipaddress.IPv4Address | ipaddress.IPv6Address) -> bool:
    """A socket bound to ``address`` is reachable from other hosts: a wildcard or a
    non-loopback address (an IPv4-mapped IPv6 address judged as its IPv4 one)."""
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped
    return not address.is_loopback


def proc_net_address(hex_text: str, byteorder: str = sys.byteorder) -> ipaddress.IPv4Address | ipaddress.IPv6Address:
    """The address of a ``/proc/net/{tcp,udp}{,6}`` line (ValueError when it is not one)."""
    # The kernel prints each 32-bit word of the address as a number in host byte order.
    raw = bytes.fromhex(hex_text)
    if len(raw) not in (4, 16):
        raise ValueError(f"address of {len(raw)} bytes")
    if byteorder == "little":
        raw = b"".join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4))
    return ipaddress.ip_address(raw)


def parse_proc_net_tcp(text: str, *, byteorder: str = sys.byteorder) -> list[Listener]:
    """The sockets in LISTEN of one ``/proc/net/tcp`` or ``/proc/net/tcp6`` text (the
    header line and sockets in any other state are skipped). ``byteorder`` is the
    machine's that wrote the text. A LISTEN line that does not parse raises
    :class:`ExposureError`: an unknown socket is never taken for a private one."""
    listeners = []
    for number, line in enumerate(text.splitlines()[1:], start=2):
        fields = line.split()
        if len(fields) < 4 or fields[3] != _LISTEN:
            continue
        address_hex, colon, port_hex = fields[1].partition(":")
        try:
            if not colon:
                raise ValueError("no port")
            listeners.append(Listener(address=proc_net_address(address_hex, byteorder), port=int(port_hex, 16),
                                      inode=int(fields[9]) if len(fields) > 9 else 0))
        except ValueError as exc:
            raise ExposureError(f"line {number} of the socket table does not parse ({exc}): {line.strip()[:80]}") from None
    return listeners


# linux/netlink.h, linux/sock_diag.h, linux/inet_diag.h
_NETLINK_SOCK_DIAG = 4
_SOCK_DIAG_BY_FAMILY = 20
_NLM_F_REQUEST, _NLM_F_DUMP = 0x1, 0x300
_NLMSG_ERROR, _NLMSG_DONE = 2, 3
_NLMSG = struct.Struct("=IHHII")  # len, type, flags, seq, pid
#: inet_diag_req_v2: family, protocol, ext, pad, states, then inet_diag_sockid (48 bytes)
_REQUEST = struct.Struct("=BBBBI48x")
#: inet_diag_msg: family, state, timer, retrans, then sockid: sport, dport (big endian), src[16]
_DIAG_MSG = struct.Struct("=BBBB2H16s")
#: where inet_diag_msg's idiag_inode is (after the 48-byte sockid, expires, rqueue, wqueue, uid)
_DIAG_INODE = struct.Struct("=68xI")
_TCP_LISTEN = 10
#: the request's filter (attribute INET_DIAG_REQ_BYTECODE): a program of inet_diag_bc_op
#: (code, yes, no); ``yes``/``no`` are the bytes to skip, and a socket is kept when the
#: program ends exactly at its end (so ``no`` = what is left + 4 rejects)
_INET_DIAG_REQ_BYTECODE = 1
_BC_S_GE, _BC_S_LE = 2, 3
_BC_OP = struct.Struct("=BBH")


def sock_diag_request(family: int, port: int | None = None, seq: int = 1) -> bytes:
    """The netlink request for the TCP sockets in LISTEN of ``family`` (AF_INET or
    AF_INET6); with ``port``, only those on that local port (the kernel filters: source
    port >= port and <= port, comparisons every kernel since 2.6 has)."""
    body = _REQUEST.pack(family, socket.IPPROTO_TCP, 0, 0, 1 << _TCP_LISTEN)
    if port is not None:
        program = (_BC_OP.pack(_BC_S_GE, 8, 20) + _BC_OP.pack(0, 0, port)
                   + _BC_OP.pack(_BC_S_LE, 8, 12) + _BC_OP.pack(0, 0, port))
        body += struct.pack("=HH", 4 + len(program), _INET_DIAG_REQ_BYTECODE) + program
    return _NLMSG.pack(_NLMSG.size + len(body), _SOCK_DIAG_BY_FAMILY, _NLM_F_REQUEST | _NLM_F_DUMP, seq, 0) + body


def parse_sock_diag(data: bytes) -> tuple[list[Listener], bool]:
    """The listeners in one datagram of a ``sock_diag`` dump, and whether the dump is
    done (``NLMSG_DONE`` seen). An error message or a truncated one raises
    :class:`ExposureError`."""
    listeners = []
    offset = 0
    while offset < len(data):
        if len(data) - offset < _NLMSG.size:
            raise ExposureError("truncated netlink message")
        length, kind = _NLMSG.unpack_from(data, offset)[:2]
        if length < _NLMSG.size or offset + length > len(data):
            raise ExposureError(f"netlink message of {length} bytes in {len(data) - offset}")
        if kind == _NLMSG_DONE:
            return listeners, True
        if kind == _NLMSG_ERROR:
            code = struct.unpack_from("=i", data, offset + _NLMSG.size)[0] if length >= _NLMSG.size + 4 else 0
            raise ExposureError(f"sock_diag refused: {os.strerror(-code) if code < 0 else code}")
        if kind == _SOCK_DIAG_BY_FAMILY:
            if length < _NLMSG.size + _DIAG_MSG.size:
                raise ExposureError("truncated inet_diag message")
            family, state, _, _, sport, _, src = _DIAG_MSG.unpack_from(data, offset + _NLMSG.size)
            if state == _TCP_LISTEN and family in (socket.AF_INET, socket.AF_INET6):
                raw = src[:4] if family == socket.AF_INET else src
                inode = (_DIAG_INODE.unpack_from(data, offset + _NLMSG.size)[0]
                         if length >= _NLMSG.size + _DIAG_INODE.size else 0)
                listeners.append(Listener(address=ipaddress.ip_address(raw), port=socket.ntohs(sport), inode=inode))
        offset += (length + 3) & ~3
    return listeners, False


def _read_sock_diag(family: int, port: int | None) -> list[Listener]:
    with socket.socket(socket.AF_NETLINK, socket.SOCK_RAW, _NETLINK_SOCK_DIAG) as sock:
        sock.settimeout(2.0)
        sock.sendto(sock_diag_request(family, port), (0, 0))
        listeners: list[Listener] = []
        while True:
            found, done = parse_sock_diag(sock.recv(1 << 16))
            listeners += found
            if done:
                return listeners


def read_listeners(port: int | None = None, proc_net: Path = PROC_NET) -> list[Listener]:
    """The TCP sockets in LISTEN of this network namespace (IPv4 and IPv6), all or those
    on ``port``, from ``sock_diag``; where netlink is refused, from ``/proc/net/tcp`` and
    ``tcp6`` (a host without IPv6 has no ``tcp6``, which is fine). :class:`ExposureError`
    when neither can be read."""
    try:
        return _read_sock_diag(socket.AF_INET, port) + _read_sock_diag(socket.AF_INET6, port)
    except (OSError, ExposureError):
        pass
    listeners: list[Listener] = []
    for name in ("tcp", "tcp6"):
        try:
            text = (proc_net / name).read_text(encoding="ascii")
        except FileNotFoundError:
            if name == "tcp6":
                continue
            raise ExposureError(f"cannot read {proc_net / name}: no such file (not Linux?)") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ExposureError(f"cannot read {proc_net / name}: {exc}") from None
        listeners += parse_proc_net_tcp(text)
    return listeners if port is None else [one for one in listeners if one.port == port]


#: Linux's default ``net.ipv4.ip_local_port_range``
DEFAULT_EPHEMERAL = (32768, 60999)


def ephemeral_ports(text: str | None = None) -> tuple[int, int]:
    """The kernel's range of ephemeral ports (where a socket bound to port 0 lands), from
    ``text`` or ``/proc/sys/net/ipv4/ip_local_port_range``; Linux's default when unread."""
    try:
        if text is None:
            text = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text()
        low, high = (int(n) for n in text.split()[:2])
        return low, high
    except (OSError, ValueError):
        return DEFAULT_EPHEMERAL


def is_loopback_host(host: str) -> bool:
    """``localhost`` or a loopback address (127.0.0.0/8, ::1); a name is not."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def exposed_addresses(listeners: list[Listener], port: int) -> list[str]:
    """The non-loopback addresses (``0.0.0.0`` and ``::`` included) a socket listens on
    at ``port``, sorted; empty: that port answers on loopback only, or not at all."""
    return sorted({str(one.address) for one in listeners if one.port == port and one.exposed})


def _localnet_values(conf: Mapping[str, str | int]) -> dict[str, int]:
    values = {}
    for name, value in conf.items():
        try:
            values[name] = int(str(value).strip())
        except ValueError:
            raise ExposureError(f"route_localnet of {name} is not a number: {str(value).strip()[:20]!r}") from None
    if "all" not in values:
        raise ExposureError("no route_localnet of 'all' (not Linux?)")
    return values


def localnet_routed(conf: Mapping[str, str | int]) -> list[str]:
    """The settings that make this host's loopback (127.0.0.0/8) reachable from other
    hosts: ``all`` and each interface but ``lo`` whose ``route_localnet`` is not 0
    (``all`` first, then by name); empty: loopback answers this host only. ``conf``: the
    ``route_localnet`` of ``all``, ``default`` and each interface (name -> the file's
    text or a number). The kernel routes a packet for 127.0.0.0/8 that arrives on an
    interface when ``all`` or that interface has it (``IN_DEV_ROUTE_LOCALNET`` is an
    ``IN_DEV_ORCONF``), so ``all`` alone opens every interface; ``default`` is only what
    interfaces made later start with (a new one shows its own value), and ``lo`` carries
    nothing from other hosts. A value that is not a number, or no ``all``, raises
    :class:`ExposureError` (unknown is never taken for private)."""
    values = _localnet_values(conf)
    interfaces = sorted(name for name, value in values.items() if value and name not in ("all", "default", "lo"))
    return (["all"] if values["all"] else []) + interfaces


def sysctl_name(interface: str) -> str:
    """The ``sysctl`` name of an interface's ``route_localnet`` (a dot in an interface
    name, a VLAN's ``eth0.100``, is written ``/``)."""
    return f"net.ipv4.conf.{interface.replace('.', '/')}.route_localnet"


def route_localnet_fix(conf: Mapping[str, str | int]) -> str:
    """The command that stops the routing :func:`localnet_routed` finds: every setting
    it names set to 0, and ``default`` too when it is set (interfaces made later would
    start with it)."""
    values = _localnet_values(conf)
    names = localnet_routed(conf) + (["default"] if values.get("default") else [])
    names.sort(key=lambda name: (name != "all", name != "default", name))
    return "sysctl -w " + " ".join(f"{sysctl_name(name)}=0" for name in names)


def read_route_localnet(conf_dir: Path = PROC_SYS_CONF) -> dict[str, str]:
    """The ``route_localnet`` of ``all``, ``default`` and each interface of this network
    namespace (name -> the file's text), for :func:`localnet_routed`. An interface gone
    while it is read is left out; :class:`ExposureError` when the directory or ``all``
    cannot be read."""
    try:
        names = os.listdir(conf_dir)
    except OSError as exc:
        raise ExposureError(f"cannot read {conf_dir}: {exc.strerror or exc}") from None
    conf = {}
    for name in names:
        try:
            conf[name] = (conf_dir / name / "route_localnet").read_text(encoding="ascii")
        except FileNotFoundError:
            if name == "all":
                raise ExposureError(f"cannot read {conf_dir / name / 'route_localnet'}: no such file") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ExposureError(f"cannot read {conf_dir / name / 'route_localnet'}: {exc}") from None
    if "all" not in conf:
        raise ExposureError(f"cannot read {conf_dir / 'all' / 'route_localnet'}: no such file")
    return conf


__all__ = ["DEFAULT_EPHEMERAL", "ephemeral_ports", "ExposureError", "Listener", "PROC_NET", "PROC_SYS_CONF", "exposed_addresses", "is_exposed",
           "is_loopback_host", "localnet_routed", "parse_proc_net_tcp", "proc_net_address", "read_route_localnet",
           "route_localnet_fix", "sysctl_name",
           "parse_sock_diag", "read_listeners", "sock_diag_request"]
