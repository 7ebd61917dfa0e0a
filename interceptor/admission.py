"""The public side: every stream a peer opens to this interceptor, from its accept
through the TLS handshake (counted, deadline, certificate checked inside it) and the
sans-IO :class:`~interceptor.gate.StreamGate` (preamble, token, limits, the role's
target and judge) to the role that serves its purpose."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import socket
import ssl

from cryptoros.errors import CryptorosError, PolicyDenied, TokenError
from cryptoros.lru import remember
from cryptoros.tls import (
    cert_thumbprint_s256,
    peer_cert_der,
)
from cryptoros.tunnel import NEED_DATA
from interceptor.gate import REFRESH, StreamGate
from interceptor.streams import (
    READ_SIZE,
    InboundStream,
    Peer,
    cert_hosts,
    drain_within,
    log,
    read_into,
)

#: source addresses remembered as a verified peer's (exempt from max_pending_streams)
KNOWN_SOURCES = 4096
#: an unknown source whose TLS handshakes fail faster than this (per second, after a burst)
#: is closed at accept, before any TLS, for SHUN_SECONDS. Each failed handshake costs the
#: loop a key exchange and a signature: a stranger's 640 a second took half of robot A's
#: interceptor and its relayed messages' p50 from 0.4 to 5-10 ms (audit on namespace hosts).
#: A robot's handshakes do not fail, and a source a verified peer used is never shunned.
FAILED_HANDSHAKE_RATE = 2.0
FAILED_HANDSHAKE_BURST = 20
SHUN_SECONDS = 10.0


class Admission:
    """The public side of :class:`~interceptor.gateway.Gateway` (a part of it)."""

    # ================================================================ public side
    async def _on_public(self, sock: socket.socket) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._streams.add(task)
            task.add_done_callback(self._streams.discard)
        try:
            peername = sock.getpeername()
        except OSError:  # gone already
            sock.close()
            return
        source = str(peername[0]) if peername else "?"
        who = f"{source}:{peername[1]}" if peername else "?"
        if self._shunned.left(source) and source not in self._known_sources:
            self.deny("tls", PolicyDenied("handshake_failures", f"over {FAILED_HANDSHAKE_BURST} failed TLS handshakes, "
                                          f"then over {FAILED_HANDSHAKE_RATE:g} a second: closed at accept, "
                                          f"without TLS, for {SHUN_SECONDS:g} s"), source)
            sock.close()
            return
        limits = self.cfg.limits
        entered: list[tuple[str, ...]] = []
        gate = StreamGate(self._checks)
        try:
            # Until its token is verified a stream is bounded per source address and in
            # all from its accept (through the TLS handshake), then per certificate too.
            # A source a verified peer streamed from (KNOWN_SOURCES) is not counted in all:
            # strangers on 16 addresses holding 16 each filled the interceptor's 256, and no
            # robot opened a stream while they went on.
            # With all of them taken, a new stream from an unknown source takes the place of
            # the oldest stream not verified yet of the source holding the most (closed): a
            # stranger holds up to max_pending_per_source on each of its addresses, a robot
            # one or two, so a robot that never streamed here still gets in while strangers
            # hold every slot, however fast they open new ones (a re-audit: evicting the
            # oldest of all, a flood evicted robots in their handshakes, 21 of 40).
            caps = [(("source", source), limits.max_pending_per_source)]
            if source not in self._known_sources:
                caps.append((("all",), limits.max_pending_streams))
            for key, cap in caps:
                if key == ("all",):
                    self._make_room(cap)
                self._pending.enter(key, cap, "interceptor" if key == ("all",) else key[0])
                entered.append(key)
            if ("all",) in entered and task is not None:
                self._unverified.setdefault(source, {})[task] = entered
        except PolicyDenied as exc:
            for key in entered:
                self._pending.leave(key)
            self.deny("tls", exc, source)  # per source address, aggregated: a flood is a few lines
            sock.close()
            return
        writer: asyncio.StreamWriter | None = None
        slot: str | None = None  # the peer whose open streams count this one, from its admission
        try:
            streams = await self._accept_tls(sock, source)
            if streams is None:
                return
            reader, writer = streams
            der = self._check_peer_certificate(writer.get_extra_info("ssl_object"), "in")
            key = ("certificate", hashlib.sha256(der).hexdigest())
            self._pending.enter(key, limits.max_pending_per_certificate, "certificate")
            entered.append(key)
            # nothing in flight until the preamble (a peer's spare connection waits here):
            # a stop cuts it at once instead of waiting out its grace period
            async with asyncio.timeout(limits.preamble_timeout):
                with self.cuttable():
                    while (event := gate.next_event()) is NEED_DATA:
                        await read_into(reader, gate.receive_data, limits.preamble_timeout)
            self.metrics.stream_checks.labels("token").inc()
            access = self.verifier.note(await self.verifier.verify_fresh(event.preamble.token, der))  # its freshest
            self._forget_unverified(task, source)  # verified: no stranger's connection takes its place
            if source not in self._known_sources:
                for listener in self.source_listeners:  # kept across a restart (the ROS 1 role's state)
                    listener()
            remember(self._known_sources, source, True, KNOWN_SOURCES)
            # a verified peer's refusals are grouped by its manager and address, not by
            # connection (its source port): a disabled manager's robot retrying logged 11
            # lines in 8 s (a day-2 audit), and an insider's broken streams a line each
            who = f"{access.subject}@{source}"
            admitted = gate.admit(
                access, feed=self.feed_problem(), allow_new_stream=self._new_stream_limiter.allow,
                open_streams=self._open_per_peer.get(access.subject, 0), max_streams=limits.max_connections_per_peer,
            )
            if admitted.purpose != REFRESH:
                # counted from here, not once the token below is in: its first fetch for a
                # peer takes a round trip to the authorization server, and every stream of
                # a burst admitted meanwhile saw the count without the others (6 of 6 let in
                # past a cap of 2: tests/system/test_peer_stream_cap.py)
                slot = access.subject
                self._open_per_peer[slot] = self._open_per_peer.get(slot, 0) + 1
            own_token = await self.keeper.for_peer(cert_thumbprint_s256(der))  # what this peer needs, no more
        except asyncio.CancelledError:
            self._free_slot(slot)
            if writer is not None:
                writer.transport.abort()  # stop(): no preamble yet, nothing to finish
            raise
        except (CryptorosError, OSError) as exc:  # OSError: TimeoutError, a reset, a broken TLS record
            self._free_slot(slot)
            if isinstance(exc, TimeoutError):
                exc = PolicyDenied("preamble_timeout", f"timed out (a preamble's limit: {limits.preamble_timeout:g} s)")
            elif not isinstance(exc, CryptorosError):
                exc = PolicyDenied(type(exc).__name__, str(exc))
            self.deny("stream", exc, who)
            if writer is None:
                return
            with contextlib.suppress(Exception):
                writer.write(gate.refuse())
                await asyncio.wait_for(writer.drain(), 1)
            if isinstance(exc, PolicyDenied) and exc.reason in ("preamble_timeout", "pending_limit"):
                writer.transport.abort()  # no graceful TLS close for a peer that dribbles
            else:
                writer.close()
            return
        except BaseException:
            self._free_slot(slot)
            raise
        finally:
            self._forget_unverified(task, source)
            for key in entered:
                self._pending.leave(key)
        writer.write(gate.accept(own_token))
        purpose = admitted.purpose
        if purpose == REFRESH:  # tokens shown both ways: nothing more to do
            self.metrics.connections.labels(REFRESH, "in").inc()
            with contextlib.suppress(Exception):
                await drain_within(writer, limits.handshake_timeout)
            writer.close()
            return
        self.metrics.connections.labels(purpose, "in").inc()
        self.metrics.open_streams.labels(purpose).inc()

        watch = self.verifier.watch(access, lambda _reason: writer.transport.abort(), admitted.judge)
        peer = Peer(access=access, hosts=cert_hosts(der))
        _check, serve = self._purposes[purpose]
        try:
            await serve(InboundStream(reader, writer, peer, purpose, admitted.target, gate.trailing_data,
                                      admitted.resolved, watch))
        except (CryptorosError, OSError) as exc:  # OSError: TimeoutError, a reset, a broken TLS record
            if isinstance(exc, CryptorosError):
                self.deny(purpose, exc, who)
        except asyncio.CancelledError:
            pass  # stop(): the grace period is over
        finally:
            watch.close()
            self.metrics.open_streams.labels(purpose).dec()
            self._free_slot(slot)
            writer.close()

    def _free_slot(self, peer: str | None) -> None:
        """A stream of ``peer`` counted in its open streams ended (None: none was counted)."""
        if peer is None:
            return
        left = self._open_per_peer.get(peer, 0) - 1
        if left > 0:
            self._open_per_peer[peer] = left
        else:
            self._open_per_peer.pop(peer, None)

    def _forget_unverified(self, task, source: str) -> None:
        streams = self._unverified.get(source)
        if streams is not None and streams.pop(task, None) is not None and not streams:
            del self._unverified[source]

    def _make_room(self, cap: int) -> None:
        """``max_pending_streams`` reached: the oldest stream not verified yet of the
        unknown source holding the most gives its place (its task cancelled: its socket
        closed, no reply)."""
        while self._pending.count(("all",)) >= cap and self._unverified:
            source = max(self._unverified, key=lambda s: len(self._unverified[s]))
            victim = next(iter(self._unverified[source]))
            entered = self._unverified[source][victim]
            self._forget_unverified(victim, source)
            if ("all",) in entered:
                entered.remove(("all",))
                self._pending.leave(("all",))
            victim.cancel()
            self.deny("tls", PolicyDenied("pending_limit", f"{cap} unauthenticated streams from unknown sources: "
                                                           "the oldest of this source, which holds the most, closed "
                                                           "to make room"), source)

    async def _accept_tls(self, sock: socket.socket,
                          source: str) -> tuple[asyncio.StreamReader, asyncio.StreamWriter] | None:
        """The server side of the mutual TLS handshake on an accepted socket, within
        ``handshake_timeout``, with the certificate source's context as it is now: a
        stream pair, or None for a failed or late handshake (counted and logged like
        every other denial, per source address and aggregated, the socket closed)."""
        loop = asyncio.get_running_loop()
        reader = asyncio.StreamReader(limit=READ_SIZE)
        protocol = asyncio.StreamReaderProtocol(reader)
        try:
            with self.cuttable():  # nothing in flight yet: a stop need not wait for it
                transport, _ = await loop.connect_accepted_socket(
                    lambda: protocol, sock, ssl=self.certs.server_ctx,
                    ssl_handshake_timeout=self.cfg.limits.handshake_timeout)
        except asyncio.CancelledError:
            sock.close()
            raise
        except OSError as exc:  # an SSLError, a reset, the handshake deadline (TimeoutError)
            if source not in self._known_sources:
                self._shunned.failed(source)
            # logged before the socket closes: a client that sees the close finds the line
            if isinstance(exc, ssl.SSLError):
                reason = getattr(exc, "cryptoros_reason", None) or (exc.reason or type(exc).__name__).lower()
                self.deny("tls", PolicyDenied(reason, f"handshake: {getattr(exc, 'cryptoros_detail', exc)}"), source)
            elif isinstance(exc, TimeoutError) or "longer than" in str(exc):
                self.deny("tls", PolicyDenied("handshake_timeout", f"handshake: {exc or 'handshake_timeout'}"), source)
            else:  # closed before or during the handshake (a port probe, a peer gone): no denial
                log.debug("connection from %s closed in its TLS handshake: %s", source, exc)
            sock.close()
            return None
        return reader, asyncio.StreamWriter(transport, protocol, reader, loop)

    def _counting_sslobject_class(self) -> type[ssl.SSLObject]:
        """An SSLObject whose handshake fails for a client certificate
        :class:`~cryptoros.tls.PeerCertificateCheck` refuses: on the CRL, revoked by the CA
        since (the feed's serials), out of its validity period (a resumed handshake, which
        OpenSSL does not verify again). The client's connection then closes before any
        stream begins; :meth:`_accept_tls` counts and logs the failure with its source
        (asyncio itself only logs failed handshakes in debug mode)."""
        gateway = self

        class CountingSSLObject(ssl.SSLObject):
            def do_handshake(self) -> None:
                super().do_handshake()  # a failure is counted and logged by _accept_tls (it knows the source)
                if self.server_side:
                    try:
                        gateway.certs.cert_check.check(peer_cert_der(self))
                    except TokenError as exc:
                        refused = ssl.SSLError(ssl.SSL_ERROR_SSL, f"{exc.reason}: {exc.detail}")
                        refused.cryptoros_reason, refused.cryptoros_detail = exc.reason, exc.detail  # type: ignore[attr-defined]
                        raise refused from None

        return CountingSSLObject

    def _check_peer_certificate(self, ssl_object, direction: str) -> bytes:
        """The peer's certificate, checked on every stream (resumed or not): validity
        period, CRL and the CA's revocations in the feed (for a stream in, inside the
        handshake: :meth:`_counting_sslobject_class`), then its token. Returns its DER."""
        der = peer_cert_der(ssl_object)
        resumed = bool(ssl_object.session_reused)
        self.metrics.handshakes.labels(direction, "resumed" if resumed else "full").inc()
        self.metrics.stream_checks.labels("certificate").inc()
        if direction == "in":
            self.certs.full_handshakes.admit(der, resumed=resumed, version=ssl_object.version())
        else:
            self.certs.cert_check.check(der)
        return der

