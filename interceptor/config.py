"""The interceptor's configuration: a TOML file loaded into frozen dataclasses.

Why one long module: every key's parsing, default, check and reload rule (:data:`RELOAD`)
sit side by side, so a key cannot be added in one place and forgotten in another.

Everything is validated at start-up, in the spirit of ghostunnel: unknown keys,
missing files, an interceptor with no CA, certificate, key or token source, and
plaintext toward a non-loopback address without an explicit ``unsafe_*`` setting are
all start-up errors with one clear line (:class:`~cryptoros.errors.ConfigError`).

Example::

    manager = "robot1"              # the manager whose token this interceptor holds
    roles = ["node"]                # "node", "master", or both
    state_dir = "state"             # tables kept across restarts (default: <config stem>.state
                                    # beside this file), the instance lock among them
    allow_exposed_master = false    # master role: serve a rosmaster other hosts reach (warned)
    allow_exposed_nodes = []        # node role: node-name patterns served though their ports are
                                    # on every address (roscpp's XML-RPC API): a firewall closes them

    [tls]
    ca = "pki/ca.crt"
    cert = "pki/issued/robot1.crt"
    key = "pki/private/robot1.key"
    tls_key_passphrase_file = "robot1.pass"   # or env CRYPTOROS_KEY_PASSPHRASE, or none
                                              # (key_passphrase_file: its old name, accepted)
    crl = "pki/crl.pem"
    pin_tls12 = false

    [authz]
    url = "https://127.0.0.1:8443"
    issuer = "cryptoros-authz"
    audience = "cryptoros"

    [listen]
    public = "127.0.0.2:11400"        # mutual-TLS endpoint for other interceptors
    local_master = "127.0.0.1:11311"  # node role: ROS_MASTER_URI of this host's nodes
    metrics = "127.0.0.1:9102"        # optional Prometheus endpoint

    [master]
    interceptor = "127.0.0.4:11400"   # node role: the master's interceptor
    manager = "master"                # the manager that runs the master's interceptor
    upstream = "http://127.0.0.1:11311"  # master role: rosmaster or `cryptoros master`

    [limits]
    max_connections_per_peer = 256
    max_new_connections_per_second = 50.0
    max_messages_per_second = 10000.0  # per peer, all its streams in (default 5000; 0 = unlimited)
    max_message_size = 16777216       # bytes per TCPROS message from a peer (default 16 MiB)
    preamble_timeout = 5.0            # seconds from the TLS handshake until the peer's preamble is verified
    max_pending_per_source = 16       # unauthenticated streams per source address
    max_pending_per_certificate = 8   # ... and per client certificate
    max_pending_streams = 256         # ... and in all (from accept, TLS handshake included)
    max_relays_per_peer = 512         # relay listeners toward one peer interceptor
    tls_session_lifetime = 300.0      # TLS 1.3 resumption between interceptors (0: off)
    name_hold_seconds = 120.0         # master role: a released node name stays its owner's (0: off)
    dead_node_check = 10.0            # node role: a local node that died unregistered is cleaned up (0: off)
    max_master_calls_per_second = 200.0  # master role: per peer manager, after master_call_burst = 4000
    max_param_keys_per_peer = 10000   # master role: what a peer may store through setParam (keys...
    max_param_bytes_per_peer = 16777216  # ... and bytes); deleteParam frees it
    max_master_reply = 67108864       # master role: largest answer read from rosmaster (then pruned)
    tunnel_idle_timeout = 60.0        # a pooled XML-RPC tunnel to a peer closes after this long unused
    stalled_stream_timeout = 30.0     # a stream whose receiver takes no bytes this long is cut (0: never)
    spare_connections = true          # up to 2 connections kept ready per peer with streams in a row

    [limits.message_size]             # per-topic exceptions (fnmatch patterns, first match wins)
    "/camera/points" = 67108864

    [ros2]                            # the ros2 role (roles = ["ros2"]): see docs/ros2.md
    domain_id = 11                    # this robot's localhost-only DDS domain
    peers = ["127.0.0.3:11400"]       # interceptors of robots to forward to
    python = ".ros2-venv/bin/python"  # optional: env CRYPTOROS_ROS2_PYTHON, else <repo>/.ros2-venv
    depth = 10                        # history depth of bridged topics (the graph does not report it)
    transient_local = ["/map"]        # topics kept for late joiners here (else republished volatile)
    max_kept_bytes_per_peer = 67108864  # what one peer may make this robot keep for late joiners
    require_private_domain = true     # topics of a participant reachable from the network are not carried
    local = ["/tf", "/robot_a/*"]     # topics/services that never leave this robot (fnmatch
                                      # patterns): not offered, not logged as denials

    [monitor]                         # the runtime monitor (docs/monitor.md)
    model = "monitor-model.json"      # written by `cryptoros monitor train`
    topics = ["/team/*", "/*/pose"]   # fnmatch patterns of the topics watched (default all)
    action = "quarantine"             # "log" (default) or "quarantine" (cut and refuse the publisher)
    quarantine_seconds = 30.0
    fail_closed = false               # true: a stream the monitor cannot follow is cut

Relative paths are relative to the configuration file's directory.
"""

from __future__ import annotations

