"""URI translation between a host's local ROS endpoints and the interceptor network.

No ROS process ever sees another host's real address. Between interceptors every
endpoint is named *canonically*::

    cryptoros://<owner interceptor host>:<port>/x/<id>   an exported node XML-RPC API
    cryptoros://<owner interceptor host>:<port>/t/<id>   an exported TCPROS server
    cryptoros://master                                   the master (whoever's it is)

- A local endpoint (on loopback) handed outward is *exported*: given a stable id in
  the owner's export table, the only table a peer can reach through (a peer names an
  id, never an address, so it cannot make us connect anywhere else). The id of an
  IPv4 loopback endpoint is a number made of its address, port and kind (the same
  after a restart); a restarted interceptor takes back the exports rosmaster still
  names (:meth:`Translator.adopt`, from what the master's interceptor answers), never
  one a peer names.
- A canonical name handed to a local process becomes a *relay*: a listener on
  127.0.0.1 that tunnels to the owner over mutual TLS. One relay per canonical
  target, for the life of the interceptor, so the master sees stable URIs and
  ``unregister*`` still matches. A canonical name owned by this interceptor maps
  straight back to the local endpoint (two nodes on one host talk directly). The
  relays the master's interceptor hands rosmaster carry their canonical name in their
  path (``http://127.0.0.1:<port>/cryptoros/<host>/<port>/x/<id>``): restarted with
  no state, it reads every name back from rosmaster (:meth:`Translator.from_master`)
  and re-opens each relay on its old port.

The translator is state plus pure mapping; opening relay listeners is the
``open_relay`` callback's job (the asyncio edge).
"""

from __future__ import annotations

import functools
import ipaddress
import re
from collections.abc import Callable
from dataclasses import dataclass

from cryptoros.errors import PolicyDenied
from cryptoros.exposure import is_loopback_host

SCHEME = "cryptoros"
MASTER = "cryptoros://master"
KIND_XMLRPC = "x"
KIND_TCPROS = "t"
_KIND_SCHEME = {KIND_XMLRPC: "http", KIND_TCPROS: "rosrpc"}
_SCHEME_KIND = {"http": KIND_XMLRPC, "rosrpc": KIND_TCPROS}
_CANONICAL = re.compile(r"^cryptoros://([^/:]+):(\d{1,5})/([xt])/(\d{1,14})$")
#: the path of a relay URI handed to rosmaster: the canonical name it stands for
_NAMED_PATH = re.compile(r"^/cryptoros/([^/:]+)/(\d{1,5})/([xt])/(\d{1,14})$")
#: export ids below this are counted (endpoints with no IPv4 loopback address); from it on
#: they are made of the endpoint (:func:`_endpoint_number`)
_NUMBERED = 1 << 17
_ROS_URI = re.compile(r"^(http|rosrpc)://([^/:]+):(\d{1,5})(/.*)?$")


@dataclass(frozen=True, slots=True)
class Canonical:
    host: str
    port: int
    kind: str
    id: str

    def __str__(self) -> str:
        return f"{SCHEME}://{self.host}:{self.port}/{self.kind}/{self.id}"

    @classmethod
    def parse(cls, text: str) -> Canonical | None:
        m = _CANONICAL.match(text) if isinstance(text, str) else None
        if m is None:
            return None
        port = int(m.group(2))
        if not 0 < port < 65536:
            return None
        return cls(host=m.group(1), port=port, kind=m.group(3), id=m.group(4))


@dataclass(frozen=True, slots=True)
class LocalEndpoint:
    kind: str
    host: str
    port: int
    uri: str  # exactly as the local process wrote it


def is_loopback(host: str) -> bool:
    return isinstance(host, str) and _is_loopback_name(host)


# every registration asks (ipaddress parses a string in ~15 us)
_is_loopback_name = functools.lru_cache(maxsize=256)(is_loopback_host)


def _parse_ros_uri(uri: str) -> tuple[str, str, int]:
    m = _ROS_URI.match(uri) if isinstance(uri, str) else None
    if m is None or not 0 < int(m.group(3)) < 65536:
        raise PolicyDenied("bad_uri", f"not a ROS URI: {uri!r:.80}")
    return _SCHEME_KIND[m.group(1)], m.group(2), int(m.group(3))


def _endpoint_number(kind: str, host: str, port: int) -> str | None:
    """The id of an IPv4 loopback endpoint: its address (127.0.0.0/8: 24 bits), port and
    kind, in one number (at least :data:`_NUMBERED`); None for another host name."""
    try:
        address = ipaddress.IPv4Address(host)
    except ValueError:
        return None
    if not address.is_loopback or not 0 < port < 65536:
        return None
    return str((((int(address) & 0xFFFFFF) << 16 | port) << 1) | (kind == KIND_TCPROS))


