"""The interceptor's deployment checks: rosmaster and local nodes on loopback only.

Processes behind an interceptor are trusted because nothing but this host reaches them.
A rosmaster or node that listens on a non-loopback address (rosmaster and rospy do
without ``ROS_IP=127.0.0.1``) is reachable from other hosts past every check: the
master's interceptor refuses to serve such a rosmaster, a robot's interceptor refuses
such a node's registrations (docs/interceptor.md, "Deployment checks"). Loopback itself
answers other hosts when the kernel routes 127.0.0.0/8 from the network
(``route_localnet``, :func:`localnet_problem`): then the master's interceptor refuses
its rosmaster the same way, and a robot's interceptor refuses every call to its local
master (a stranger reaches that port too) and every endpoint its nodes announce.

What the kernel says about a port (:mod:`cryptoros.exposure`) is kept for :data:`TTL`
seconds, so a node's many registrations and ``requestTopic`` replies cost a dict
lookup; a port not seen listening is asked again at once (a node announces a port only
once it listens, so a fresh port is never judged from an older answer). The
``route_localnet`` settings are kept as long.
"""

from __future__ import annotations

import asyncio
import fnmatch
import re
import socket
import time
from collections.abc import Callable, Mapping
from pathlib import Path

from cryptoros.errors import PolicyDenied
from cryptoros.exposure import (
    ExposureError,
    Listener,
    is_loopback_host,
    localnet_routed,
    read_listeners,
    read_route_localnet,
    route_localnet_fix,
    sysctl_name,
)
from cryptoros.lru import remember
from cryptoros.ros1.uri import UriError, host_port
from cryptoros.ros1.xmlrpc import Request

#: seconds a port's answer is reused
TTL = 1.0
#: ports whose answers are kept
MAX_PORTS = 4096


def localnet_problem(conf: Mapping[str, str | int]) -> str | None:
    """Why every loopback port of this host answers other hosts, in one line naming the
    settings and the fix, or None: ``conf`` is what
    :func:`~cryptoros.exposure.read_route_localnet` reads (ExposureError when it does
    not parse)."""
    routed = localnet_routed(conf)
    if not routed:
        return None
    settings = " and ".join(f"{sysctl_name(name)}={str(conf[name]).strip()}" for name in routed)
    return (f"{settings}: the kernel accepts packets for 127.0.0.0/8 from the network, so other hosts reach every "
            f"loopback port of this host (rosmaster, nodes, the interceptor's local master) past every check: run "
            f"'{route_localnet_fix(conf)}' and remove the setting from /etc/sysctl.conf and /etc/sysctl.d "
            f"(kube-proxy, and Docker with --userland-proxy=false, set it)")