import fnmatch
import math
import os
import tomllib
import urllib.parse
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from cryptoros.files import CONFIG_LIMIT, read_bounded
from cryptoros.errors import ConfigError
from cryptoros.exposure import is_loopback_host as is_loopback
from cryptoros.monitor.model import MonitorModel
from cryptoros.passphrase import PassphraseError, from_env, read_file
from cryptoros.ros1.uri import UriError, host_port
from cryptoros.ros2 import default_ros2_python
from cryptoros.tls import TLSConfig
from interceptor.monitor import MonitorSettings

PASSPHRASE_ENV = "CRYPTOROS_KEY_PASSPHRASE"
#: seconds an inbound XML-RPC stream may sit idle between two requests before it is closed
XMLRPC_IDLE_TIMEOUT = 600.0
#: [limits] max_messages_per_second unless the file says otherwise (0 there: no limit).
DEFAULT_MESSAGES_PER_SECOND = 5_000.0
ROLES = ("node", "master", "ros2")


@dataclass(frozen=True, kw_only=True)
class Endpoint:
    host: str
    port: int

    @classmethod
    def parse(cls, text: Any, where: str) -> Endpoint:
        if not isinstance(text, str) or text.count(":") != 1:
            raise ConfigError(f"{where}: expected host:port, got {text!r}")
        host, _, port_text = text.partition(":")
        try:
            port = int(port_text)
        except ValueError:
            raise ConfigError(f"{where}: port {port_text!r} is not a number") from None
        if not host or not 0 < port < 65536:
            raise ConfigError(f"{where}: expected host:port with a port in 1..65535, got {text!r}")
        return cls(host=host, port=port)

    @property
    def is_loopback(self) -> bool:
        return is_loopback(self.host)

    def __str__(self) -> str:
        return f"{self.host}:{self.port}"


@dataclass(frozen=True, kw_only=True)
class AuthzSettings:
    url: str
    #: every replica, ``url`` first; requests fail over to the next when one does not answer
    urls: tuple[str, ...] = ()
    issuer: str = "cryptoros-authz"
    audience: str = "cryptoros"
    refresh_margin: float = 60.0
    revocation_poll_interval: float = 1.0
    #: the server holds a feed request up to this long and answers at once on a change
    #: (long-poll: changes arrive within a fraction of a second, one request per this
    #: many seconds when nothing changes); 0 polls every revocation_poll_interval. A
    #: hold is kept under [limits] max_feed_age - request_timeout (the feed would look
    #: stale meanwhile) and under the server's max_feed_wait (it answers then)
    feed_wait: float = 600.0
    #: while it holds a feed request the server writes a sign of life this often (which
    #: also says the feed is unchanged): a replica that hangs is left after two of them,
    #: and the feed stays fresh through a long hold. 0: none (the hold is then kept under
    #: max_feed_age as above; older servers answer without them)
    feed_heartbeat: float = 15.0
    request_timeout: float = 5.0
    #: A stream is cut this long after its peer's freshest token expired.
    token_grace: float = 30.0
    #: A stream whose token the feed revoked is cut unless its peer shows a fresh
    #: token within this many seconds (then it is re-judged by that token's grants).
    revocation_grace: float = 3.0


@dataclass(frozen=True, kw_only=True)
class MasterSettings:
    interceptor: Endpoint | None = None
    manager: str = "master"
    upstream: str | None = None