def _endpoint_of(kind: str, ident: str) -> tuple[str, int] | None:
    """The endpoint an id of :func:`_endpoint_number` was made of (None: a counted id)."""
    number = int(ident) if ident.isdigit() else 0
    if number < _NUMBERED or (number & 1) != (kind == KIND_TCPROS):
        return None
    number >>= 1
    port, low = number & 0xFFFF, number >> 16
    if not 0 < port or low >> 24:
        return None
    return str(ipaddress.IPv4Address((127 << 24) | low)), port


def _relay_uri(target: Canonical, relay: tuple[str, int], named: bool) -> str:
    path = f"/{SCHEME}/{target.host}/{target.port}/{target.kind}/{target.id}" if named else \
        ("/" if target.kind == KIND_XMLRPC else "")
    return f"{_KIND_SCHEME[target.kind]}://{relay[0]}:{relay[1]}{path}"


class Translator:
    """Export table, relay table and the mappings between them."""

    #: Local endpoints given ids (each node's XML-RPC, TCPROS and service ports; a node
    #: restarted on new ports adds its new ones): a local process registering endless
    #: fake URIs is refused past this, and the state file it rewrites stays bounded.
    MAX_EXPORTS = 16_384

    def __init__(
        self,
        *,
        public_host: str,
        public_port: int,
        local_master_uri: str | None,
        open_relay: Callable[[Canonical, int], tuple[str, int]],
        max_relays_per_host: int = 512,
        on_change: Callable[[], None] = lambda: None,
    ) -> None:
        self._on_change = on_change
        self.max_relays_per_host = max_relays_per_host
        self._relays_per_host: dict[str, int] = {}
        self.public_host = public_host
        self.public_port = public_port
        self.local_master_uri = local_master_uri
        self._open_relay = open_relay
        self._exports: dict[str, LocalEndpoint] = {}
        self._export_ids: dict[tuple[str, str, int], str] = {}
        #: counted ids are never reused; an id made of an endpoint names that endpoint only
        self._next_id = 1
        self._relays: dict[Canonical, tuple[str, int]] = {}
        self._relay_targets: dict[tuple[str, int], Canonical] = {}
        self._master_uris: set[str] = set()

    # ------------------------------------------------------------ tables
    def add_master_uri(self, uri: str) -> None:
        """A URI that means "the master" on this host (upstream, or the local proxy)."""
        self._master_uris.add(uri.rstrip("/"))

    def export(self, kind: str, host: str, port: int, uri: str) -> Canonical:
        """Give a local endpoint a stable id; only loopback endpoints are exported."""
        if not is_loopback(host):
            raise PolicyDenied("foreign_uri", f"local endpoint {host}:{port} is not on loopback")
        key = (kind, host, port)
        ident = self._export_ids.get(key)
        if ident is None:
            if len(self._exports) >= self.MAX_EXPORTS:  # a local flood stops here (released ids do not count)
                raise PolicyDenied("export_limit", f"{self.MAX_EXPORTS} local endpoints exported already")
            ident = _endpoint_number(kind, host, port)
            if ident is None or ident in self._exports:
                ident = str(self._next_id)
                self._next_id += 1
            self._export_ids[key] = ident
            self._exports[ident] = LocalEndpoint(kind=kind, host=host, port=port, uri=uri)
            self._on_change()
        return Canonical(host=self.public_host, port=self.public_port, kind=kind, id=ident)

    def adopt(self, text: str) -> LocalEndpoint | None:
        """Take back the export behind one of our canonical names that rosmaster still
        holds (a restart with no state): its id says which loopback endpoint it was.
        None for another interceptor's name or a counted id. Only names the master's
        interceptor answers come here, never one a peer names."""
        target = Canonical.parse(text)
        if target is None or not self.owns(target):
            return None
        known = self._exports.get(target.id)
        if known is not None:
            return known if known.kind == target.kind else None
        endpoint = _endpoint_of(target.kind, target.id)
        if endpoint is None:
            return None
        host, port = endpoint
        uri = f"http://{host}:{port}/" if target.kind == KIND_XMLRPC else f"rosrpc://{host}:{port}"
        if str(self.export(target.kind, host, port, uri)) != text:
            return None
        return self._exports[target.id]

    def release(self, ident: str) -> bool:
        """Forget an export whose endpoint is gone (its node restarted on new ports):
        new streams to its id are refused (``unknown_target``) until an endpoint on the
        same address and port is exported again."""
        endpoint = self._exports.pop(ident, None)
        if endpoint is None:
            return False
        self._export_ids.pop((endpoint.kind, endpoint.host, endpoint.port), None)
        self._on_change()
        return True

    def own_id(self, text: str) -> str | None:
        """The export id in one of our canonical names, else None."""
        target = Canonical.parse(text) if isinstance(text, str) else None
        return target.id if target is not None and self.owns(target) else None

    @property
    def export_count(self) -> int:
        return len(self._exports)

    def resolve(self, kind: str, ident: str) -> LocalEndpoint:
        """The local endpoint behind one of our ids; unknown ids are refused, saying
        which endpoint an id made of one names, and why a peer may name what is not
        exported (transient: its name came before a restart or a node's exit)."""
        endpoint = self._exports.get(ident)
        if endpoint is None or endpoint.kind != kind:
            named = _endpoint_of(kind, ident)
            where = f" ({named[0]} port {named[1]})" if named is not None else ""
            raise PolicyDenied("unknown_target", f"no exported {kind} endpoint {ident!r:.20}{where}: named before "
                                                 "this interceptor restarted or its node exited; the peer retries "
                                                 "with the endpoint the master names now")
        return endpoint

    def relay_for(self, target: Canonical, *, port: int = 0) -> tuple[str, int]:
        """The relay for ``target``, opened on first use (on ``port`` if given and
        free); at most ``max_relays_per_host`` toward one peer interceptor
        (``relay_limit``)."""
        relay = self._relays.get(target)
        if relay is None:
            count = self._relays_per_host.get(target.host, 0)
            if count >= self.max_relays_per_host:
                raise PolicyDenied(
                    "relay_limit", f"{self.max_relays_per_host} relays toward {target.host} already (max_relays_per_peer)"
                )
            relay = self._open_relay(target, port)
            self._relays[target] = relay
            self._relay_targets[relay] = target
            self._relays_per_host[target.host] = count + 1
            self._on_change()
        return relay

    # ------------------------------------------------------------ kept across restarts
    def snapshot(self) -> dict:
        """The export and relay tables as JSON-able data (see :meth:`restore`)."""
        return {
            "exports": {i: [e.kind, e.host, e.port, e.uri] for i, e in self._exports.items()},
            "next_id": self._next_id,
            "relays": [[str(t), port] for t, (_h, port) in self._relays.items()],
        }

    def restore(self, data: dict) -> list[str]:
        """Take back a :meth:`snapshot` after a restart: the same export ids, and the
        relays re-opened on their old ports where free. Returns problems, one line each."""
        problems = []
        for ident, (kind, host, port, uri) in data.get("exports", {}).items():
            if kind in _KIND_SCHEME and is_loopback(host) and ident.isdigit():
                self._exports[ident] = LocalEndpoint(kind=kind, host=host, port=int(port), uri=uri)
                self._export_ids[(kind, host, int(port))] = ident
                if int(ident) < _NUMBERED:
                    self._next_id = max(self._next_id, int(ident) + 1)
        next_id = data.get("next_id")
        if isinstance(next_id, int) and next_id < _NUMBERED:
            self._next_id = max(self._next_id, next_id)
        for text, port in data.get("relays", []):
            target = Canonical.parse(text)
            if target is None:
                continue
            try:
                relay = self.relay_for(target, port=int(port))
            except (OSError, PolicyDenied) as exc:
                problems.append(f"relay {text}: {exc}")
                continue
            if relay[1] != int(port):
                problems.append(f"relay {text} moved from port {port} to {relay[1]}")
        return problems

    def relay_target(self, host: str, port: int) -> Canonical | None:
        """The canonical target behind one of our relays, or None."""
        return self._relay_targets.get((host, port))

    def forget_relay(self, host: str, port: int) -> None:
        """Drop a released relay (its listener is closed by the caller)."""
        target = self._relay_targets.pop((host, port), None)
        if target is None:
            return
        self._relays.pop(target, None)
        left = self._relays_per_host.get(target.host, 1) - 1
        if left > 0:
            self._relays_per_host[target.host] = left
        else:
            self._relays_per_host.pop(target.host, None)
        self._on_change()

    def existing_local(self, text: str, *, named: bool = False) -> str | None:
        """Like :meth:`to_local`, but never opens a relay: None for a canonical name
        this interceptor never handed out (an ``unregister*`` of it matches nothing)."""
        target = Canonical.parse(text)
        if target is None:
            raise PolicyDenied("bad_uri", f"not a canonical cryptoros name: {text!r:.80}")
        if self.owns(target):
            return self.resolve(target.kind, target.id).uri
        relay = self._relays.get(target)
        if relay is None:
            return None
        return _relay_uri(target, relay, named)

    @property
    def relay_count(self) -> int:
        return len(self._relays)

    def owns(self, target: Canonical) -> bool:
        return (target.host, target.port) == (self.public_host, self.public_port)

    # ------------------------------------------------------------ URIs
    def to_canonical(self, uri: str) -> str:
        """A URI written by a local process -> its canonical name."""
        return self._canonical(uri, export=True)

    def name_of(self, uri: str) -> str:
        """Like :meth:`to_canonical`, but exports nothing: the name a local URI has, or
        had before it was released. An ``unregister*`` sent late by a node's replaced
        process names its old endpoint this way; rosmaster then finds nothing under it,
        and no export slot is taken again for an endpoint that is gone."""
        return self._canonical(uri, export=False)

    def _canonical(self, uri: str, *, export: bool) -> str:
        if isinstance(uri, str) and uri.rstrip("/") in self._master_uris:
            return MASTER
        kind, host, port = _parse_ros_uri(uri)
        target = self._relay_targets.get((host, port))
        if target is not None:
            return str(target)
        if export:
            return str(self.export(kind, host, port, uri))
        if not is_loopback(host):
            raise PolicyDenied("foreign_uri", f"local endpoint {host}:{port} is not on loopback")
        ident = self._export_ids.get((kind, host, port)) or _endpoint_number(kind, host, port) or "0"
        return str(Canonical(host=self.public_host, port=self.public_port, kind=kind, id=ident))

    def exported(self, text: str) -> bool:
        """Whether ``text`` is one of our canonical names with a live export behind it."""
        ident = self.own_id(text)
        return ident is not None and ident in self._exports

    def to_local(self, text: str, *, named: bool = False) -> str:
        """A canonical name -> a URI a local process can call (``named``: a relay's URI
        carries the name in its path, for rosmaster: see :meth:`from_master`)."""
        if text == MASTER:
            if self.local_master_uri is None:
                raise PolicyDenied("no_master", "this interceptor has no local master URI")
            return self.local_master_uri
        target = Canonical.parse(text)
        if target is None:
            raise PolicyDenied("bad_uri", f"not a canonical cryptoros name: {text!r:.80}")
        if self.owns(target):
            return self.resolve(target.kind, target.id).uri
        return _relay_uri(target, self.relay_for(target), named)

    def from_master(self, uri: str) -> str:
        """Like :meth:`to_canonical`, for a URI rosmaster answers (master role): a relay
        URI with a name in its path (:meth:`to_local` ``named``) is that name, and its
        relay is opened again on its old port (free after our restart) if it is gone."""
        if isinstance(uri, str) and uri.rstrip("/") not in self._master_uris:
            kind, host, port = _parse_ros_uri(uri)
            path = uri.split("://", 1)[1].partition("/")[2]
            m = _NAMED_PATH.match("/" + path) if is_loopback(host) else None  # the name, not the port, says
            target = Canonical.parse(f"{SCHEME}://{m.group(1)}:{m.group(2)}/{m.group(3)}/{m.group(4)}") if m else None
            if target is not None and target.kind == kind and not self.owns(target):
                if target not in self._relays:
                    try:
                        self.relay_for(target, port=port)
                    except (OSError, PolicyDenied):
                        pass  # named all the same; rosmaster's calls to it fail until it is registered anew
                return str(target)
        return self.to_canonical(uri)

    def tcpros_to_canonical(self, host: str, port: int) -> tuple[str, int]:
        """A ``['TCPROS', host, port]`` reply of a local node -> (canonical, public port)."""
        target = self._relay_targets.get((host, port))
        if target is None:
            target = self.export(KIND_TCPROS, host, port, f"rosrpc://{host}:{port}")
        return str(target), target.port

    def tcpros_to_local(self, host: str, port: int, *, via: tuple[str, int] | None = None) -> tuple[str, int]:
        """A canonical TCPROS reply from a peer -> (host, port) a local node connects to.
        ``via``: the (host, port) of the interceptor that answered; a publisher is served
        by the interceptor in front of it, so a reply naming another one is refused
        (``endpoint_not_peer``): else a peer could have us open a relay, and connect,
        wherever it says, one listening socket per name it makes up."""
        target = Canonical.parse(host)
        if target is None or target.kind != KIND_TCPROS:
            raise PolicyDenied("bad_uri", f"TCPROS reply host is not a canonical name: {host!r:.80}")
        if via is not None and (target.host, target.port) != via:
            raise PolicyDenied("endpoint_not_peer", f"requestTopic reply from {via[0]}:{via[1]} names another "
                                                    f"interceptor ({target.host}:{target.port})")
        if self.owns(target):
            endpoint = self.resolve(KIND_TCPROS, target.id)
            return endpoint.host, endpoint.port
        return self.relay_for(target)


__all__ = ["Canonical", "KIND_TCPROS", "KIND_XMLRPC", "MASTER", "Translator", "is_loopback"]
