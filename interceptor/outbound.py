"""Streams this interceptor opens to peer interceptors: :meth:`Outbound.open_tunnel`
(mutual TLS, our token in the preamble, the peer's verified), the spare connections kept
ready per peer endpoint, the opening slots that keep a burst to a few handshakes at a
time, and TLS session resumption on the client side."""

from __future__ import annotations

import asyncio
import contextlib
import ssl
import time
from typing import Any

from cryptoros.errors import PEER_FAILURES, PolicyDenied, Refusal, RemoteProtocolError
from cryptoros.lru import remember
from cryptoros.tls import (
    cert_thumbprint_s256,
    offering,
)
from cryptoros.tunnel import Preamble, PreambleReader, PreambleReply, encode
from interceptor.gate import REFRESH
from interceptor.streams import (
    MAX_PEER_ENDPOINTS,
    READ_SIZE,
    SPARE_AGE,
    SPARE_QUIET,
    SPARES_PER_PEER,
    Peer,
    Tunnel,
    _Connected,
    cert_hosts,
    log,
    read_into,
)


class Outbound:
    """The outbound side of :class:`~interceptor.gateway.Gateway` (a part of it)."""

    # ================================================================ outbound
    async def open_tunnel(
        self, host: str, port: int, purpose: str, target: str, *, first: bytes = b"", whole: bool | None = None,
        settles: bool = False,
    ) -> Tunnel:
        """Mutual TLS to a peer interceptor, our token in the preamble, its token in
        the reply (verified and bound to its certificate). ``first`` (a connection
        header, an XML-RPC request) is sent right behind the preamble, saving a round
        trip; the peer reads it only once our token passed.

        The token shown is narrowed for the peer (its certificate the audience, only
        the grants on names its manager holds too), except on master streams
        (``whole``, by default for purpose ``master``): the master's interceptor judges
        every registration, so it sees every grant.

        ``settles``: the caller calls :meth:`Tunnel.settle` once the stream's set-up is
        over; the spare connection for the next stream (``spare_connections``) is made
        only then, so its handshake does not take the CPU from this stream's set-up on
        both interceptors (otherwise it is made at once)."""
        self.keeper.current()  # no token of our own: nothing is opened
        self.check_feed_age()  # nor with a stale feed: the peer's token in its reply may be revoked
        whole = purpose == "master" if whole is None else whole
        endpoint = (host, port)
        if purpose != REFRESH:
            self._note_stream(endpoint)
        # a token exchange also tells whether the peer is reachable now (_wait_reachable):
        # it never goes over a spare, which may have been connected before the peer stopped
        spare = self._take_spare(endpoint) if purpose != REFRESH else None
        connecting = ([f for f in self._spare_connecting.get(endpoint, ()) if not f.done()]
                      if spare is None and purpose != REFRESH else [])
        if connecting:
            # a spare is being connected: it is ready sooner than a connection of our own
            await asyncio.wait(connecting, timeout=self.cfg.limits.handshake_timeout,
                               return_when=asyncio.FIRST_COMPLETED)
            spare = self._take_spare(endpoint)
        settled = asyncio.get_running_loop().create_future() if settles else None
        if spare is not None:
            log.debug("%s stream to %s:%d over a spare connection", purpose, host, port)
            try:
                tunnel = await self._tunnel_over(spare, host, port, purpose, target, first=first, whole=whole)
            except (ConnectionError, RemoteProtocolError, ssl.SSLError) as exc:
                log.info("spare connection to %s:%d was gone (%s): opening a fresh one", host, port, exc)
                tunnel = None  # the peer closed it before a byte of this stream was read
            except Refusal as exc:
                # A spare shows the certificate the peer had when it was made: after the
                # peer's reload (a renewal) the token for that certificate is refused there
                # (bad_audience) or by the authorization server. Its other spares are as
                # old; this stream tries once more on a fresh connection, whose refusal
                # is the answer (day-2 audit: every first stream after a renewal failed).
                log.info("refused over a spare connection to %s:%d (%s): its spares dropped, "
                         "trying a fresh connection", host, port, exc)
                self._drop_spares_to(endpoint)
                tunnel = None
            finally:
                if not spare.used.done():
                    spare.used.set_result(None)
            if tunnel is not None:
                self.metrics.spares.labels("used").inc()
                return self._with_spare_after(tunnel, endpoint, purpose, settled)
        async with self._opening_slot(host, port):
            tunnel = await self._tunnel_over(await self._connect(host, port), host, port, purpose, target,
                                             first=first, whole=whole)
        return self._with_spare_after(tunnel, endpoint, purpose, settled)

    # ---------------------------------------------------------------- spare connections
    def _with_spare_after(self, tunnel: Tunnel, endpoint: tuple[str, int], purpose: str,
                          settled: asyncio.Future | None) -> Tunnel:
        """``tunnel``, and a spare for the next stream to ``endpoint`` made once it settles."""
        self._want_spare(endpoint, purpose, settled)
        if settled is None:
            return tunnel
        return Tunnel(tunnel.reader, tunnel.writer, tunnel.peer, tunnel.pending, settled)

    def _take_spare(self, endpoint: tuple[str, int]) -> _Connected | None:
        """The oldest ready spare to ``endpoint`` still open, if any (its maker stops
        counting toward the endpoint's spares: the next stream may want another)."""
        spares = self._spares.get(endpoint)
        while spares:
            spare = spares.pop(0)
            if not spares:
                del self._spares[endpoint]
            self._discard_maker(endpoint, spare.maker)
            if spare.writer.is_closing() or spare.reader.at_eof():
                spare.writer.close()
                spare.used.set_result(None)
                continue
            return spare
        return None

    def _discard_maker(self, endpoint: tuple[str, int], maker: Any) -> None:
        makers = self._spare_makers.get(endpoint)
        if makers is not None:
            makers.discard(maker)
            if not makers:
                del self._spare_makers[endpoint]

    def _note_stream(self, endpoint: tuple[str, int]) -> None:
        now = time.monotonic()
        recent = [t for t in self._recent_streams.get(endpoint, ()) if now - t < self._spare_window()]
        remember(self._recent_streams, endpoint, [*recent[-SPARES_PER_PEER:], now], MAX_PEER_ENDPOINTS)

    def _spare_window(self) -> float:
        return SPARE_AGE * self.cfg.limits.preamble_timeout

    def _spares_wanted(self, endpoint: tuple[str, int]) -> int:
        """As many spares as streams to ``endpoint`` were opened within a spare's life
        before the last one (at most ``SPARES_PER_PEER``): a peer that gets a stream now
        and then gets none (no handshake and token exchange for nothing), one that got
        a few in a row gets them."""
        recent = self._recent_streams.get(endpoint, [])
        if not recent:
            return 0
        now = time.monotonic()
        return min(SPARES_PER_PEER, sum(1 for t in recent[:-1] if now - t < self._spare_window()))

    def _want_spare(self, endpoint: tuple[str, int], purpose: str, after: asyncio.Future | None = None) -> None:
        """After a stream to ``endpoint``, have up to ``SPARES_PER_PEER`` connections to
        it ready (TLS done, no preamble; how many: :meth:`_spares_wanted`): the next
        streams skip the handshake's wait.
        Their preamble, token check and every other per-stream check run when one is
        used; unused for ``SPARE_AGE`` x the preamble timeout, a spare carries a token
        exchange and closes, so a burst costs a few extra connections and an idle peer
        none. A spare is connected once the stream ``after`` belongs to settled (bounded
        by the handshake timeout) and no stream was opened to ``endpoint`` for
        ``SPARE_QUIET`` seconds: its handshake runs between bursts, not during one."""
        if purpose == REFRESH or not self.started or not self.cfg.limits.spare_connections:
            return
        wanted = self._spares_wanted(endpoint)
        if wanted <= len(self._spare_makers.get(endpoint, ())):
            return
        makers = self._spare_makers.setdefault(endpoint, set())
        while len(makers) < wanted:
            makers.add(self.spawn(self.keep_spare(endpoint, after)))

    async def keep_spare(self, endpoint: tuple[str, int], after: asyncio.Future | None = None) -> None:
        """Connect one spare to ``endpoint`` (after ``after``, a stream's set-up, is done)
        and keep it ready until a stream takes it, it ages out, or :meth:`drop_spares`."""
        host, port = endpoint
        me = asyncio.current_task()
        spare: _Connected | None = None
        connecting: asyncio.Future | None = None
        try:
            if after is not None:
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(asyncio.shield(after), self.cfg.limits.handshake_timeout)
            while (quiet := self._recent_streams.get(endpoint, [0.0])[-1] + SPARE_QUIET - time.monotonic()) > 0:
                await asyncio.sleep(quiet)
            async with self._opening_slot(host, port):  # a spare counts as an opening stream at the peer
                connecting = asyncio.get_running_loop().create_future()
                self._spare_connecting.setdefault(endpoint, set()).add(connecting)
                generation = self._spare_generation
                connected = await self._connect(host, port)
                if generation != self._spare_generation:
                    # spares were dropped meanwhile (a reload): this one has the old client
                    # context, and a token bound to the new certificate is refused over it
                    connected.writer.close()
                    self.metrics.spares.labels("stale").inc()
                    log.debug("spare connection to %s:%d made before a reload: closed", host, port)
                    return
                spare = _Connected(connected.reader, connected.writer, connected.ssl_object, connected.offer,
                                   asyncio.get_running_loop().create_future(), me)
                self._spares.setdefault(endpoint, []).append(spare)
                self.metrics.spares.labels("made").inc()
                connecting.set_result(None)
                log.debug("spare connection to %s:%d ready", host, port)
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(asyncio.shield(spare.used), SPARE_AGE * self.cfg.limits.preamble_timeout)
                if self._unlist_spare(endpoint, spare):  # unused: show the peer our token and close
                    log.debug("spare connection to %s:%d unused: a token exchange", host, port)
                    self._discard_maker(endpoint, me)
                    self.metrics.spares.labels("expired").inc()
                    tunnel = await self._tunnel_over(spare, host, port, REFRESH, "", first=b"", whole=False)
                    tunnel.writer.close()
                else:  # taken: its user holds the slot until the peer's reply is verified
                    await asyncio.wait_for(asyncio.shield(spare.used), self.cfg.limits.handshake_timeout)
        except PEER_FAILURES as exc:
            log.info("spare connection to %s:%d: %s", host, port, exc)
        except Exception:
            log.exception("spare connection to %s:%d", host, port)
        finally:
            if connecting is not None:
                if not connecting.done():
                    connecting.set_result(None)
                waiting = self._spare_connecting.get(endpoint)
                if waiting is not None:
                    waiting.discard(connecting)
                    if not waiting:
                        del self._spare_connecting[endpoint]
            self._discard_maker(endpoint, me)
            if spare is not None and self._unlist_spare(endpoint, spare):
                spare.writer.close()

    def _unlist_spare(self, endpoint: tuple[str, int], spare: _Connected) -> bool:
        """Take ``spare`` off the ready list of ``endpoint``; False if it was not there (taken)."""
        spares = self._spares.get(endpoint, [])
        for i, ready in enumerate(spares):
            if ready is spare:
                del spares[i]
                if not spares:
                    del self._spares[endpoint]
                return True
        return False

    def spares_ready(self, endpoint: tuple[str, int]) -> list:
        """The spare connections ready for ``endpoint`` now, oldest first."""
        return list(self._spares.get(endpoint, ()))

    def spares_connecting(self, endpoint: tuple[str, int]) -> list[asyncio.Future]:
        """The spare connections to ``endpoint`` still in their TLS handshake."""
        return list(self._spare_connecting.get(endpoint, ()))

    def drop_spares(self) -> None:
        """Close every ready spare; one still connecting is closed once connected (generation)."""
        self._spare_generation += 1
        for endpoint in list(self._spares):
            self._drop_spares_to(endpoint)

    def _drop_spares_to(self, endpoint: tuple[str, int]) -> None:
        """Close the ready spares to ``endpoint``."""
        for spare in self._spares.pop(endpoint, ()):
            spare.writer.close()
            if not spare.used.done():
                spare.used.set_result(None)

    def _opening_slot(self, host: str, port: int):
        """At most ``max_pending_per_certificate`` streams to one peer endpoint between
        connect and its verified reply: the peer refuses more unauthenticated streams
        from one certificate than that (``pending_limit``), so a burst (a robot's
        bring-up: dozens of nodes subscribing at once) waits its turn here instead of
        being refused there. The wait is bounded by the handshake timeout."""
        limits = self.cfg.limits
        return self._opening.hold(
            (host, port), limits.max_pending_per_certificate, limits.handshake_timeout,
            lambda: PolicyDenied("peer_busy", f"{host}:{port}: no free slot to open a stream within "
                                              f"{limits.handshake_timeout:g} s"))

    async def _connect(self, host: str, port: int) -> _Connected:
        """Mutual TLS to a peer interceptor, resuming the session kept for it if any."""
        certs = self.certs
        sessions = certs.sessions
        offer = sessions.get((host, port))
        try:
            with offering(certs.client_ctx, offer):
                reader, writer = await asyncio.wait_for(
                    asyncio.open_connection(
                        host, port, ssl=certs.client_ctx, server_hostname=host,
                        local_addr=(self.cfg.public.host, 0), limit=READ_SIZE,
                    ),
                    self.cfg.limits.handshake_timeout,
                )
        except (OSError, asyncio.TimeoutError) as exc:
            if offer is not None:
                sessions.forget((host, port))
            raise PolicyDenied("peer_unreachable", f"{host}:{port}: {exc}") from exc
        return _Connected(reader, writer, writer.get_extra_info("ssl_object"), offer)

    async def _tunnel_over(
        self, connected: _Connected, host: str, port: int, purpose: str, target: str, *, first: bytes, whole: bool,
    ) -> Tunnel:
        """Our token in the preamble (``first`` right behind it), the peer's reply and
        its token verified and bound to its certificate, checked again on this stream."""
        reader, writer, ssl_object, offer = connected.reader, connected.writer, connected.ssl_object, connected.offer
        sessions = self.certs.sessions
        try:
            der = self._check_peer_certificate(ssl_object, "out")
            token = self.keeper.current() if whole else await self.keeper.for_peer(cert_thumbprint_s256(der))
            remember(self._views, (host, port), self._views.get((host, port), set()) | {whole}, MAX_PEER_ENDPOINTS)
            writer.write(encode(Preamble(token=token, purpose=purpose, target=target)) + first)
            preamble_reader = PreambleReader(PreambleReply)
            reply = None
            async with asyncio.timeout(self.cfg.limits.handshake_timeout):  # the whole reply, not each read
                while reply is None:
                    await read_into(reader, preamble_reader.receive_data, self.cfg.limits.handshake_timeout)
                    event = preamble_reader.next_event()
                    reply = event if isinstance(event, PreambleReply) else None
            if not reply.ok:
                if ssl_object.session_reused:  # e.g. too old for the peer: the next one in full
                    sessions.forget((host, port))
                raise PolicyDenied("peer_refused", f"{host}:{port} refused the {purpose} stream")
            self.metrics.stream_checks.labels("token").inc()
            access = await self.verifier.verify_fresh(reply.token, der)
            self.verifier.note(access)
            sessions.put((host, port), ssl_object, offer)  # the ticket came before the reply
            remember(self._peer_endpoints, (access.subject, access.thumbprint), (host, port), MAX_PEER_ENDPOINTS)
            remember(self._peer_tokens, (host, port), access, MAX_PEER_ENDPOINTS)
            pending = preamble_reader.trailing_data()
        except BaseException:
            writer.close()
            raise
        self.metrics.connections.labels(purpose, "out").inc()
        return Tunnel(reader, writer, Peer(access=access, hosts=cert_hosts(der)), pending)

