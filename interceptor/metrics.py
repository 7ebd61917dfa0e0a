"""Prometheus metrics of one interceptor (its own registry, served on ``/metrics``)."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, generate_latest


class Metrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.connections = Counter(
            "cryptoros_interceptor_connections_total",
            "Streams opened, by purpose and direction (in: from a peer, out: to a peer)",
            ["purpose", "direction"],
            registry=self.registry,
        )
        self.open_streams = Gauge(
            "cryptoros_interceptor_open_streams", "Streams open now", ["purpose"], registry=self.registry
        )
        self.bytes = Counter(
            "cryptoros_interceptor_bytes_total",
            "Bytes relayed after the header checks (tx: toward the peer interceptor)",
            ["direction"],
            registry=self.registry,
        )
        self.allowed = Counter(
            "cryptoros_interceptor_allowed_total", "Requests and streams allowed", ["kind"], registry=self.registry
        )
        self.denied = Counter(
            "cryptoros_interceptor_denied_total",
            "Requests and streams denied, by reason",
            ["kind", "reason"],
            registry=self.registry,
        )
        self.cutoffs = Counter(
            "cryptoros_interceptor_revocation_cutoffs_total",
            "Open streams cut because their authority ended, by reason (revoked, subject_disabled, "
            "certificate_revoked, grant_removed, token_expired, own_token_expired)",
            ["reason"],
            registry=self.registry,
        )
        self.token_expires = Gauge(
            "cryptoros_interceptor_token_expiry_seconds",
            "Unix time at which this interceptor's own access token expires",
            registry=self.registry,
        )
        self.handshakes = Counter(
            "cryptoros_interceptor_tls_handshakes_total",
            "TLS handshakes between interceptors that completed, by direction and kind "
            "(full: chain and CRL verified by OpenSSL; resumed: a session ticket)",
            ["direction", "kind"],
            registry=self.registry,
        )
        self.stream_checks = Counter(
            "cryptoros_interceptor_stream_checks_total",
            "Checks run per stream between interceptors, resumed or not (certificate: validity "
            "and CRL; token: signature or cache, time, binding, revocation feed), passed or not",
            ["check"],
            registry=self.registry,
        )
        self.spares = Counter(
            "cryptoros_interceptor_spare_connections_total",
            "Spare connections to peers (TLS done before a stream needs one), by outcome "
            "(made: connected and waiting; used: a stream's preamble went over it; expired: it "
            "carried a token exchange; stale: connected across a reload, closed unused)",
            ["outcome"],
            registry=self.registry,
        )
        self.reloads = Counter(
            "cryptoros_interceptor_reloads_total", "SIGHUP reloads, by result", ["result"], registry=self.registry
        )

    def render(self) -> bytes:
        return generate_latest(self.registry)