@dataclass(frozen=True, kw_only=True)
class Limits:
    #: Streams one peer manager may hold open into this host at once (topic and service
    #: streams, pooled XML-RPC tunnels, spares). 64 was too few in the field: a 50-node
    #: bring-up after a publisher restart met ``connection_limit`` while the old tunnels
    #: idled out. Memory per stream: about 97 KiB plus 4x the peer's token
    #: (docs/performance.md, "How an interceptor grows").
    max_connections_per_peer: int = 256
    max_new_connections_per_second: float = 50.0
    max_xmlrpc_body: int = 1 << 20
    max_header_size: int = 1 << 20
    handshake_timeout: float = 10.0
    #: seconds a relayed stream's receiver may take no bytes (its side of the pump full)
    #: before the stream is cut: a subscriber that stops reading otherwise blocks its
    #: publisher for good (rospy's queue_size=None publishes synchronously). 0: never cut.
    stalled_stream_timeout: float = 30.0
    #: Messages per second one peer manager may send into this host (all its streams
    #: together: ROS 1 topic messages and service requests, ROS 2 samples), after a
    #: burst of one second's worth. Excess is throttled by backpressure, not dropped.
    #: None (``0`` in the file): no limit. The default is 5x a busy robot's traffic
    #: from one peer and holds another peer's flow during an insider's flood
    #: (docs/interceptor.md, "Message rate").
    max_messages_per_second: float | None = DEFAULT_MESSAGES_PER_SECOND
    #: Largest TCPROS message (topic message, service request or response) a peer may
    #: send into this host; a larger declared frame cuts the stream before a byte of
    #: it is relayed. Per-topic exceptions: ``[limits.message_size]``.
    max_message_size: int = 16 << 20
    #: fnmatch pattern of a topic or service -> its own max_message_size (first match wins).
    message_size: tuple[tuple[str, int], ...] = ()
    #: Overall deadline, from accept, for a peer's preamble (after the TLS handshake).
    preamble_timeout: float = 5.0
    #: Streams not yet authenticated (preamble not verified) per source address and in
    #: all, counted from accept (a connection that never finishes its TLS handshake
    #: holds one of these, not a descriptor of its own), and per client certificate
    #: once the handshake is done.
    max_pending_per_source: int = 16
    max_pending_per_certificate: int = 8
    max_pending_streams: int = 256
    #: Relay listeners toward one peer interceptor (its canonical endpoints handed to
    #: local processes or to the master); more is refused with ``relay_limit``.
    max_relays_per_peer: int = 512
    #: Node names one peer may have registered at the master (master role).
    max_nodes_per_peer: int = 1024
    #: Master-API calls one peer manager may make per second (master role; every call of
    #: a multicall counts), after a burst of ``master_call_burst``; more are refused
    #: (``rate_limited``). A robot's bring-up stays inside the burst: measured, 102 calls
    #: for the 50 subscribers of ``cryptoros bench interceptor``'s bring-up row, 19 for
    #: two rospy subscribers from start to exit (about 10 a node, more with more topics).
    max_master_calls_per_second: float = 200.0
    master_call_burst: int = 4000
    #: What one peer manager may store in rosmaster's parameter tree through setParam
    #: (master role; its nodes' private namespaces and granted ones alike): parameter
    #: keys (leaves of the values it set) and their bytes (names and values). A write
    #: past either is refused (``param_quota``); deleteParam frees what it removes. The
    #: same number of keys bounds the parameter subscriptions (subscribeParam) it holds.
    max_param_keys_per_peer: int = 10_000
    max_param_bytes_per_peer: int = 16 << 20
    #: Largest answer read from rosmaster (master role). Its parameter tree holds what
    #: every peer stored (up to ``max_param_bytes_per_peer`` each): a read of a namespace
    #: is read whole and then pruned to what the caller may read, so one manager's
    #: stored values must not make another's reads fail (at 1 MiB, two 600 kB strings
    #: in an insider's own namespace broke every peer's ``getParam('/')``).
    max_master_reply: int = 64 << 20
    #: An XML-RPC tunnel to a peer (pooled for reuse) is closed after this many seconds
    #: unused; under the peers' own :data:`XMLRPC_IDLE_TIMEOUT` (they close it then), so
    #: this side closes first and never reuses one the peer is closing.
    tunnel_idle_timeout: float = 60.0
    #: A node name its owner unregistered stays that manager's for this many seconds
    #: (master role): a node restarting cannot have its name taken in between by another
    #: manager whose grant names nodes by a pattern. 0: a released name is free at once.
    name_hold_seconds: float = 120.0
    #: Every this many seconds (node role) this host's nodes are checked: one whose API
    #: port nothing listens on died without unregistering (SIGKILL, a crash), and its
    #: registrations are withdrawn for it, as ``rosnode cleanup`` would. 0: never.
    dead_node_check: float = 10.0
    #: New streams are refused (and /healthz answers 503) while the revocation feed is
    #: older than this many seconds: a revoked peer could be let in.
    max_feed_age: float = 60.0
    #: Calls in one ``system.multicall``; fields in one TCPROS connection header.
    max_multicall: int = 256
    max_header_fields: int = 32
    #: TLS 1.3 session resumption between interceptors: a session (and every session
    #: resumed from it) is offered for at most this many seconds after the full
    #: handshake it descends from, and a peer that resumes later is refused; 0: every
    #: stream makes a full handshake. The peer's certificate (validity, CRL) and token
    #: are checked on every stream, resumed or not. At most 7200 (OpenSSL's ticket life).
    tls_session_lifetime: float = 300.0
    #: After streams in a row to a peer, have up to two spare connections to it ready
    #: (TLS done, no preamble: the next stream skips the handshake; its preamble, token
    #: and certificate checks run when it is used). Unused, one carries a token exchange
    #: and closes. On by default: made between bursts, they take the handshake off a
    #: stream's set-up (README).
    spare_connections: bool = True

    def message_size_for(self, name: str) -> int:
        """The max_message_size of one topic or service."""
        for pattern, size in self.message_size:
            if fnmatch.fnmatchcase(name, pattern):
                return size
        return self.max_message_size


@dataclass(frozen=True, kw_only=True)
class Ros2Settings:
    domain_id: int
    python: Path
    peers: tuple[Endpoint, ...] = ()
    depth: int = 10
    node_name: str = "cryptoros_bridge"
    graph_interval: float = 0.5
    max_message_size: int = 16 * 1024 * 1024
    #: fnmatch patterns of topic and service names that stay on this robot's domain
    local: tuple[str, ...] = ()
    #: fnmatch patterns of the topics a peer may republish here as transient_local
    #: (kept for late joiners); any other topic is republished volatile, whatever the
    #: sender asks. The receiver decides: depth is capped at ``depth`` too.
    transient_local: tuple[str, ...] = ()
    #: what one peer's streams may make this robot keep for late joiners: the sum over its
    #: transient_local streams of depth x the topic's max_message_size (bytes)
    max_kept_bytes_per_peer: int = 64 * 1024 * 1024
    #: a participant on this robot's domain reachable from the network (not started with
    #: the localhost DDS settings) is reported, and its topics are not carried
    require_private_domain: bool = True

    def is_local(self, name: str) -> bool:
        return any(fnmatch.fnmatchcase(name, pattern) for pattern in self.local)

    def keeps_for_late_joiners(self, name: str) -> bool:
        return any(fnmatch.fnmatchcase(name, pattern) for pattern in self.transient_local)


