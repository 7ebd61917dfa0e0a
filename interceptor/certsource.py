"""One certificate source: everything TLS an interceptor presents and checks, built
from one ``[tls]`` section and swapped by reference on a reload (ghostunnel's
certloader is the model: one reloadable source, read at the time of use).

A :class:`CertSource` is immutable. The public listener reads ``server_ctx`` at each
accept, an outgoing connection reads ``client_ctx`` and ``sessions`` when it connects,
a handshake's certificate check reads ``cert_check``: a reload builds a new source and
replaces the reference, so new handshakes use the new certificate at once, the public
port is never re-bound, and open streams stay up on the material they were made with.
"""

from __future__ import annotations

import logging
import ssl
import time
from collections.abc import Callable
from dataclasses import dataclass

from cryptoros.pemfiles import cert_der, cert_serial, cert_thumbprint_s256
from cryptoros.tls import (
    checking_server,
    FullHandshakes,
    PeerCertificateCheck,
    SessionCache,
    client_context,
    server_context,
)
from cryptoros.tokens import peer_audience
from interceptor.config import InterceptorConfig
from interceptor.health import CRL_DUE_WARNING

log = logging.getLogger("cryptoros.interceptor")


@dataclass(frozen=True, eq=False)
class CertSource:
    #: the public listener's context (mutual TLS; TLS 1.3 tickets when sessions live)
    server_ctx: ssl.SSLContext
    #: streams to peer interceptors, and the sessions kept for them (that context's only)
    client_ctx: ssl.SSLContext
    sessions: SessionCache
    #: the authorization server's client context (no session resumption)
    authz_ctx: ssl.SSLContext
    #: the server's record of full handshakes, and the per-handshake certificate check
    #: (the CRL as loaded with the contexts, and the serials the revocation feed lists now)
    full_handshakes: FullHandshakes
    cert_check: PeerCertificateCheck
    #: this interceptor's own certificate: DER, serial, and the audience of the tokens
    #: peers narrow for it
    own_der: bytes
    own_serial: int
    own_audience: str

    @classmethod
    def load(cls, cfg: InterceptorConfig, *, revoked_serials: Callable[[], frozenset[int]],
             sslobject_class: type[ssl.SSLObject] | None = None) -> CertSource:
        """Read the files of ``cfg.tls`` (a PKIError names the file that is wrong).
        A new server context draws new ticket keys: a reload makes every earlier session
        worthless."""
        lifetime = cfg.limits.tls_session_lifetime
        server_ctx = server_context(cfg.tls, tickets=1 if lifetime > 0 else 0)
        if sslobject_class is not None:
            server_ctx.sslobject_class = sslobject_class
        client_ctx = client_context(cfg.tls, check_hostname=True, resumable=lifetime > 0)
        own_der = cert_der(cfg.tls.cert_file)
        cert_check = PeerCertificateCheck(cfg.tls.crl_file, revoked_serials=revoked_serials)
        if cert_check.next_update is not None and cert_check.next_update < time.time():
            log.warning("the CRL %s is out of date (a newer one was due %s): still applied, revocations never lapse, "
                        "and the revocation feed carries newer ones; re-sign it (cryptoros-certs crl), copy it here "
                        "and SIGHUP", cfg.tls.crl_file,
                        time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(cert_check.next_update)))
        elif cert_check.next_update is not None and cert_check.next_update - time.time() < CRL_DUE_WARNING:
            log.warning("the CRL %s is due for re-signing by %s: re-sign it (cryptoros-certs crl), copy it here and "
                        "SIGHUP", cfg.tls.crl_file, time.strftime("%Y-%m-%d %H:%M UTC",
                                                                  time.gmtime(cert_check.next_update)))
        return cls(server_ctx=server_ctx, client_ctx=client_ctx, sessions=SessionCache(client_ctx, lifetime=lifetime),
                   # the authorization server's certificate checked as every peer's (CRL, feed)
                   authz_ctx=checking_server(client_context(cfg.tls, check_hostname=True), cert_check.check),
                   full_handshakes=FullHandshakes(lifetime),
                   cert_check=cert_check,
                   own_der=own_der, own_serial=cert_serial(own_der),
                   own_audience=peer_audience(cert_thumbprint_s256(own_der)))


__all__ = ["CertSource"]
