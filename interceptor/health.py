"""What an interceptor says about itself: the feed's and the roles' problems,
``/status`` (``cryptoros status``), ``/healthz`` and ``/metrics`` on the loopback
metrics endpoint."""

from __future__ import annotations

import os
import time

from aiohttp import web
from cryptography import x509

from cryptoros.errors import PolicyDenied, TokenError
from interceptor.gate import feed_problem

#: a CRL due for re-signing within this long is warned of (seconds)
CRL_DUE_WARNING = 3 * 86400.0


def crl_due(check, now: float) -> dict:
    """When the loaded CRL is due (``next_update``) and a warning when that is near or
    past: the CRL is still applied then, but it is the operator's to re-sign and copy."""
    due = check.next_update
    if due is None:
        return {}
    out = {"next_update": due, "days_left": round((due - now) / 86400, 1)}
    if due <= now:
        out["warning"] = ("out of date: still applied (revocations never lapse); re-sign it "
                          "(cryptoros-certs crl), copy it here and SIGHUP")
    elif due - now < CRL_DUE_WARNING:
        out["warning"] = "due for re-signing soon (cryptoros-certs crl, copy it here, SIGHUP)"
    return out


class Health:
    """The health side of :class:`~interceptor.gateway.Gateway` (a part of it)."""

    # ================================================================ health
    def feed_problem(self) -> PolicyDenied | None:
        return feed_problem(refused=self.verifier.refused, last_feed_at=self.verifier.last_feed_at,
                            now=time.time(), max_age=self.cfg.limits.max_feed_age)

    def check_feed_age(self) -> None:
        problem = self.feed_problem()
        if problem is not None:
            raise problem

    def check_roles(self) -> None:
        """Raise the first role's problem (a deployment check failing), if any."""
        for role in self._roles:
            problem = role.problem()
            if problem is not None:
                raise problem

    def status(self) -> dict:
        """What ``cryptoros status`` shows: who this interceptor is to the registry now
        (token subject, grants, expiry), how fresh its view of revocations is
        (feed, CRL), how long its certificate lasts, and its peers with open streams."""
        now = time.time()
        health, token = "ok", None
        try:
            access = self.own_access()
            token = {"subject": access.subject, "jti": access.jti, "expires_in": round(access.expires_at - now),
                     "grants": [[g.node, g.action, g.name, g.type] for g in access.grants]}
            self.check_feed_age()
            self.check_roles()
        except (TokenError, PolicyDenied) as exc:
            health = f"{exc.reason}: {exc.detail}"
        cert = x509.load_der_x509_certificate(self.certs.own_der)
        crl = self.cfg.tls.crl_file
        last = self.verifier.last_feed_at
        return {
            "manager": self.cfg.manager, "pid": os.getpid(), "roles": list(self.cfg.roles), "public": str(self.cfg.public),
            "health": health, "token": token,
            "token_refresh": None if self.keeper.failing is None else {
                "failing_for": round(now - self.keeper.failing[0]), "reason": self.keeper.failing[1]},
            "certificate": {"subject": cert.subject.rfc4514_string(), "serial": format(cert.serial_number, "x"),
                            "not_after": cert.not_valid_after_utc.isoformat(),
                            "days_left": round((cert.not_valid_after_utc.timestamp() - now) / 86400, 1)},
            "feed": {"age": None if last is None else round(now - last, 1),
                     "revoked_tokens": len(self.verifier.revocations.revoked_jtis),
                     "disabled_managers": sorted(self.verifier.revocations.disabled_subjects)},
            "crl": None if crl is None else {"file": str(crl), "age": round(now - os.stat(crl).st_mtime, 1)
                                             if os.path.exists(crl) else None, **crl_due(self.certs.cert_check, now)},
            "peers": self.verifier.streams_by_peer(),
            # every stream between interceptors, in and out, is watched (the stream tasks
            # are only the inbound ones and local relays, some not past their preamble)
            "open_streams": self.verifier.open_streams,
            "message_rate": self.cfg.limits.max_messages_per_second,
            "throttled": {manager: budget.throttled for manager, budget in sorted(self._budgets.items())
                          if budget.throttled},
            "monitor": self.monitor.status() if self.monitor is not None else None,
            "denials": self.denials.table(time.monotonic()),
            "learning": self.learner.status(),
            **{key: value for role in self._roles for key, value in role.status().items()},
        }

    async def _start_metrics(self) -> None:
        app = web.Application()

        async def metrics(_request: web.Request) -> web.Response:
            if self.keeper.expires_at:
                self.metrics.token_expires.set(self.keeper.expires_at)
            return web.Response(body=self.metrics.render(), content_type="text/plain", charset="utf-8")

        async def healthz(_request: web.Request) -> web.Response:
            try:
                self.keeper.current()
                self.check_feed_age()
                self.own_access()  # our own token verifies now: not revoked, manager not disabled
                self.check_roles()
            except (TokenError, PolicyDenied) as exc:
                return web.json_response({"status": exc.reason, "detail": exc.detail}, status=503)
            last = self.verifier.last_feed_at
            learning = self.learner.health_note()
            return web.json_response({"status": "ok", "open_streams": self.verifier.open_streams,
                                      "feed_age": None if last is None else round(time.time() - last, 1),
                                      **({"learning": learning} if learning else {})})

        async def status(_request: web.Request) -> web.Response:
            return web.json_response(self.status())

        app.router.add_get("/metrics", metrics)
        app.router.add_get("/healthz", healthz)
        app.router.add_get("/status", status)
        self._metrics_runner = web.AppRunner(app, access_log=None, handle_signals=False)
        await self._metrics_runner.setup()
        await web.TCPSite(self._metrics_runner, self.cfg.metrics.host, self.cfg.metrics.port).start()