@dataclass(frozen=True, kw_only=True)
class InterceptorConfig:
    manager: str
    roles: tuple[str, ...]
    tls: TLSConfig
    authz: AuthzSettings
    public: Endpoint
    local_master: Endpoint | None
    metrics: Endpoint | None
    master: MasterSettings
    limits: Limits = field(default_factory=Limits)
    unsafe_plaintext_upstream: bool = False
    ros2: Ros2Settings | None = None
    #: Where the export and relay tables, the published topics and (master role) the
    #: node owners are kept across restarts, and the lock that keeps a second instance
    #: of this configuration from starting (:func:`default_state_dir` when the file names
    #: none; None only for a configuration parsed from no file).
    state_dir: Path | None = None
    #: The runtime monitor (interceptor/monitor.py); None: no monitor.
    monitor: MonitorSettings | None = None
    #: master role: serve even while the rosmaster in ``[master] upstream`` listens on a
    #: non-loopback address (warned at start and in every status); docs/interceptor.md
    allow_exposed_master: bool = False
    #: node role: fnmatch patterns of local node names served even while an endpoint they
    #: announce listens on a non-loopback address (roscpp binds its XML-RPC API to every
    #: address whatever ROS_IP says): the operator closed those ports with a firewall
    allow_exposed_nodes: tuple[str, ...] = ()
    #: the file this configuration was loaded from, absolute (the fix a refusal names works
    #: from any directory; None: parsed from a table)
    source: Path | None = None


_SECTIONS = {
    "": {"manager", "roles", "tls", "authz", "listen", "master", "limits", "unsafe_plaintext_upstream", "ros2",
         "state_dir", "monitor", "allow_exposed_master", "allow_exposed_nodes"},
    "ros2": {f.name for f in fields(Ros2Settings)},
    "tls": {"ca", "cert", "key", "tls_key_passphrase_file", "key_passphrase_file", "crl", "pin_tls12"},
    "authz": {f.name for f in fields(AuthzSettings)} - {"urls"},  # urls: the parsed url (one or a list)
    "listen": {"public", "local_master", "metrics"},
    "master": {"interceptor", "manager", "upstream"},
    "limits": {f.name for f in fields(Limits)},
    "monitor": {f.name for f in fields(MonitorSettings)},
}


#: What a SIGHUP (:meth:`interceptor.gateway.Gateway.reload`) does with each key of the
#: file: ``APPLY`` (in effect once the reload returned: read per use from the new
#: configuration or handed to its holder by the reload) or ``RESTART`` (a reload that
#: changes it is refused before anything is swapped, naming the key; the running
#: interceptor keeps its old state). Every key of :data:`_SECTIONS` is here (a test
#: checks): a new key must be decided.
#:
#: Needs a restart, and why:
#:
#: - ``manager``, ``roles``: who this interceptor is and which roles run (listeners,
#:   children and tables made at start); ``state_dir``: the tables were loaded from it.
#: - ``[authz] url``, ``issuer``, ``audience``: another authorization server (or
#:   deployment): the feed, the keys and every token verified so far came from the old one.
#: - ``[listen] public``: baked into the endpoint names handed to the master and to peers
#:   (and kept in the state file); ``local_master`` and ``metrics``: listeners bound at start.
#: - ``[master]`` (all): local nodes registered through that master (pools, relays,
#:   replayed registrations; the master role's rosmaster watch).
#: - ``[ros2] domain_id``, ``python``, ``node_name``, ``graph_interval``,
#:   ``max_message_size``: handed to the DDS bridge child when it starts.
#: - ``[monitor]`` added or removed.
#:
#: Applied: ``[tls]`` (all: both TLS contexts, the authorization client's, the binding of
#: our own token), ``[authz]`` ``refresh_margin`` (from the next refresh),
#: ``revocation_poll_interval``, ``feed_wait``, ``feed_heartbeat`` (from the next feed
#: request), ``request_timeout``, ``token_grace``, ``revocation_grace``; every ``[limits]``
#: key (for new streams and connections: an open stream keeps the limits it started with;
#: ``handshake_timeout`` read at each accept; the public port is never re-bound);
#: ``[ros2] peers``, ``depth``, ``local``, ``transient_local``,
#: ``max_kept_bytes_per_peer``, ``require_private_domain``; every ``[monitor]`` key (the model too);
#: ``unsafe_plaintext_upstream`` (only checked when the file is loaded);
#: ``allow_exposed_master`` (read by the master role's rosmaster watch each second),
#: ``allow_exposed_nodes`` (read per registration).
APPLY = "apply"
RESTART = "restart"
RELOAD: dict[str, tuple[str, Callable[[InterceptorConfig], Any]]] = {
    "manager": (RESTART, lambda c: c.manager),
    "roles": (RESTART, lambda c: c.roles),
    "state_dir": (RESTART, lambda c: c.state_dir),
    "unsafe_plaintext_upstream": (APPLY, lambda c: c.unsafe_plaintext_upstream),
    "allow_exposed_master": (APPLY, lambda c: c.allow_exposed_master),
    "allow_exposed_nodes": (APPLY, lambda c: c.allow_exposed_nodes),
    "[tls] ca": (APPLY, lambda c: c.tls.ca_file),
    "[tls] cert": (APPLY, lambda c: c.tls.cert_file),
    "[tls] key": (APPLY, lambda c: c.tls.key_file),
    "[tls] tls_key_passphrase_file": (APPLY, lambda c: c.tls.key_passphrase),
    "[tls] key_passphrase_file": (APPLY, lambda c: c.tls.key_passphrase),  # its old name
    "[tls] crl": (APPLY, lambda c: c.tls.crl_file),
    "[tls] pin_tls12": (APPLY, lambda c: c.tls.pin_tls12),
    "[authz] url": (RESTART, lambda c: c.authz.urls),  # one URL or the list of replicas
    "[authz] issuer": (RESTART, lambda c: c.authz.issuer),
    "[authz] audience": (RESTART, lambda c: c.authz.audience),
    **{f"[authz] {name}": (APPLY, lambda c, name=name: getattr(c.authz, name))
       for name in ("refresh_margin", "revocation_poll_interval", "feed_wait", "feed_heartbeat", "request_timeout",
                    "token_grace", "revocation_grace")},
    "[listen] public": (RESTART, lambda c: c.public),
    "[listen] local_master": (RESTART, lambda c: c.local_master),
    "[listen] metrics": (RESTART, lambda c: c.metrics),
    "[master] interceptor": (RESTART, lambda c: c.master.interceptor),
    "[master] manager": (RESTART, lambda c: c.master.manager),
    "[master] upstream": (RESTART, lambda c: c.master.upstream),
    **{f"[limits] {f.name}": (APPLY, lambda c, name=f.name: getattr(c.limits, name)) for f in fields(Limits)},
    **{f"[ros2] {name}": (RESTART, lambda c, name=name: getattr(c.ros2, name, None))
       for name in ("domain_id", "python", "node_name", "graph_interval", "max_message_size")},
    **{f"[ros2] {name}": (APPLY, lambda c, name=name: getattr(c.ros2, name, None))
       for name in ("peers", "depth", "local", "transient_local", "max_kept_bytes_per_peer",
                    "require_private_domain")},
    "[monitor]": (RESTART, lambda c: c.monitor is not None),  # the section added or removed
    **{f"[monitor] {f.name}": (APPLY, lambda c, name=f.name: getattr(c.monitor, name, None))
       for f in fields(MonitorSettings)},
}