class PortExposure:
    """``exposed(port)``: the non-loopback addresses a port listens on (empty: loopback
    only, or not listening). The kernel is asked about that port alone (its sockets in
    LISTEN, filtered by the kernel: the cost does not grow with the host's other
    listeners, the interceptor's relays among them); a port seen listening keeps its
    answer for :data:`TTL` seconds (at most :data:`MAX_PORTS` ports, the oldest
    forgotten first). ``loopback_problem()``: whether loopback itself answers other
    hosts (``route_localnet``), kept as long. ``read``, ``read_localnet`` and ``clock``
    are injectable."""

    def __init__(self, read: Callable[[int], list[Listener]] = read_listeners,
                 clock: Callable[[], float] = time.monotonic, ttl: float = TTL,
                 read_localnet: Callable[[], Mapping[str, str | int]] = read_route_localnet) -> None:
        self._read, self._clock, self._ttl, self._read_localnet = read, clock, ttl, read_localnet
        self._answers: dict[int, tuple[float, list[str]]] = {}
        self._localnet: tuple[float, str | None] | None = None
        self.reads = 0
        self.localnet_reads = 0

    def loopback_problem(self) -> str | None:
        """:func:`localnet_problem` of this network namespace's settings, read at most
        once per :data:`TTL`. Raises :class:`~cryptoros.exposure.ExposureError` when
        they cannot be read (not kept: asked again next time)."""
        now = self._clock()
        if self._localnet is None or now - self._localnet[0] >= self._ttl:
            problem = localnet_problem(self._read_localnet())
            self.localnet_reads += 1
            self._localnet = (now, problem)
        return self._localnet[1]

    def exposed(self, port: int) -> list[str]:
        """Raises :class:`~cryptoros.exposure.ExposureError` when the kernel cannot be asked."""
        now = self._clock()
        kept = self._answers.get(port)
        if kept is not None and now - kept[0] < self._ttl:
            return kept[1]
        listeners = [one for one in self._read(port) if one.port == port]
        self.reads += 1
        addresses = sorted({str(one.address) for one in listeners if one.exposed})
        if listeners:
            remember(self._answers, port, (now, addresses), MAX_PORTS)
        else:  # not listening: asked again next time (a port is announced once it listens)
            self._answers.pop(port, None)
        return addresses

    def sockets(self, port: int) -> frozenset[int]:
        """The exposed sockets on ``port`` now (their inodes; empty: none), read afresh:
        whether the process served on a port still holds it. Raises
        :class:`~cryptoros.exposure.ExposureError` when the kernel cannot be asked."""
        self.reads += 1
        return frozenset(one.inode for one in self._read(port) if one.port == port and one.exposed)


def _announced(uri: object) -> tuple[str, int]:
    """(host, port) of an endpoint a node announced (a ROS URI, or an IPv6 ``http://`` one
    without brackets); UriError otherwise."""
    try:
        return host_port(uri)
    except UriError:
        return lenient_host_port(uri)


def lenient_host_port(uri: object) -> tuple[str, int]:
    """(host, port) of an ``http://`` URI a node announced, taking the IPv6 address rospy
    writes without brackets (``http://fd06::3:41255/``) too; UriError otherwise."""
    try:
        return host_port(uri, ("http",))
    except UriError:
        match = re.fullmatch(r"http://\[?([0-9A-Fa-f:.]+)\]?:(\d{1,5})/?", uri) if isinstance(uri, str) else None
        if match is None or not 0 < int(match.group(2)) < 65536:
            raise
        return match.group(1), int(match.group(2))


async def is_this_host(host: str) -> bool:
    """Whether ``host`` (a name or address a node announced) is this host: loopback, or
    resolving to an address a socket here can bind (only a host's own addresses can)."""
    if is_loopback_host(host):
        return True
    try:
        infos = await asyncio.get_running_loop().getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except OSError:
        return False
    for family, _type, _proto, _name, address in infos:
        try:
            with socket.socket(family, socket.SOCK_STREAM) as probe:
                probe.bind((address[0], 0))
            return True
        except OSError:
            continue
    return False


def run_hint(config: Path | None, command: str) -> str:
    """How to start ``command`` with this interceptor's environment."""
    return f"cryptoros run --config {config or 'FILE'} -- {command}"


def master_problem(upstream: str, exposure: PortExposure, config: Path | None) -> str | None:
    """Why the rosmaster at ``upstream`` (a loopback URI of this host) must not be
    served, in one line, or None. A table that cannot be read is a problem too."""
    try:
        host, port = host_port(upstream, ("http",))
    except UriError:
        return None  # config.py accepts only http://host:port
    if not is_loopback_host(host):
        return (f"rosmaster ({upstream}) is at a non-loopback address, reachable from other hosts past every "
                f"check: run it on this host on loopback only (ROS_IP=127.0.0.1 rosmaster --core -p {port}) and "
                f"point [master] upstream at 127.0.0.1, or set allow_exposed_master = true")
    try:
        addresses = exposure.exposed(port)
        localnet = None if addresses else exposure.loopback_problem()
    except ExposureError as exc:
        return f"cannot tell whether rosmaster ({upstream}) answers other hosts: {exc}"
    if localnet is not None:
        return f"rosmaster ({upstream}) answers other hosts on loopback: {localnet}, or set allow_exposed_master = true"
    if not addresses:
        return None
    return (f"rosmaster ({upstream}) listens on {', '.join(addresses)} port {port}, so other hosts reach it past "
            f"every check: restart it on loopback only (ROS_IP=127.0.0.1 rosmaster --core -p {port}, or "
            f"{run_hint(config, f'rosmaster --core -p {port}')}), or set allow_exposed_master = true")


