"""The interceptor's deployment checks: rosmaster and local nodes on loopback only.

Processes behind an interceptor are trusted because nothing but this host reaches them.
A rosmaster or node that listens on a non-loopback address (rosmaster and rospy do
without ``ROS_IP=127.0.0.1``) is reachable from other hosts past every check: the
master's interceptor refuses to serve such a rosmaster, a robot's interceptor refuses
such a node's registrations (docs/interceptor.md, "Deployment checks").

What the kernel says (:mod:`cryptoros.exposure`) is cached per port for
:data:`TTL` seconds, so a node's many registrations and ``requestTopic`` replies cost a
dict lookup; a port not seen listening is asked again at once (a node announces a port
only once it listens, so a fresh port is never judged from an older table).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from cryptoros.errors import PolicyDenied
from cryptoros.exposure import ExposureError, Listener, exposed_addresses, is_loopback_host, read_listeners
from cryptoros.ros1.uri import UriError, host_port
from cryptoros.ros1.xmlrpc import Request

#: seconds a port's answer is reused
TTL = 1.0
#: ports remembered at most (a table read refreshes them all)
MAX_PORTS = 65536


class PortExposure:
    """``exposed(port)``: the non-loopback addresses a port listens on (empty: loopback
    only, or not listening). Reads the socket table at most once per :data:`TTL` for
    ports it has seen listening; ``read`` and ``clock`` are injectable."""

    def __init__(self, read: Callable[[], list[Listener]] = read_listeners,
                 clock: Callable[[], float] = time.monotonic, ttl: float = TTL) -> None:
        self._read, self._clock, self._ttl = read, clock, ttl
        self._table: dict[int, list[str]] = {}
        self._read_at = float("-inf")
        self.reads = 0

    def exposed(self, port: int) -> list[str]:
        """Raises :class:`~cryptoros.exposure.ExposureError` when the table cannot be read."""
        now = self._clock()
        if port not in self._table or now - self._read_at >= self._ttl:
            listeners = self._read()
            self.reads += 1
            ports = {one.port for one in listeners}
            self._table = {p: exposed_addresses(listeners, p) for p in list(ports)[:MAX_PORTS]}
            self._read_at = now
        return self._table.get(port, [])


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
    except ExposureError as exc:
        return f"cannot tell whether rosmaster ({upstream}) answers other hosts: {exc}"
    if not addresses:
        return None
    return (f"rosmaster ({upstream}) listens on {', '.join(addresses)} port {port}, so other hosts reach it past "
            f"every check: restart it on loopback only (ROS_IP=127.0.0.1 rosmaster --core -p {port}, or "
            f"{run_hint(config, f'rosmaster --core -p {port}')}), or set allow_exposed_master = true")


def check_node_endpoint(node: str, uri: str, what: str, exposure: PortExposure, config: Path | None) -> None:
    """PolicyDenied ``exposed_endpoint`` when the local ``uri`` (``what``: "XML-RPC API",
    "TCPROS port", "service") listens where other hosts reach it; a URI that does not
    parse is left to the policy that checks it."""
    try:
        _, port = host_port(uri)
    except UriError:
        return
    check_node_port(node, port, what, exposure, config)


def check_node_port(node: str, port: int, what: str, exposure: PortExposure, config: Path | None) -> None:
    """As :func:`check_node_endpoint`, for a port."""
    try:
        addresses = exposure.exposed(port)
    except ExposureError as exc:
        raise PolicyDenied("exposed_endpoint", f"cannot tell whether node {node}'s {what} (port {port}) answers "
                                               f"other hosts: {exc}") from None
    if addresses:
        raise PolicyDenied("exposed_endpoint", f"node {node}'s {what} listens on {', '.join(addresses)} port {port}, "
                                               f"reachable from other hosts: start it with ROS_IP=127.0.0.1 "
                                               f"({run_hint(config, 'CMD')})")


#: where a local node's master call names its own endpoints: index -> what it is
REGISTRATION_URIS: dict[str, tuple[tuple[int, str], ...]] = {
    "registerPublisher": ((3, "XML-RPC API"),),
    "registerSubscriber": ((3, "XML-RPC API"),),
    "registerService": ((2, "service port"), (3, "XML-RPC API")),
    "subscribeParam": ((1, "XML-RPC API"),),
}


def check_registrations(calls: list[Request], exposure: PortExposure, config: Path | None) -> None:
    """PolicyDenied ``exposed_endpoint`` for the first local registration among
    ``calls`` (a request, or the calls of a multicall) whose node listens where other
    hosts reach it."""
    for call in calls:
        for index, what in REGISTRATION_URIS.get(call.method, ()):
            if len(call.params) > index and isinstance(call.params[0], str):
                check_node_endpoint(call.params[0], call.params[index], what, exposure, config)


__all__ = ["MAX_PORTS", "REGISTRATION_URIS", "TTL", "PortExposure", "check_node_endpoint", "check_node_port",
           "check_registrations", "master_problem", "run_hint"]