def reload_refusals(old: InterceptorConfig, new: InterceptorConfig) -> list[str]:
    """The keys that differ between ``old`` (running) and ``new`` and need a restart
    (:data:`RELOAD`), in the table's order; empty: a reload may apply ``new``."""
    return [key for key, (action, value) in RELOAD.items() if action == RESTART and value(old) != value(new)]


def check_reload(old: InterceptorConfig, new: InterceptorConfig) -> None:
    """ConfigError naming every key of ``new`` a reload cannot apply (see :data:`RELOAD`)."""
    refused = reload_refusals(old, new)
    if refused:
        raise ConfigError("; ".join(f"{key} changed" for key in refused) + ": needs a restart of the interceptor")


def check_key_names(raw: dict[str, Any]) -> None:
    """ConfigError for a key no section knows (a typo would otherwise be a setting silently
    left at its default), without reading any file the configuration names."""
    _check_keys(raw, "")
    for section in _SECTIONS:
        if section and section in raw:
            _check_keys(raw[section], section)


def _check_keys(table: Any, section: str) -> dict[str, Any]:
    where = f"[{section}]" if section else "top level"
    if not isinstance(table, dict):
        raise ConfigError(f"{where} must be a table")
    unknown = sorted(set(table) - _SECTIONS[section])
    if unknown:
        homes = [f"[{name}]" if name else "the top level (above every [section])"
                 for name, keys in _SECTIONS.items() if unknown[0] in keys]
        hint = f" (it belongs at {homes[0]})" if homes else ""
        raise ConfigError(f"unknown key {unknown[0]!r} in {where}{hint}; allowed: "
                          f"{', '.join(sorted(_SECTIONS[section]))}")
    return table


def _typed(value: Any, kind: type, where: str) -> Any:
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise ConfigError(f"{where} must be {kind.__name__}, got {value!r}")
    if kind in (int, float) and not 0 < value < math.inf:  # TOML's nan and inf too (nan fails every comparison)
        raise ConfigError(f"{where} must be positive and finite, got {value!r}")
    return value


