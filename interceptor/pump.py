"""The byte pump: relays a stream between two transports after its header was checked.

The hot path of the interceptor. Measured on this machine (perf-baselines.md), an
``asyncio.BufferedProtocol`` that reads into a reused buffer and issues one
``write()`` per read keeps up with or beats stunnel, while reading frame by frame
(``readexactly`` + ``drain``) is thirty times slower on small messages. So: no
parsing, no per-message work, backpressure through ``pause_reading`` /
``resume_reading`` driven by the other side's ``pause_writing`` /
``resume_writing``.

Usage: once both transports exist (each was opened with some protocol that read the
preamble and the connection header), call :func:`splice`. It moves both transports
to :class:`PumpProtocol` instances (``transport.set_protocol``), forwards any bytes
already read past the header, and returns a future resolved when both sides closed.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

DEFAULT_BUFFER_SIZE = 256 * 1024
#: Write-buffer limits of each transport: pause the source above HIGH, resume below LOW.
HIGH_WATER = 1024 * 1024
LOW_WATER = 256 * 1024


class PumpProtocol(asyncio.BufferedProtocol):
    """Reads into one reused buffer and writes each read to the peer transport."""

    def __init__(self, *, buffer_size: int = DEFAULT_BUFFER_SIZE, on_bytes: Callable[[int], None] | None = None):
        self._buffer = bytearray(buffer_size)
        self._view = memoryview(self._buffer)
        self._on_bytes = on_bytes
        self.transport: asyncio.Transport | None = None
        self.peer: PumpProtocol | None = None
        self.closed: asyncio.Future[None] = asyncio.get_running_loop().create_future()

    # -- wiring
    def connection_made(self, transport: asyncio.BaseTransport) -> None:  # pragma: no cover - set_protocol path
        self.transport = transport  # type: ignore[assignment]

    def attach(self, transport: asyncio.Transport, peer: PumpProtocol) -> None:
        self.transport = transport
        self.peer = peer
        transport.set_write_buffer_limits(high=HIGH_WATER, low=LOW_WATER)

    # -- reading: one write to the peer per read
    def get_buffer(self, sizehint: int) -> memoryview:
        return self._view

    def buffer_updated(self, nbytes: int) -> None:
        # Copy out of the reused buffer: a transport may keep what it could not send yet.
        self.forward(bytes(self._view[:nbytes]))

    def forward(self, data: bytes) -> None:
        peer = self.peer
        if peer is None or peer.transport is None or peer.transport.is_closing():
            return
        peer.transport.write(data)
        if self._on_bytes is not None:
            self._on_bytes(len(data))

    def eof_received(self) -> bool:
        # TLS transports cannot half-close: close the other side once it has flushed.
        if self.peer is not None and self.peer.transport is not None:
            self.peer.transport.close()
        return False

    def connection_lost(self, exc: Exception | None) -> None:
        if self.peer is not None and self.peer.transport is not None and not self.peer.transport.is_closing():
            self.peer.transport.close()
        if not self.closed.done():
            self.closed.set_result(None)

    # -- backpressure: our transport's write buffer is full -> stop reading the peer
    def pause_writing(self) -> None:
        if self.peer is not None and self.peer.transport is not None:
            self.peer.transport.pause_reading()

    def resume_writing(self) -> None:
        if self.peer is not None and self.peer.transport is not None and not self.peer.transport.is_closing():
            self.peer.transport.resume_reading()


def splice(
    left: asyncio.Transport,
    right: asyncio.Transport,
    *,
    left_pending: bytes = b"",
    right_pending: bytes = b"",
    on_left_bytes: Callable[[int], None] | None = None,
    on_right_bytes: Callable[[int], None] | None = None,
) -> asyncio.Future[None]:
    """Relay ``left`` <-> ``right`` until both close.

    ``left_pending`` are bytes already read from ``left`` (past the header) that must
    reach ``right`` first; likewise ``right_pending``. ``on_*_bytes`` count the bytes
    read from each side (for metrics); they must be cheap.
    """
    a = PumpProtocol(on_bytes=on_left_bytes)
    b = PumpProtocol(on_bytes=on_right_bytes)
    a.attach(left, b)
    b.attach(right, a)
    left.set_protocol(a)
    right.set_protocol(b)
    if left_pending:
        a.forward(left_pending)
    if right_pending:
        b.forward(right_pending)
    if left.is_closing():
        a.connection_lost(None)
    if right.is_closing():
        b.connection_lost(None)
    return asyncio.gather(a.closed, b.closed)  # type: ignore[return-value]


__all__ = ["PumpProtocol", "splice", "DEFAULT_BUFFER_SIZE"]
