"""ROS URIs: ``http://host:port/`` (node and master API), ``rosrpc://host:port`` (services).

One parser for every part of cryptoros that turns a ROS URI into an address: it
accepts exactly a scheme from the caller's list, a host (an IPv6 literal in
brackets, ``http://[::1]:11311/``) and a port in 1..65535, and raises
:class:`UriError` (a :class:`~cryptoros.errors.RemoteProtocolError`: URIs come from
peers and the master) with the URI in the message otherwise. :func:`make_uri` is the
inverse, bracketing an IPv6 host.
"""

from __future__ import annotations

import urllib.parse
from dataclasses import dataclass

from cryptoros.errors import RemoteProtocolError

__all__ = ["RosUri", "UriError", "host_port", "make_uri", "split_uri"]

#: Schemes :func:`host_port` accepts unless told otherwise.
ROS_SCHEMES = ("http", "rosrpc")


class UriError(RemoteProtocolError):
    """A URI that is not ``scheme://host:port[/path]`` with an accepted scheme."""


@dataclass(frozen=True, kw_only=True, slots=True)
class RosUri:
    scheme: str
    host: str  # without brackets
    port: int
    path: str


def split_uri(uri: object, schemes: tuple[str, ...] = ROS_SCHEMES) -> RosUri:
    """Scheme, host, port and path of ``uri``; :class:`UriError` on anything else."""
    if not isinstance(uri, str) or not uri or len(uri) > 2048:
        raise UriError(f"bad URI {uri!r:.80}: not a non-empty string")
    try:
        u = urllib.parse.urlsplit(uri)
        port = u.port
    except ValueError as err:  # a port out of range or not a number, a broken IPv6 literal
        raise UriError(f"bad URI {uri!r:.80}: {err}") from err
    if u.scheme not in schemes:
        raise UriError(f"bad URI {uri!r:.80}: scheme is not {' or '.join(schemes)}")
    if not u.hostname:
        raise UriError(f"bad URI {uri!r:.80}: no host")
    if not port:
        raise UriError(f"bad URI {uri!r:.80}: no port")
    if u.username is not None or u.password is not None:
        raise UriError(f"bad URI {uri!r:.80}: user information is not allowed")
    return RosUri(scheme=u.scheme, host=u.hostname, port=port, path=u.path or "/")


def host_port(uri: object, schemes: tuple[str, ...] = ROS_SCHEMES) -> tuple[str, int]:
    """``http://host:port/`` -> ``(host, port)`` (an IPv6 host without brackets)."""
    parsed = split_uri(uri, schemes)
    return parsed.host, parsed.port


def make_uri(host: str, port: int, scheme: str = "http", path: str = "/") -> str:
    """``scheme://host:port/path``, an IPv6 host in brackets."""
    if ":" in host and not host.startswith("["):
        host = f"[{host}]"
    return f"{scheme}://{host}:{port}{path}"