def _node_refusal(node: str, what: str, port: int, addresses: list[str], config: Path | None,
                  advertised: str | None) -> str:
    where = f"node {node}'s {what} listens on {', '.join(addresses)} port {port}, reachable from other hosts"
    if advertised is not None and is_loopback_host(advertised):
        # ROS_IP is set and the node binds every address all the same: roscpp's XML-RPC server
        return (f"{where}, though it announces {advertised} (roscpp binds its XML-RPC API to every address "
                f"whatever ROS_IP says): close the node's ports to the network with the host's firewall, then list "
                f"it in allow_exposed_nodes")
    return f"{where}: start it with ROS_IP=127.0.0.1 ({run_hint(config, 'CMD')})"


#: where a local node's master call names its own endpoints: index -> what it is
REGISTRATION_URIS: dict[str, tuple[tuple[int, str], ...]] = {
    "registerPublisher": ((3, "XML-RPC API"),),
    "registerSubscriber": ((3, "XML-RPC API"),),
    "registerService": ((2, "service port"), (3, "XML-RPC API")),
    "subscribeParam": ((1, "XML-RPC API"),),
}


class NodeGuard:
    """The node role's check of the endpoints its local nodes announce. An endpoint
    other hosts reach is refused (PolicyDenied ``exposed_endpoint``) unless the node
    matches a pattern of ``allow_exposed_nodes`` (the operator closed its ports with a
    firewall, which no socket table shows): then it is served and remembered, with the
    sockets it listens on, for the status warning (at most :data:`MAX_NOTED` nodes) for as
    long as those sockets listen: a node that exited is forgotten, and a process that
    binds its port later is judged as itself. While loopback itself answers other
    hosts (``route_localnet``) every call to the local master is refused, and every
    endpoint, allowed nodes' too: the fix is one sysctl, and the local master, which a
    stranger reaches as well, is no node a firewall note could cover."""

    MAX_NOTED = 1024
    #: seconds a node asked to shut down (:meth:`exposed_apis`) is not named again: a
    #: starting node's several registrations are refused one after the other
    ASK_AGAIN_AFTER = 10.0
    #: a node name found exposed again within this many seconds of the last time is a
    #: repeat (a launch file's ``respawn="true"`` starts it again at once): asked to shut
    #: down without the first time's delay, and named in the status for as long
    REPEAT_WINDOW = 600.0

    def __init__(self, exposure: PortExposure | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.exposure = exposure or PortExposure()
        # (node, port) -> (addresses, the exposed sockets then listening), served exposed
        self._served: dict[tuple[str, int], tuple[str, frozenset[int]]] = {}
        self._named: dict[tuple[str, int], float] = {}  # (node, port) -> when exposed_apis last named it
        self._running: set[tuple[str, int]] = set()  # refused nodes that could not be asked to shut down
        self._repeats: dict[str, tuple[int, float]] = {}  # node name -> (times found exposed, last time)
        self._clock = clock

    def check_port(self, node: str | Callable[[], str], port: int, what: str, *, allow: tuple[str, ...],
                   config: Path | None, advertised: str | None = None) -> str | None:
        """None when ``port`` answers on loopback only; a warning line the first time an
        allowed node is seen exposed on it; PolicyDenied otherwise. ``node`` may be a
        callable, asked only when the port is exposed; ``advertised``: the host the node
        announces with the port (it picks the fix the refusal names)."""
        try:
            addresses = self.exposure.exposed(port)
            localnet = None if addresses else self.exposure.loopback_problem()
        except ExposureError as exc:
            name = node() if callable(node) else node
            raise PolicyDenied("exposed_endpoint", f"cannot tell whether node {name}'s {what} (port {port}) answers "
                                                   f"other hosts: {exc}") from None
        if localnet is not None:
            name = node() if callable(node) else node
            raise PolicyDenied("exposed_endpoint", f"node {name}'s {what} (port {port}) is on loopback, which other "
                                                   f"hosts reach: {localnet}")
        if not addresses:
            return None
        name = node() if callable(node) else node
        if not any(fnmatch.fnmatchcase(name, pattern) for pattern in allow):
            raise PolicyDenied("exposed_endpoint", _node_refusal(name, what, port, addresses, config, advertised))
        if (name, port) in self._served and self._holds(name, port):
            return None
        if len(self._served) >= self.MAX_NOTED:
            self._prune_served()
            if len(self._served) >= self.MAX_NOTED:
                return None
        try:
            sockets = self.exposure.sockets(port)
        except ExposureError:
            sockets = frozenset()  # not kept: asked again on the node's next registration
        if sockets:
            self._served[(name, port)] = (", ".join(addresses), sockets)
        return (f"allow_exposed_nodes: node {name}'s {what} listens on {', '.join(addresses)} port {port}, served "
                f"(its ports must be closed to the network by the host's firewall)")

    def _holds(self, node: str, port: int) -> bool:
        """Whether the sockets ``node`` was served on still listen on ``port`` (kept while
        that cannot be told); forgotten when they do not."""
        try:
            now = self.exposure.sockets(port)
        except ExposureError:
            return True
        if now & self._served[(node, port)][1]:
            return True
        del self._served[(node, port)]
        return False

    def _prune_served(self) -> None:
        for node, port in list(self._served):
            self._holds(node, port)

    def check_host(self) -> None:
        """PolicyDenied (``exposed_endpoint``) while this host's loopback answers other
        hosts, or whether it does cannot be told: a call to the local master may then
        come from a stranger (its answer shows the robot's graph, its registrations are
        made with the robot's certificate)."""
        try:
            problem = self.exposure.loopback_problem()
        except ExposureError as exc:
            raise PolicyDenied("exposed_endpoint", f"cannot tell whether this host's loopback (the local master "
                                                   f"among it) answers other hosts: {exc}") from None
        if problem is not None:
            raise PolicyDenied("exposed_endpoint", f"local master calls refused, this host's loopback answers other "
                                                   f"hosts: {problem}")

    def check_registrations(self, calls: list[Request], *, allow: tuple[str, ...], config: Path | None) -> list[str]:
        """Every request to the local master (a request, or the calls of a multicall):
        :meth:`check_host`, then :meth:`check_port` for every endpoint the registrations
        among ``calls`` announce; the new warnings."""
        if calls:
            self.check_host()
        warnings = []
        for call in calls:
            for index, what in REGISTRATION_URIS.get(call.method, ()):
                if len(call.params) <= index or not isinstance(call.params[0], str):
                    continue
                try:
                    host, port = _announced(call.params[index])
                except UriError:
                    continue  # left to the policy that checks the call
                warning = self.check_port(call.params[0], port, what, allow=allow, config=config, advertised=host)
                if warning:
                    warnings.append(warning)
        return warnings

    def exposed_apis(self, calls: list[Request], *, allow: tuple[str, ...]) -> list[tuple[str, int, str, bool]]:
        """(node, port, announced host, repeat) of each XML-RPC API that registrations
        among ``calls`` announce and that other hosts reach, of a node not in ``allow`` and
        on no port an allowed node was served on and still listens on (a local process
        naming an allowed node's port in its own registration gets it no shutdown): the nodes a refused registration
        leaves running exposed, each once within :data:`ASK_AGAIN_AFTER`. ``repeat``: the
        node name was found exposed before, within :data:`REPEAT_WINDOW`. Uses the answers
        :meth:`check_port` just read."""
        found: list[tuple[str, int, str, bool]] = []
        for call in calls:
            for index, what in REGISTRATION_URIS.get(call.method, ()):
                if what != "XML-RPC API" or len(call.params) <= index or not isinstance(call.params[0], str):
                    continue
                try:
                    host, port = _announced(call.params[index])
                    exposed = self.exposure.exposed(port)
                except (UriError, ExposureError):
                    continue
                node = call.params[0]
                if not exposed or any(fnmatch.fnmatchcase(node, p) for p in allow) or self._allowed_port(port):
                    continue
                repeat = self.to_ask(node, port)
                if repeat is not None:
                    found.append((node, port, host, repeat))
        return found

    def _allowed_port(self, port: int) -> bool:
        """Whether an allowed node served on ``port`` still listens there."""
        return any(self._holds(node, served) for node, served in list(self._served) if served == port)

    def to_ask(self, node: str, port: int) -> bool | None:
        """Whether the exposed process of ``node`` on ``port`` is to be asked to shut down
        now: None if it was within :data:`ASK_AGAIN_AFTER`, else whether its name is a
        repeat (found exposed before, within :data:`REPEAT_WINDOW`); noted either way."""
        now = self._clock()
        if now - self._named.get((node, port), -self.ASK_AGAIN_AFTER) < self.ASK_AGAIN_AFTER:
            return None
        remember(self._named, (node, port), now, self.MAX_NOTED)
        times, last = self._repeats.get(node, (0, now - 2 * self.REPEAT_WINDOW))
        repeat = now - last < self.REPEAT_WINDOW
        remember(self._repeats, node, (times + 1 if repeat else 1, now), self.MAX_NOTED)
        return repeat

    def still_running(self, node: str, port: int) -> None:
        """A refused node that could not be asked to shut down: named in :meth:`warnings`
        for as long as its port answers other hosts."""
        if len(self._running) < self.MAX_NOTED:
            self._running.add((node, port))

    def warnings(self) -> list[str]:
        """The status lines: loopback answering other hosts (``route_localnet``), refused
        nodes still listening where other hosts reach them, and the nodes served exposed
        (empty: none of these)."""
        try:
            problem = self.exposure.loopback_problem()
            host = [f"this host's loopback answers other hosts: {problem}"] if problem is not None else []
        except ExposureError as exc:
            host = [f"cannot tell whether this host's loopback answers other hosts: {exc}"]
        for node, port in sorted(self._running):
            try:
                gone = not self.exposure.exposed(port)
            except ExposureError:
                gone = False
            if gone:
                self._running.discard((node, port))
        if self._running:
            host.append("refused nodes still listening where other hosts reach them (they could not be asked to shut "
                        "down: stop them): " + ", ".join(f"{n} (port {p})" for n, p in sorted(self._running)[:8]))
        now = self._clock()
        again = sorted((node, times) for node, (times, last) in self._repeats.items()
                       if times > 1 and now - last < self.REPEAT_WINDOW)
        if again:
            host.append("nodes started again and again where other hosts reach them, each time refused and shut down "
                        "(a launch file's respawn?); other hosts reach each for a moment every time: " +
                        ", ".join(f"{node} ({times} times)" for node, times in again[:8]) +
                        "; start them on loopback (cryptoros run, no __ip/ROS_IP of the network) or stop them")
        self._prune_served()
        if not self._served:
            return host
        named = ", ".join(f"{node} ({where} port {port})" for (node, port), (where, _sockets)
                          in list(self._served.items())[:8])
        more = len(self._served) - 8
        served = f"allow_exposed_nodes: served with ports other hosts reach unless a firewall closes them: {named}"
        return host + [served + (f" and {more} more" if more > 0 else "")]


__all__ = ["MAX_PORTS", "REGISTRATION_URIS", "TTL", "NodeGuard", "PortExposure", "is_this_host", "lenient_host_port",
           "localnet_problem", "master_problem", "run_hint"]