def _seconds_or_zero(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value < math.inf:
        raise ConfigError(f"{where} must be a number of seconds, 0 or more, got {value!r}")
    return float(value)


def _path(base: Path, value: Any, where: str) -> Path:
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{where} must be a file path")
    path = Path(value)
    return path if path.is_absolute() else base / path


def read_toml(path: Path) -> dict[str, Any]:
    """A configuration file's TOML table; ConfigError (one line) when it cannot be read."""
    try:
        return tomllib.loads(read_bounded(path, CONFIG_LIMIT).decode("utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"configuration file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read configuration file {path}: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: invalid TOML: {exc}") from None


def load(path: str | os.PathLike[str]) -> InterceptorConfig:
    """Load and validate a configuration file; every problem is one ConfigError line."""
    path = Path(path).absolute()
    return parse(read_toml(path), base=path.parent, source=path)


def default_state_dir(source: Path) -> Path:
    """Where a configuration file without ``state_dir`` keeps its state: beside it, named
    after it (``/etc/cryptoros/robot_a.toml`` -> ``/etc/cryptoros/robot_a.state``). Beside
    the file, not under a user's state directory: every start of the same file finds the
    same lock, whoever starts it and from whatever environment (a service and an
    operator's shell alike), so one configuration runs as one instance."""
    source = source.absolute()
    return source.with_name(f"{source.stem}.state")


def metrics_endpoint(listen: dict[str, Any]) -> Endpoint | None:
    """``[listen] metrics`` (None when absent): on loopback only, since status and metrics
    answer without a certificate."""
    if "metrics" not in listen:
        return None
    metrics = Endpoint.parse(listen["metrics"], "[listen] metrics")
    if not metrics.is_loopback:
        raise ConfigError("[listen] metrics must be a loopback address")
    return metrics


def parse(raw: dict[str, Any], *, base: Path, source: Path | None = None) -> InterceptorConfig:
    top = _check_keys(raw, "")
    manager = top.get("manager")
    if not isinstance(manager, str) or not manager:
        raise ConfigError("manager is required: the name of the manager whose token this interceptor holds")
    roles = top.get("roles", ["node"])
    if not isinstance(roles, list) or not roles or any(r not in ROLES for r in roles) or len(set(roles)) != len(roles):
        raise ConfigError(f"roles must be a non-empty list of {', '.join(ROLES)}, got {roles!r}")

    if "tls" not in top:
        raise ConfigError("[tls] is required: the interceptor will not start without a CA, certificate and key")
    tls_raw = _check_keys(top["tls"], "tls")
    for required in ("ca", "cert", "key"):
        if required not in tls_raw:
            raise ConfigError(f"[tls] {required} is required")
    passphrase, pass_path = None, None
    given = [name for name in ("tls_key_passphrase_file", "key_passphrase_file") if name in tls_raw]
    if len(given) > 1:
        raise ConfigError("[tls] tls_key_passphrase_file and key_passphrase_file (its old name) are both given")
    if given:
        pass_path = _path(base, tls_raw[given[0]], f"[tls] {given[0]}")
        try:
            passphrase = read_file(pass_path)
        except PassphraseError as exc:
            raise ConfigError(f"[tls] {given[0]}: {exc}") from None
    else:
        passphrase = from_env(PASSPHRASE_ENV)
    tls = TLSConfig(
        ca_file=_path(base, tls_raw["ca"], "[tls] ca"),
        cert_file=_path(base, tls_raw["cert"], "[tls] cert"),
        key_file=_path(base, tls_raw["key"], "[tls] key"),
        key_passphrase=passphrase,
        crl_file=_path(base, tls_raw["crl"], "[tls] crl") if "crl" in tls_raw else None,
        pin_tls12=bool(_typed(tls_raw.get("pin_tls12", False), bool, "[tls] pin_tls12")),
        key_passphrase_file=pass_path,
    )

    if "authz" not in top:
        raise ConfigError("[authz] is required: the interceptor will not start without a token source")
    authz_raw = _check_keys(top["authz"], "authz")
    url = authz_raw.get("url")
    candidates = url if isinstance(url, list) and url else [url]
    for one in candidates:
        parsed = urllib.parse.urlsplit(one) if isinstance(one, str) else None
        if parsed is None or parsed.scheme != "https" or not parsed.hostname:
            raise ConfigError(f"[authz] url must be an https:// URL or a list of them (replicas), got {url!r}")
    urls = tuple(dict.fromkeys(one.rstrip("/") for one in candidates))
    authz = AuthzSettings(
        url=urls[0],
        urls=urls,
        **{
            k: _typed(authz_raw[k], str if k in ("issuer", "audience") else float, f"[authz] {k}")
            for k in authz_raw
            if k != "url"
        },
    )

    for name, low, high in (("revocation_poll_interval", 0.05, 60.0), ("feed_wait", 0.0, 600.0),
                            ("request_timeout", 0.1, 120.0)):
        value = getattr(authz, name)
        if not low <= value <= high:
            raise ConfigError(f"[authz] {name} = {value!r}: expected {low:g}..{high:g} seconds")
    if authz.feed_heartbeat and not 0.2 <= authz.feed_heartbeat <= 300.0:
        raise ConfigError(f"[authz] feed_heartbeat = {authz.feed_heartbeat!r}: expected 0 (none) or 0.2..300 seconds")

    listen = _check_keys(top.get("listen", {}), "listen")
    if "public" not in listen:
        raise ConfigError("[listen] public is required: the mutual-TLS endpoint other interceptors connect to")
    public = Endpoint.parse(listen["public"], "[listen] public")
    local_master = Endpoint.parse(listen["local_master"], "[listen] local_master") if "local_master" in listen else None
    metrics = metrics_endpoint(listen)
    if local_master is not None and not local_master.is_loopback:
        raise ConfigError("[listen] local_master must be a loopback address: local nodes are trusted only there")

    master_raw = _check_keys(top.get("master", {}), "master")
    master = MasterSettings(
        interceptor=Endpoint.parse(master_raw["interceptor"], "[master] interceptor") if "interceptor" in master_raw else None,
        manager=_typed(master_raw.get("manager", "master"), str, "[master] manager"),
        upstream=master_raw.get("upstream"),
    )
    unsafe_plaintext = bool(_typed(top.get("unsafe_plaintext_upstream", False), bool, "unsafe_plaintext_upstream"))
    if "node" in roles:
        if local_master is None:
            raise ConfigError("the node role needs [listen] local_master (the ROS_MASTER_URI of local nodes)")
        if master.interceptor is None and "master" not in roles:
            raise ConfigError("the node role needs [master] interceptor (the master's interceptor host:port)")
    if "master" in roles:
        try:
            upstream_host, _ = host_port(master.upstream, ("http",))
        except UriError:
            raise ConfigError(f"the master role needs [master] upstream = http://host:port, got {master.upstream!r}") from None
        if not is_loopback(upstream_host) and not unsafe_plaintext:
            raise ConfigError(
                f"[master] upstream {master.upstream} is plaintext toward a non-loopback address; "
                "set unsafe_plaintext_upstream = true (at the top level, above every [section]) to allow it"
            )

    limits_raw = dict(_check_keys(top.get("limits", {}), "limits"))
    sizes_raw = limits_raw.pop("message_size", {})
    if not isinstance(sizes_raw, dict) or len(sizes_raw) > 256:
        raise ConfigError("[limits.message_size] must be a table of at most 256 \"/topic/pattern\" = bytes")
    sizes = []
    for pattern, size in sizes_raw.items():
        if not pattern.startswith("/") or len(pattern) > 256:
            raise ConfigError(f"[limits.message_size] {pattern!r}: a topic or service pattern starts with /")
        sizes.append((pattern, _typed(size, int, f"[limits.message_size] {pattern!r}")))
    spare = limits_raw.pop("spare_connections", Limits.spare_connections)
    if not isinstance(spare, bool):
        raise ConfigError(f"[limits] spare_connections must be true or false, got {spare!r}")
    lifetime = limits_raw.pop("tls_session_lifetime", Limits.tls_session_lifetime)
    if isinstance(lifetime, bool) or not isinstance(lifetime, (int, float)) or not 0 <= lifetime <= 7200:
        raise ConfigError(f"[limits] tls_session_lifetime must be seconds from 0 (off) to 7200, got {lifetime!r}")
    hold = limits_raw.pop("name_hold_seconds", Limits.name_hold_seconds)
    if isinstance(hold, bool) or not isinstance(hold, (int, float)) or not 0 <= hold <= 86400:
        raise ConfigError(f"[limits] name_hold_seconds must be seconds from 0 (off) to 86400, got {hold!r}")
    check = limits_raw.pop("dead_node_check", Limits.dead_node_check)
    if isinstance(check, bool) or not isinstance(check, (int, float)) or not (check == 0 or 1 <= check <= 3600):
        raise ConfigError(f"[limits] dead_node_check must be seconds from 1 to 3600, or 0 (off), got {check!r}")
    rate = limits_raw.pop("max_messages_per_second", Limits.max_messages_per_second)
    if rate is not None and (isinstance(rate, bool) or not isinstance(rate, (int, float)) or not rate >= 0):
        raise ConfigError(f"[limits] max_messages_per_second must be messages a second, 0 (no limit) or more, "
                          f"got {rate!r}")
    idle = limits_raw.pop("tunnel_idle_timeout", Limits.tunnel_idle_timeout)
    if isinstance(idle, bool) or not isinstance(idle, (int, float)) or not 0 < idle < XMLRPC_IDLE_TIMEOUT:
        raise ConfigError(f"[limits] tunnel_idle_timeout must be seconds over 0 and under {XMLRPC_IDLE_TIMEOUT:g} "
                          f"(peers close an idle XML-RPC stream then), got {idle!r}")
    stalled = limits_raw.get("stalled_stream_timeout", Limits.stalled_stream_timeout)
    if isinstance(stalled, bool) or not isinstance(stalled, (int, float)) or not 0 <= stalled <= 86400:
        raise ConfigError(f"[limits] stalled_stream_timeout must be seconds from 0 (never) to 86400, got {stalled!r}")
    limit_types = {f.name: (int if f.type in ("int", int) else float) for f in fields(Limits)}
    limits = Limits(
        message_size=tuple(sizes),
        tls_session_lifetime=float(lifetime),
        name_hold_seconds=float(hold),
        dead_node_check=float(check),
        tunnel_idle_timeout=float(idle),
        max_messages_per_second=float(rate) if rate else None,
        spare_connections=spare,
        **{k: _typed(v, limit_types[k], f"[limits] {k}") for k, v in limits_raw.items()},
    )

    ros2 = None
    if "ros2" in top and "ros2" not in roles:
        raise ConfigError('[ros2] is set but roles does not include "ros2"')
    if "ros2" in roles:
        ros2 = _parse_ros2(_check_keys(top.get("ros2", {}), "ros2"), base)

    return InterceptorConfig(
        manager=manager,
        roles=tuple(roles),
        tls=tls,
        authz=authz,
        public=public,
        local_master=local_master,
        metrics=metrics,
        master=master,
        limits=limits,
        unsafe_plaintext_upstream=unsafe_plaintext,
        state_dir=(_state_dir(_path(base, top["state_dir"], "state_dir")) if "state_dir" in top
                   else default_state_dir(source) if source is not None else None),
        ros2=ros2,
        monitor=_parse_monitor(_check_keys(top["monitor"], "monitor"), base) if "monitor" in top else None,
        allow_exposed_master=_typed(top.get("allow_exposed_master", False), bool, "allow_exposed_master"),
        allow_exposed_nodes=_node_patterns(top.get("allow_exposed_nodes", []), "allow_exposed_nodes"),
        source=source,
    )


def _state_dir(path: Path) -> Path:
    """``state_dir`` as given: a directory, or nothing yet (made at start)."""
    if path.exists() and not path.is_dir():
        raise ConfigError(f"state_dir {path} exists and is not a directory")
    return path


def _node_patterns(value: Any, where: str) -> tuple[str, ...]:
    if not isinstance(value, list) or len(value) > 256 or not all(
            isinstance(p, str) and p.startswith("/") and len(p) <= 256 for p in value):
        raise ConfigError(f"{where} must be a list of at most 256 node name patterns, each starting with /")
    return tuple(value)


def _parse_monitor(raw: dict[str, Any], base: Path) -> MonitorSettings:
    if "model" not in raw:
        raise ConfigError("[monitor] model is required: the file `cryptoros monitor train` wrote")
    topics = raw.get("topics", ["*"])
    if not isinstance(topics, list) or not all(isinstance(p, str) for p in topics) or len(topics) > 256:
        raise ConfigError("[monitor] topics must be a list of at most 256 topic patterns")
    gate = raw.get("gate", [])
    if not isinstance(gate, list) or not all(isinstance(p, str) for p in gate) or len(gate) > 256:
        raise ConfigError("[monitor] gate must be a list of at most 256 topic patterns")
    settings = MonitorSettings(
        model=_path(base, raw["model"], "[monitor] model"),
        topics=tuple(topics),
        gate=tuple(gate),
        action=_typed(raw.get("action", "log"), str, "[monitor] action"),
        quarantine_seconds=_typed(raw.get("quarantine_seconds", 30.0), float, "[monitor] quarantine_seconds"),
        max_backlog_bytes=_typed(raw.get("max_backlog_bytes", 4 << 20), int, "[monitor] max_backlog_bytes"),
        max_streams=_typed(raw.get("max_streams", 1024), int, "[monitor] max_streams"),
        fail_closed=_typed(raw.get("fail_closed", False), bool, "[monitor] fail_closed"),
        manager_after=_typed(raw.get("manager_after", 3), int, "[monitor] manager_after"),
        batch_seconds=_seconds_or_zero(raw.get("batch_seconds", 0.25), "[monitor] batch_seconds"),
    )
    MonitorModel.load(settings.model)  # a model that does not load stops the start, with its reason
    return settings


def _parse_ros2(raw: dict[str, Any], base: Path) -> Ros2Settings:
    domain = raw.get("domain_id")
    if not isinstance(domain, int) or isinstance(domain, bool) or not 0 <= domain <= 232:
        raise ConfigError(f"the ros2 role needs [ros2] domain_id, an integer in 0..232, got {domain!r}")
    python = _path(base, raw["python"], "[ros2] python") if "python" in raw else default_ros2_python()
    if not python.exists():
        raise ConfigError(f"[ros2] python: {python} does not exist (create it with scripts/ros2-venv)")
    peers_raw = raw.get("peers", [])
    if not isinstance(peers_raw, list):
        raise ConfigError("[ros2] peers must be a list of host:port")
    peers = tuple(Endpoint.parse(p, "[ros2] peers") for p in peers_raw)
    if len(set(peers)) != len(peers):
        raise ConfigError("[ros2] peers lists an interceptor twice")
    node_name = _typed(raw.get("node_name", "cryptoros_bridge"), str, "[ros2] node_name")
    if not node_name.isidentifier():
        raise ConfigError(f"[ros2] node_name must be a plain ROS node name, got {node_name!r}")
    depth = _typed(raw.get("depth", 10), int, "[ros2] depth")
    if depth > 1000:
        raise ConfigError("[ros2] depth must be at most 1000")
    local = raw.get("local", [])
    if not isinstance(local, list) or len(local) > 256 or not all(
            isinstance(p, str) and p.startswith("/") and len(p) <= 256 for p in local):
        raise ConfigError("[ros2] local must be a list of at most 256 name patterns, each starting with /")
    latched = raw.get("transient_local", [])
    if not isinstance(latched, list) or len(latched) > 256 or not all(
            isinstance(p, str) and p.startswith("/") and len(p) <= 256 for p in latched):
        raise ConfigError("[ros2] transient_local must be a list of at most 256 topic patterns, each starting with /")
    return Ros2Settings(
        domain_id=domain,
        python=python,
        peers=peers,
        depth=depth,
        node_name=node_name,
        graph_interval=_typed(raw.get("graph_interval", 0.5), float, "[ros2] graph_interval"),
        max_message_size=_typed(raw.get("max_message_size", 16 * 1024 * 1024), int, "[ros2] max_message_size"),
        local=tuple(local),
        transient_local=tuple(latched),
        max_kept_bytes_per_peer=_typed(raw.get("max_kept_bytes_per_peer", 64 * 1024 * 1024), int,
                                       "[ros2] max_kept_bytes_per_peer"),
        require_private_domain=_typed(raw.get("require_private_domain", True), bool, "[ros2] require_private_domain"),
    )


__all__ = [
    "APPLY", "RELOAD", "RESTART", "AuthzSettings", "Endpoint", "InterceptorConfig", "Limits", "MasterSettings",
    "Ros2Settings", "check_reload", "default_ros2_python", "default_state_dir", "is_loopback", "metrics_endpoint", "read_toml", "load", "parse", "reload_refusals",
]
