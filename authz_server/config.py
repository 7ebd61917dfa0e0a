"""The daemon's configuration: one frozen dataclass, validated when it is built.

Sources, lowest precedence first: built-in defaults, a TOML file (``serve --config``,
unknown keys are an error), environment variables, command-line flags. The CLI merges
them into a plain dict and calls :func:`build_config`, so every source goes through
the same checks.
"""

from __future__ import annotations

import ipaddress
import tomllib
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from authz_server.db import DEFAULT_DB_URL
from authz_server.keys import KeyProtection, protection
from cryptoros.files import CONFIG_LIMIT, read_bounded
from cryptoros.errors import ConfigError
from cryptoros.passphrase import read_file
from cryptoros.tls import TLSConfig

DEFAULT_ISSUER = "cryptoros-authz"
DEFAULT_AUDIENCE = "cryptoros"
DEFAULT_LIFETIME = 300
MIN_LIFETIME, MAX_LIFETIME = 10, 24 * 3600
MAX_FEED_WAIT_LIMIT = 900.0


@dataclass(frozen=True, kw_only=True)
class ServeConfig:
    db_url: str
    tls: TLSConfig
    keys: KeyProtection
    host: str = "127.0.0.1"
    port: int = 8443
    issuer: str = DEFAULT_ISSUER
    audience: str = DEFAULT_AUDIENCE
    token_lifetime: int = DEFAULT_LIFETIME
    #: how long manager grants, JWKS and the revocation feed are cached in memory
    cache_seconds: float = 1.0
    db_threads: int = 4
    #: grace period for open connections on SIGTERM
    shutdown_grace: float = 5.0
    #: ``host:port`` on loopback: /healthz and /metrics over plain HTTP for probes
    probe: str | None = None
    #: token requests per second one client certificate may make (bucket of token_burst)
    token_rate: float = 20.0
    token_burst: int = 300
    #: the audit log keeps rows this many days, and at most audit_max_rows (pruned hourly)
    audit_keep_days: float = 90.0
    audit_max_rows: int = 1_000_000
    #: the longest this replica holds a long-poll of the feed (``/revocations?wait=``); a
    #: longer wait is held this long. Any proxy in front must allow a request this long.
    max_feed_wait: float = 600.0
    #: connections past their TLS handshake one client certificate may hold, and all may
    #: (a certificate holder holding thousands of unfinished requests exhausted the
    #: daemon's descriptors and memory: every robot's token renewal timed out)
    max_connections_per_client: int = 256
    max_connections: int = 2048
    #: seconds a connection may wait for its next request's head (since it opened, or
    #: since its last answer) before it is closed; a request being answered is not idle
    idle_timeout: float = 30.0

    def __post_init__(self) -> None:
        try:
            ipaddress.ip_address(self.host)
        except ValueError:
            if not self.host or len(self.host) > 253:
                raise ConfigError(f"invalid listen host {self.host!r}") from None
        if not (isinstance(self.port, int) and 0 <= self.port <= 65535):
            raise ConfigError(f"invalid port {self.port!r}: expected 0..65535")
        if not (isinstance(self.token_lifetime, int) and MIN_LIFETIME <= self.token_lifetime <= MAX_LIFETIME):
            raise ConfigError(
                f"invalid token lifetime {self.token_lifetime!r}: expected {MIN_LIFETIME}..{MAX_LIFETIME} seconds"
            )
        for label in ("issuer", "audience"):
            value = getattr(self, label)
            if not isinstance(value, str) or not value or len(value) > 256:
                raise ConfigError(f"invalid {label} {value!r}")
        if not (0 <= self.cache_seconds <= 10):
            raise ConfigError(f"invalid cache_seconds {self.cache_seconds!r}: expected 0..10")
        if not (1 <= self.db_threads <= 64):
            raise ConfigError(f"invalid db_threads {self.db_threads!r}: expected 1..64")
        if self.probe is not None:
            self.probe_endpoint()
        if not (0 < self.token_rate <= 10_000 and 1 <= self.token_burst <= 100_000):
            raise ConfigError(f"invalid token_rate/token_burst {self.token_rate!r}/{self.token_burst!r}: "
                              "expected 0 < rate <= 10000 and 1 <= burst <= 100000")
        if not (1 <= self.audit_keep_days <= 36_500 and 1_000 <= self.audit_max_rows <= 1_000_000_000):
            raise ConfigError(f"invalid audit_keep_days/audit_max_rows {self.audit_keep_days!r}/"
                              f"{self.audit_max_rows!r}: expected 1..36500 days and 1000..1e9 rows")

        if not (1 <= self.max_connections_per_client <= self.max_connections <= 100_000):
            raise ConfigError(f"invalid max_connections_per_client/max_connections {self.max_connections_per_client!r}/"
                              f"{self.max_connections!r}: expected 1 <= per client <= in all <= 100000")
        if not (1 <= self.idle_timeout <= 3600):
            raise ConfigError(f"invalid idle_timeout {self.idle_timeout!r}: expected 1..3600 seconds")
        if not (1 <= self.max_feed_wait <= MAX_FEED_WAIT_LIMIT):
            raise ConfigError(f"invalid max_feed_wait {self.max_feed_wait!r}: expected 1..{MAX_FEED_WAIT_LIMIT:g} seconds")

    def probe_endpoint(self) -> tuple[str, int]:
        """The probe's (host, port); it must be on loopback: it answers without a certificate."""
        host, sep, port = str(self.probe).rpartition(":")
        try:
            loopback = ipaddress.ip_address(host.strip("[]")).is_loopback
            number = int(port)
        except ValueError:
            loopback, number = False, -1
        if not sep or not loopback or not 0 < number <= 65535:
            raise ConfigError(f"invalid probe {self.probe!r}: expected a loopback host:port such as 127.0.0.1:9103 "
                              "(it answers without a client certificate)")
        return host.strip("[]"), number


