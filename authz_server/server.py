"""Running the daemon: open the registry, listen with mutual TLS, stop on SIGTERM.

Start-up failures (database missing or unreachable, TLS or key files missing, wrong
passphrase, port taken) raise :class:`ConfigError` or :class:`StartupError` with a
one-line reason; the CLI prints it and exits non-zero. SIGTERM and SIGINT stop
listening, give open connections ``shutdown_grace`` seconds, flush the audit log
and exit 0. SIGHUP re-reads the TLS material (certificate, key, CA, CRL) from the
same files: new connections get the new context (open connections stay), and a reload
that fails keeps the old one, in one log line. The public socket is
:class:`~authz_server.listener.TLSListener` (connections in their handshake capped).
"""

from __future__ import annotations

import asyncio
import errno
import logging
import ssl
import signal
import time
from pathlib import Path

from aiohttp import web

from authz_server.app import CERT_WARN_DAYS, AuthzService, make_app
from authz_server.changes import ChangeSource
from authz_server.config import ServeConfig
from authz_server.db import open_registry, shown_db
from authz_server.listener import TLSListener
from authz_server.registry import Registry
from cryptoros.errors import ConfigError, CryptorosError
from cryptoros.fdlimit import raise_descriptor_limit
from cryptoros.files import open_to_others
from cryptoros.pemfiles import cert_serial
from cryptoros.tls import server_context

log = logging.getLogger("cryptoros.authz")


class StartupError(CryptorosError):
    """The daemon could not start (port taken...)."""


def _refusing_revoked(ctx: ssl.SSLContext, service: AuthzService) -> ssl.SSLContext:
    """``ctx``, its handshakes refusing a client certificate on the CRL as it was when
    the context was made (start, SIGHUP), as OpenSSL would; OpenSSL itself does not check
    the CRL (cryptoros.tls: it would refuse everyone once the CRL is out of date). A
    certificate revoked since gets through the handshake and is refused by every
    endpoint (``invalid_client``, audited at /token), the CRL re-read within a second."""
    revoked = service.crl.revoked if service.crl is not None else frozenset()

    class RevocationCheckedSSLObject(ssl.SSLObject):
        def do_handshake(self) -> None:
            super().do_handshake()
            der = self.getpeercert(binary_form=True) if self.server_side and revoked else None
            if der and cert_serial(der) in revoked:
                raise ssl.SSLError(ssl.SSL_ERROR_SSL, "certificate_revoked: the client's certificate is on the CRL")

    ctx.sslobject_class = RevocationCheckedSSLObject
    return ctx


def own_certificate_until(cert_file, now: float | None = None) -> float:
    """When this server's certificate expires (a POSIX time). ConfigError if it is not
    valid now: every interceptor would refuse the server (token refreshes fail, the
    fleet stops when its tokens run out), and the server would say nothing of it."""
    from cryptography import x509

    now = time.time() if now is None else now
    try:
        cert = x509.load_pem_x509_certificate(Path(cert_file).read_bytes())
    except (OSError, ValueError) as exc:
        raise ConfigError(f"cannot read the server certificate {cert_file}: {exc}") from None
    if cert.not_valid_after_utc.timestamp() <= now:
        raise ConfigError(f"the server certificate {cert_file} expired on {cert.not_valid_after_utc:%Y-%m-%d %H:%M} "
                          "UTC: interceptors refuse it; renew it (cryptoros-certs renew)")
    if cert.not_valid_before_utc.timestamp() > now:
        raise ConfigError(f"the server certificate {cert_file} is not valid before "
                          f"{cert.not_valid_before_utc:%Y-%m-%d %H:%M} UTC (is this host's clock right?)")
    until = cert.not_valid_after_utc.timestamp()
    if until - now < CERT_WARN_DAYS * 86400:
        log.warning("the server certificate %s expires in %.1f days (%s UTC): renew it (cryptoros-certs renew)",
                    cert_file, (until - now) / 86400, f"{cert.not_valid_after_utc:%Y-%m-%d %H:%M}")
    return until


def _weak_settings(cfg: ServeConfig, service: AuthzService) -> None:
    """Warn of what the configuration allows but weakens: no CRL, secret files other
    local users may read."""
    if service.crl is None:
        log.warning("no CRL (--crl, or crl = in the configuration): a certificate revoked with "
                    "'cryptoros-certs revoke' still gets tokens while it is bound to its manager, and no "
                    "interceptor learns of it")
    for warning in open_to_others([*cfg.tls.secret_files(),
                                   ("the signing keys' passphrase file", cfg.keys.passphrase_file)]):
        log.warning("%s", warning)


