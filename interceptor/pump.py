"""The byte pump: relays a stream between two transports after its header was checked.

The hot path of the interceptor. Measured (docs/performance.md has the figures), an
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
import time
from collections.abc import Callable

from cryptoros.errors import PolicyDenied, RemoteProtocolError
from cryptoros.ros1.tcpros import FrameTooLarge, FrameWalker

DEFAULT_BUFFER_SIZE = 256 * 1024
#: a pump starts reading into this much and grows to its ``buffer_size`` on the first
#: read that fills it: most streams carry small messages, and 256 KiB per direction per
#: stream, zeroed on allocation (new heap pages fault in), was 3.5 % of an interceptor's
#: CPU in a robot's bring-up (py-spy)
FIRST_BUFFER_SIZE = 16 * 1024
#: Write-buffer limits of each transport: pause the source above HIGH, resume below LOW.
HIGH_WATER = 1024 * 1024
LOW_WATER = 256 * 1024


class FrameCounter(FrameWalker):
    """The pump's :class:`~cryptoros.ros1.tcpros.FrameWalker`: finds TCPROS frame
    starts in a byte stream without copying bodies. ``u32 LE length`` + body by
    default; with ``service_response=True``, ``u8 ok`` + ``u32 LE length`` + body (a
    service server's replies). A declared length over ``max_size`` (None: unbounded)
    raises :class:`~cryptoros.errors.PolicyDenied` ``message_too_large`` before a byte
    of that frame is let through; an ``ok`` byte other than 0 or 1 ``malformed``."""

    __slots__ = ()

    def __init__(self, *, max_size: int | None = None, service_response: bool = False, what: str = "stream") -> None:
        super().__init__(max_size=max_size, service_response=service_response, what=what)

    def take(self, data: bytes | bytearray | memoryview, allowed: int) -> tuple[int, int]:
        """Walk ``data`` but start at most ``allowed`` new frames: returns the byte
        offset where the walk stopped (everything before may be forwarded) and how
        many frames were started. A started frame's body is always let through."""
        try:
            return self.walk(data, allowed)
        except FrameTooLarge as err:
            raise PolicyDenied(
                "message_too_large",
                f"{self.what}: frame of {err.size} bytes exceeds max_message_size {err.limit}",
            ) from err
        except RemoteProtocolError as err:
            raise PolicyDenied("malformed", str(err)) from err


class MessageBudget:
    """A token bucket of messages per second, shared by every stream of one peer."""

    def __init__(self, rate: float, *, burst: float | None = None, clock: Callable[[], float] = time.monotonic):
        if rate <= 0:
            raise ValueError("rate must be positive")
        self.rate = rate
        self.burst = burst if burst is not None else max(1.0, rate)
        self._clock = clock
        self._tokens = self.burst
        self._last = clock()
        self.throttled = 0  # how many times a stream had to wait

    def allowance(self) -> int:
        """Whole messages that may pass now."""
        now = self._clock()
        self._tokens = min(self.burst, self._tokens + (now - self._last) * self.rate)
        self._last = now
        return max(0, int(self._tokens))

    def spend(self, count: int) -> None:
        self._tokens -= count

    def delay(self, count: int) -> float:
        """Seconds to wait before ``count`` messages may pass (0: they pass now and
        are spent). A batch larger than the bucket passes once the bucket is full and
        leaves a debt that later batches wait out: the rate holds on average, and no
        batch size, however large, waits forever."""
        now = self._clock()
        self._tokens = min(self.burst, self._tokens + (now - self._last) * self.rate)
        self._last = now
        need = min(count, self.burst)
        if self._tokens >= need:
            self._tokens -= count
            return 0.0
        return (need - self._tokens) / self.rate


class PumpProtocol(asyncio.BufferedProtocol):
    """Reads into one reused buffer and writes each read to the peer transport.

    With ``frames`` (a :class:`FrameCounter`), the TCPROS frames read are walked and
    each declared size checked before it is let through; with a ``budget`` too, they
    are counted and reading pauses while the peer is over its message rate (the
    sender then sees TCP backpressure). With ``discard``, what is read is dropped
    (a direction that carries nothing after the header). A frame over its limit
    cuts both sides; ``on_deny`` hears why. ``tap`` is handed every chunk forwarded
    (its own copy; it must only queue it: the runtime monitor). ``gate`` is asked about
    every whole TCPROS frame's body before the frame goes on, and drops it by returning
    False (the monitor's gated topics; the frame sizes are checked before, so what is
    held for it is at most one frame)."""

    def __init__(
        self,
        *,
        buffer_size: int = DEFAULT_BUFFER_SIZE,
        on_bytes: Callable[[int], None] | None = None,
        budget: MessageBudget | None = None,
        frames: FrameCounter | None = None,
        discard: bool = False,
        on_deny: Callable[[PolicyDenied], None] | None = None,
        tap: Callable[[bytes], None] | None = None,
        gate: Callable[[bytes], bool] | None = None,
        stall_timeout: float = 0.0,
    ):
        self._buffer_size = buffer_size
        self._stall_timeout = stall_timeout
        self._stall_timer: asyncio.TimerHandle | None = None
        self._buffer = bytearray(min(buffer_size, FIRST_BUFFER_SIZE))
        self._tap = tap
        self._gate = gate
        self._gate_buffer = bytearray()  # a frame still arriving, held until the gate has seen all of it
        self._view = memoryview(self._buffer)
        self._on_bytes = on_bytes
        self._budget = budget
        self._frames = frames if frames is not None else (FrameCounter() if budget is not None else None)
        self._discard = discard
        self._on_deny = on_deny
        self._held = bytearray()  # bytes read but over the message budget
        self._paused_by: set[str] = set()
        self.transport: asyncio.Transport | None = None
        self.peer: PumpProtocol | None = None
        self.closed: asyncio.Future[None] = asyncio.get_running_loop().create_future()

    def pause(self, reason: str) -> None:
        if not self._paused_by and self.transport is not None and not self.transport.is_closing():
            self.transport.pause_reading()
        self._paused_by.add(reason)

    def unpause(self, reason: str) -> None:
        self._paused_by.discard(reason)
        if not self._paused_by and self.transport is not None and not self.transport.is_closing():
            self.transport.resume_reading()

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
        data = bytes(self._view[:nbytes])
        if nbytes == len(self._buffer) < self._buffer_size:  # a bulk stream: read more at once from now on
            self._buffer = bytearray(self._buffer_size)
            self._view = memoryview(self._buffer)
        self.feed(data)

    def feed(self, data: bytes) -> None:
        """Bytes read from our side (or before the pump took over, as if just read)."""
        if self._discard:
            return
        if self._frames is None:
            self.forward(data)
        elif self._budget is None:
            try:
                self._frames.take(data, len(data) + 1)
            except PolicyDenied as exc:
                self._deny(exc)
                return
            self.forward(data)
        else:
            self._held += data
            self._release()

    def _deny(self, exc: PolicyDenied) -> None:
        """A frame over its limit, a stalled receiver: nothing more passes either way."""
        self._held.clear()
        if self._on_deny is not None:
            self._on_deny(exc)
            self._on_deny = None
        for transport in (self.transport, self.peer.transport if self.peer else None):
            if transport is not None and not transport.is_closing():
                transport.abort()

    def _release(self) -> None:
        """Forward the held frames the budget allows; hold the rest and stop reading
        until the budget refills (the sender sees TCP backpressure)."""
        try:
            cut, started = self._frames.take(self._held, self._budget.allowance())
        except PolicyDenied as exc:
            self._deny(exc)
            return
        self._budget.spend(started)
        if cut:
            self.forward(bytes(self._held[:cut]))
            del self._held[:cut]
        if self._held:
            if "rate" not in self._paused_by:
                self._budget.throttled += 1
            self.pause("rate")
            asyncio.get_running_loop().call_later(1.0 / self._budget.rate, self._retry)
        else:
            self.unpause("rate")

    def _retry(self) -> None:
        if self.transport is not None and not self.transport.is_closing():
            self._release()

    def forward(self, data: bytes) -> None:
        peer = self.peer
        if peer is None or peer.transport is None or peer.transport.is_closing():
            return
        if self._gate is not None:
            data = self._gated(data)
            if not data:
                return
        peer.transport.write(data)
        if self._on_bytes is not None:
            self._on_bytes(len(data))
        if self._tap is not None:
            self._tap(data)

    def _gated(self, data: bytes) -> bytes:
        """The whole frames of what arrived (with what was held) that the gate lets
        through; a frame still arriving is held."""
        held = self._gate_buffer
        held += data
        out = bytearray()
        pos = 0
        while len(held) - pos >= 4:
            end = pos + 4 + int.from_bytes(held[pos:pos + 4], "little")
            if end > len(held):
                break
            if self._gate(bytes(held[pos + 4:end])):
                out += held[pos:end]
            pos = end
        del held[:pos]
        return bytes(out)

    def eof_received(self) -> bool:
        # TLS transports cannot half-close: close the other side once it has flushed.
        if self.peer is not None and self.peer.transport is not None:
            self.peer.transport.close()
        return False

    def connection_lost(self, exc: Exception | None) -> None:
        if self._stall_timer is not None:
            self._stall_timer.cancel()
        if self.peer is not None and self.peer.transport is not None and not self.peer.transport.is_closing():
            self.peer.transport.close()
        if not self.closed.done():
            self.closed.set_result(None)

    # -- backpressure: our transport's write buffer is full -> stop reading the peer
    def pause_writing(self) -> None:
        if self.peer is not None:
            self.peer.pause("backpressure")
        if self._stall_timeout > 0 and self._stall_timer is None:
            self._stall_timer = asyncio.get_running_loop().call_later(self._stall_timeout, self._stalled)

    def resume_writing(self) -> None:
        if self._stall_timer is not None:
            self._stall_timer.cancel()
            self._stall_timer = None
        if self.peer is not None:
            self.peer.unpause("backpressure")

    def _stalled(self) -> None:
        """Our receiver took too few bytes for ``stall_timeout`` to bring our write buffer
        down: the stream is cut, both sides, so the sender it blocked goes on (a rospy
        publisher with queue_size=None waits for every subscriber)."""
        self._stall_timer = None
        self._deny(PolicyDenied("stalled_stream", f"the receiver took no bytes for {self._stall_timeout:g} s "
                                                  "([limits] stalled_stream_timeout): stream cut"))


def splice(
    left: asyncio.Transport,
    right: asyncio.Transport,
    *,
    left_pending: bytes = b"",
    right_pending: bytes = b"",
    on_left_bytes: Callable[[int], None] | None = None,
    on_right_bytes: Callable[[int], None] | None = None,
    left_budget: MessageBudget | None = None,
    right_budget: MessageBudget | None = None,
    left_frames: FrameCounter | None = None,
    right_frames: FrameCounter | None = None,
    left_discard: bool = False,
    on_deny: Callable[[PolicyDenied], None] | None = None,
    left_tap: Callable[[bytes], None] | None = None,
    right_tap: Callable[[bytes], None] | None = None,
    left_gate: Callable[[bytes], bool] | None = None,
    stall_timeout: float = 0.0,
) -> asyncio.Future[None]:
    """Relay ``left`` <-> ``right`` until both close.

    ``left_pending`` are bytes already read from ``left`` (past the header) that must
    reach ``right`` first; likewise ``right_pending``. ``on_*_bytes`` count the bytes
    read from each side (for metrics); they must be cheap. A ``*_budget`` rate-limits
    the TCPROS frames read from that side; ``*_frames`` checks their declared sizes;
    ``left_discard`` drops what ``left`` sends (a subscriber sends nothing after its
    header). ``on_deny`` hears of a frame over its limit (both sides are then cut).
    ``left_tap`` is handed every chunk forwarded from ``left`` (the runtime monitor);
    ``right_tap`` likewise from ``right`` (the monitor's reading of this host's own beacons);
    ``left_gate`` decides on each whole frame from ``left`` before it goes on.
    ``stall_timeout`` (0: never): a side whose receiver keeps its write buffer full that
    long cuts both (``stalled_stream``).
    """
    if left_gate is not None and left_frames is None:
        raise ValueError("a gate needs the frame sizes checked (left_frames)")
    a = PumpProtocol(on_bytes=on_left_bytes, budget=left_budget, frames=left_frames, discard=left_discard,
                     on_deny=on_deny, tap=left_tap, gate=left_gate, stall_timeout=stall_timeout)
    b = PumpProtocol(on_bytes=on_right_bytes, budget=right_budget, frames=right_frames, on_deny=on_deny,
                     tap=right_tap, stall_timeout=stall_timeout)
    a.attach(left, b)
    b.attach(right, a)
    left.set_protocol(a)
    right.set_protocol(b)
    if left_pending:
        a.feed(left_pending)
    if right_pending:
        b.feed(right_pending)
    if left.is_closing():
        a.connection_lost(None)
    if right.is_closing():
        b.connection_lost(None)
    return asyncio.gather(a.closed, b.closed)  # type: ignore[return-value]


__all__ = ["DEFAULT_BUFFER_SIZE", "FrameCounter", "MessageBudget", "PumpProtocol", "splice"]
