"""What the gateway and its roles share: the streams (a peer, a tunnel we opened, an
inbound stream admitted), the :class:`Role` hooks, the public listener, and the
helpers that read a stream with a deadline or take what a StreamReader buffered."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import os
import socket
from collections.abc import Awaitable, Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from cryptography import x509

from cryptoros.errors import ConfigError
from cryptoros.tokens import AccessToken
from interceptor.verifier import StreamWatch

log = logging.getLogger("cryptoros.interceptor")

READ_SIZE = 65536
#: a spare connection to a peer (TLS done, no preamble yet) is used within this share of
#: the preamble timeout or turned into a token exchange: the peer's preamble deadline
#: counts from its accept (and refuses a stream that waits longer)
SPARE_AGE = 0.4
#: spare connections kept ready per peer endpoint (a subscription's TCPROS stream and a
#: service call, or a few nodes starting together, each find one)
SPARES_PER_PEER = 2
#: a spare is connected only once no stream was opened to its endpoint for this long
#: (seconds): its handshake then takes no CPU from the streams of a burst
SPARE_QUIET = 0.01
#: peer endpoints remembered (tokens they showed, views of ours they saw): the least recently
#: used go first (a peer may name endpoints on many ports of its address over time)
MAX_PEER_ENDPOINTS = 4096


@contextlib.contextmanager
def listening(what: str, endpoint: object) -> Iterator[None]:
    """A listener that cannot bind is a ConfigError naming it and its address:
    ``cannot listen on 127.0.0.2:11400 (public): Address already in use``."""
    try:
        yield
    except OSError as exc:
        detail = os.strerror(exc.errno) if exc.errno else str(exc)
        raise ConfigError(f"cannot listen on {endpoint} ({what}): {detail}") from None


@dataclass(frozen=True, slots=True)
class Peer:
    """A verified peer interceptor: the token it opened the stream with and the
    addresses its certificate names."""

    access: AccessToken
    hosts: frozenset[str]

    @property
    def manager(self) -> str:
        return self.access.subject


@dataclass(frozen=True, slots=True)
class Tunnel:
    """A stream we opened to a peer interceptor, past its reply: ``pending`` holds the
    bytes it sent behind the reply (the role reads them first)."""

    reader: asyncio.StreamReader
    writer: asyncio.StreamWriter
    peer: Peer
    pending: bytes = b""
    #: completed by :meth:`settle` (see :meth:`Gateway.open_tunnel`, ``settles``)
    settled: asyncio.Future | None = field(default=None, compare=False)

    def settle(self) -> None:
        """This stream's set-up is over (its first reply relayed, or it failed): the
        spare connection for the next stream to this peer may be made now."""
        if self.settled is not None and not self.settled.done():
            self.settled.set_result(None)


@dataclass(frozen=True, slots=True)
class _Connected:
    """A TLS connection to a peer interceptor, before its preamble: the session it
    offered (if any) and, for a spare, the future its user completes once the peer's
    reply is verified (the spare's opening slot is held until then)."""

    reader: asyncio.StreamReader
    writer: asyncio.StreamWriter
    ssl_object: Any
    offer: Any
    used: asyncio.Future | None = None
    #: the task that made the spare (and holds its opening slot until it is used)
    maker: Any = None


@dataclass(frozen=True, slots=True)
class InboundStream:
    """A stream the gate admitted, handed to the role serving its purpose: ``pending``
    holds the bytes the peer sent behind its preamble."""

    reader: asyncio.StreamReader
    writer: asyncio.StreamWriter
    peer: Peer
    purpose: str
    target: str
    pending: bytes = b""
    #: what the role's target check resolved the target to (checked before the reply)
    resolved: Any = None
    #: the stream as the verifier watches it: its judge (declared by the target check, or
    #: by the role once it read what the stream is for), why it was cut
    watch: StreamWatch | None = field(default=None, compare=False)


@functools.lru_cache(maxsize=256)
def cert_hosts(der: bytes) -> frozenset[str]:
    """IP and DNS names in a certificate's SAN: where its owner's endpoints may live
    (each certificate parsed once: a peer shows the same one on every stream)."""
    try:
        san = x509.load_der_x509_certificate(der).extensions.get_extension_for_class(x509.SubjectAlternativeName)
    except (ValueError, x509.ExtensionNotFound):
        return frozenset()
    ips = {str(ip) for ip in san.value.get_values_for_type(x509.IPAddress)}
    return frozenset(ips | set(san.value.get_values_for_type(x509.DNSName)))


def take_buffered(reader: asyncio.StreamReader) -> bytes:
    """Bytes a StreamReader received but nobody read yet, when a stream leaves the
    StreamReader for the pump (which takes the transport). The one place the edge reads
    CPython's StreamReader internals: asyncio has no public "take what is buffered"."""
    buffer = getattr(reader, "_buffer", None)
    if not buffer:
        return b""
    data = bytes(buffer)
    buffer.clear()
    return data


def widen_reader(reader: asyncio.StreamReader, limit: int) -> None:
    """Let ``reader`` buffer up to ``limit`` bytes before it pauses its transport (a
    topic stream of large messages; the public listener's readers start at
    :data:`READ_SIZE`). The one place the edge writes a StreamReader's internals:
    asyncio sets the limit only when the reader is made, before the purpose is known."""
    if getattr(reader, "_limit", None) is not None:
        reader._limit = max(reader._limit, limit)


async def read_into(reader: asyncio.StreamReader, feed: Callable[[bytes], None], timeout: float) -> None:
    """One read (within ``timeout``) handed to a sans-IO codec's ``receive_data``."""
    async with asyncio.timeout(timeout):  # no task per read, as wait_for would make
        data = await reader.read(READ_SIZE)
    feed(data)


async def drain_within(writer: asyncio.StreamWriter, timeout: float) -> None:
    """``writer.drain()`` within ``timeout`` seconds (``TimeoutError``), with no task of
    its own (``wait_for`` wraps the drain in one: a task per message written)."""
    async with asyncio.timeout(timeout):
        await writer.drain()


async def read_chunks(reader: asyncio.StreamReader, size: int, first: bytes = b""):
    """``first`` (bytes already read from the stream), then every read until EOF."""
    if first:
        yield first
    while data := await reader.read(size):
        yield data


class PublicListener:
    """The public port's listening socket, accepting by hand: each accepted socket goes
    to ``on_accept(sock)`` in a task of its own before any byte of it is read (the
    gateway counts it against its caps, then starts TLS on it). ``close`` and
    ``wait_closed`` as an ``asyncio.Server``'s."""

    def __init__(self, listener: socket.socket, on_accept: Callable[[socket.socket], Awaitable[None]]) -> None:
        self._listener = listener
        self._on_accept = on_accept
        self._loop = asyncio.get_running_loop()
        self._closed = self._loop.create_future()
        self._loop.add_reader(listener.fileno(), self._accept)

    @classmethod
    async def start(cls, host: str, port: int, on_accept: Callable[[socket.socket], Awaitable[None]],
                    backlog: int = 100) -> PublicListener:
        infos = await asyncio.get_running_loop().getaddrinfo(host, port, type=socket.SOCK_STREAM,
                                                             flags=socket.AI_PASSIVE)
        family, _type, _proto, _name, address = infos[0]
        listener = socket.socket(family, socket.SOCK_STREAM)
        try:
            listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            listener.bind(address)
            listener.listen(backlog)
            listener.setblocking(False)
        except BaseException:
            listener.close()
            raise
        return cls(listener, on_accept)

    def _accept(self) -> None:
        for _ in range(64):  # a burst: take it, but let the loop run between bursts
            try:
                sock, _addr = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # out of descriptors and the like: the rest wait in the backlog
                log.warning("accept on the public port failed: %s", exc)
                self._loop.remove_reader(self._listener.fileno())
                self._loop.call_later(0.1, self._resume)
                return
            sock.setblocking(False)
            asyncio.ensure_future(self._on_accept(sock))

    def _resume(self) -> None:
        if not self._closed.done():
            self._loop.add_reader(self._listener.fileno(), self._accept)

    def close(self) -> None:
        if self._closed.done():
            return
        self._loop.remove_reader(self._listener.fileno())
        self._listener.close()
        self._closed.set_result(None)

    async def wait_closed(self) -> None:
        await self._closed