async def serve(cfg: ServeConfig, *, ready: asyncio.Event | None = None,
                stop: asyncio.Event | None = None) -> None:
    cert_until = own_certificate_until(cfg.tls.cert_file)
    ssl_ctx = server_context(cfg.tls)  # ConfigError on bad TLS material
    engine = open_registry(cfg.db_url, create=False)
    registry = Registry(engine, source=ChangeSource.here("cryptoros-authz serve"))
    service = AuthzService(cfg, registry)
    service.cert_until = cert_until
    _refusing_revoked(ssl_ctx, service)
    runner: web.AppRunner | None = None
    probe_runner: web.AppRunner | None = None
    listener: TLSListener | None = None
    raise_descriptor_limit()  # the listener's caps bind first, not the kernel's limit
    stop = stop or asyncio.Event()
    loop = asyncio.get_running_loop()
    try:
        await service.start()
        # keepalive_timeout: aiohttp closes a connection with no request under way this long
        # after it opened or after its last answer (its default, an hour, let a held
        # unfinished request head live that long)
        runner = web.AppRunner(make_app(service), access_log=None, handle_signals=False,
                               shutdown_timeout=cfg.shutdown_grace, handler_cancellation=True,
                               keepalive_timeout=cfg.idle_timeout)
        await runner.setup()
        listener = TLSListener(cfg.host, cfg.port, ssl_ctx, runner.server,
                               on_failed_handshake=service.metrics.tls_handshakes_refused.inc,
                               per_client=cfg.max_connections_per_client, established=cfg.max_connections)
        try:
            listener.start()
        except OSError as exc:
            why = "address already in use" if exc.errno == errno.EADDRINUSE else (exc.strerror or str(exc))
            raise StartupError(f"cannot listen on {cfg.host}:{cfg.port}: {why}") from exc
        if cfg.probe is not None:
            probe_runner = web.AppRunner(make_app(service, probe=True), access_log=None, handle_signals=False)
            await probe_runner.setup()
            probe_host, probe_port = cfg.probe_endpoint()
            try:
                await web.TCPSite(probe_runner, probe_host, probe_port, reuse_address=True).start()
            except OSError as exc:
                why = "address already in use" if exc.errno == errno.EADDRINUSE else (exc.strerror or str(exc))
                raise StartupError(f"cannot listen on the probe {cfg.probe}: {why}") from exc
            log.info("probe (healthz, metrics; plain HTTP, no client certificate) on http://%s", cfg.probe)
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        loop.add_signal_handler(signal.SIGHUP, lambda: _reload_tls(cfg, listener, service))
        assert service.signing_kid is not None
        log.info("serving on https://%s:%d (registry %s, issuer %s, audience %s, token lifetime %ds, signing key %s)",
                 cfg.host, cfg.port, shown_db(cfg.db_url), cfg.issuer, cfg.audience, cfg.token_lifetime,
                 service.signing_kid)
        _weak_settings(cfg, service)  # once serving: a start refused stays one line
        if ready is not None:
            ready.set()
        await stop.wait()
        log.info("shutting down")
    finally:
        for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
            loop.remove_signal_handler(sig)
        service.release_waiters()  # long-polls answer at once instead of holding shutdown_grace
        if listener is not None:
            await listener.close()
        if probe_runner is not None:
            await probe_runner.cleanup()
        if runner is not None:
            await runner.cleanup()
        await service.close()
        engine.dispose()
    log.info("stopped")


def _reload_tls(cfg: ServeConfig, listener: TLSListener, service: AuthzService) -> None:
    """SIGHUP: a new TLS context from the same files for new connections (open ones
    stay), or the old one kept."""
    try:
        cert_until = own_certificate_until(cfg.tls.cert_file)
        listener.ssl_ctx = _refusing_revoked(server_context(cfg.tls), service)
    except CryptorosError as exc:
        log.error("reload failed, keeping the old TLS material: %s", exc)
        return
    service.cert_until = cert_until
    if service.crl is not None:
        service.crl.refresh(force=True)
    log.info("reloaded TLS material (certificate, key, CA, CRL) on SIGHUP")