#: keys accepted in the TOML file and by build_config (the CLI flags map onto them)
CONFIG_KEYS = {
    "db": str,
    "host": str,
    "port": int,
    "ca": str,
    "cert": str,
    "key": str,
    "tls_key_passphrase_file": str,  # the TLS key's passphrase (read into key_passphrase_file)
    "key_passphrase_file": str,  # the same, its old TOML name (still accepted)
    "crl": str,
    "issuer": str,
    "audience": str,
    "token_lifetime": int,
    "signing_key_passphrase_file": str,
    "unsafe_no_passphrase": bool,
    "cache_seconds": float,
    "db_threads": int,
    "shutdown_grace": float,
    "probe": str,
    "token_rate": float,
    "token_burst": int,
    "audit_keep_days": float,
    "audit_max_rows": int,
    "max_feed_wait": float,
    "max_connections_per_client": int,
    "max_connections": int,
    "idle_timeout": float,
}


def load_toml(path: str | Path) -> dict[str, Any]:
    try:
        data = tomllib.loads(read_bounded(path, CONFIG_LIMIT).decode("utf-8"))
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc.strerror}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config file {path} is not valid TOML: {exc}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(f"config file {path} is not UTF-8 text (byte {exc.start}: {exc.reason})") from None
    unknown = set(data) - set(CONFIG_KEYS)
    if unknown:
        raise ConfigError(f"config file {path}: unknown key(s) {', '.join(sorted(unknown))}")
    for key, value in data.items():
        want = CONFIG_KEYS[key]
        ok = isinstance(value, want) and not (want is int and isinstance(value, bool))
        if want is float and isinstance(value, int) and not isinstance(value, bool):
            ok = True
        if not ok:
            raise ConfigError(f"config file {path}: {key} must be {want.__name__}, got {value!r}")
    if "tls_key_passphrase_file" in data:  # build_config (and the CLI's flag) say key_passphrase_file
        if "key_passphrase_file" in data:
            raise ConfigError(f"config file {path}: tls_key_passphrase_file and key_passphrase_file (its old name) "
                              "are both given")
        data["key_passphrase_file"] = data.pop("tls_key_passphrase_file")
    return data


def build_config(values: dict[str, Any]) -> ServeConfig:
    """Build and validate the daemon config from merged settings."""
    missing = [k for k in ("ca", "cert", "key") if not values.get(k)]
    if missing:
        raise ConfigError(f"serve needs TLS material: missing {', '.join('--' + k for k in missing)}")
    tls_pass = None
    if values.get("key_passphrase_file"):
        tls_pass = read_file(values["key_passphrase_file"])
    tls = TLSConfig(
        ca_file=Path(values["ca"]),
        cert_file=Path(values["cert"]),
        key_file=Path(values["key"]),
        key_passphrase=tls_pass,
        crl_file=Path(values["crl"]) if values.get("crl") else None,
        key_passphrase_file=Path(values["key_passphrase_file"]) if values.get("key_passphrase_file") else None,
    )
    keys = protection(values.get("signing_key_passphrase_file"),
                      unsafe_no_passphrase=bool(values.get("unsafe_no_passphrase")))
    kwargs = {f.name: values[f.name] for f in fields(ServeConfig)
              if f.name in values and values[f.name] is not None and f.name not in ("tls", "keys", "db_url")}
    return ServeConfig(db_url=values.get("db") or DEFAULT_DB_URL, tls=tls, keys=keys, **kwargs)
