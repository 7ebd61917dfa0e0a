"""The byte pump over real sockets: TLS on one side, plain TCP on the other."""

from __future__ import annotations

import asyncio
import hashlib
import os

import pytest

from cryptoros.tls import TLSConfig, client_context, server_context
from interceptor.pump import HIGH_WATER, splice
from tests.support import Clock


@pytest.fixture(params=["asyncio", "uvloop"])
def run_loop(request):
    """Run each test on the stdlib loop and on uvloop (the interceptor's default)."""
    if request.param == "uvloop":
        import uvloop

        return uvloop.run
    return asyncio.run


class HeaderThenSplice(asyncio.Protocol):
    """Reads one line (standing in for a checked connection header), then pumps."""

    def __init__(self, upstream_port: int, spliced: list, **splice_kw) -> None:
        self.upstream_port = upstream_port
        self.spliced = spliced
        self.splice_kw = splice_kw  # more of splice()'s arguments
        self.buffer = b""

    def connection_made(self, transport):
        self.transport = transport

    def data_received(self, data):
        self.buffer += data
        if b"\n" in self.buffer:
            self.transport.pause_reading()
            header, _, rest = self.buffer.partition(b"\n")
            asyncio.ensure_future(self._open(rest))

    async def _open(self, rest: bytes) -> None:
        loop = asyncio.get_running_loop()
        up, _ = await loop.create_connection(asyncio.Protocol, "127.0.0.1", self.upstream_port)
        done = splice(self.transport, up, left_pending=rest, **self.splice_kw)
        self.transport.resume_reading()
        self.spliced.append((self.transport, up, done))


async def echo_server() -> asyncio.Server:
    async def handle(reader, writer):
        while data := await reader.read(1 << 16):
            writer.write(data)
            await writer.drain()
        writer.close()

    return await asyncio.start_server(handle, "127.0.0.1", 0)


@pytest.fixture
def tls_pair(pki):
    server = pki.issue("relay", kind="interceptor")
    client = pki.issue("robot1")
    cfg = lambda i: TLSConfig(ca_file=pki.ca_cert, cert_file=i.cert_path, key_file=i.key_path)  # noqa: E731
    return server_context(cfg(server)), client_context(cfg(client))


def test_tls_to_tcp_relay_is_byte_exact(tls_pair, run_loop):
    run_loop(tls_to_tcp_relay_is_byte_exact(*tls_pair))


async def tls_to_tcp_relay_is_byte_exact(server_ctx, client_ctx):
    echo = await echo_server()
    spliced: list = []
    loop = asyncio.get_running_loop()
    relay = await loop.create_server(
        lambda: HeaderThenSplice(echo.sockets[0].getsockname()[1], spliced), "127.0.0.1", 0, ssl=server_ctx
    )
    port = relay.sockets[0].getsockname()[1]
    reader, writer = await asyncio.open_connection("127.0.0.1", port, ssl=client_ctx, server_hostname="localhost")
    payload = os.urandom(8 * 1024 * 1024)
    writer.write(b"header\n" + payload[:1000])  # bytes after the header ride in the same write

    async def send_rest():
        for i in range(1000, len(payload), 1 << 20):
            writer.write(payload[i : i + (1 << 20)])
            await writer.drain()

    sender = asyncio.create_task(send_rest())
    received = await asyncio.wait_for(reader.readexactly(len(payload)), timeout=60)
    await sender
    assert hashlib.sha256(received).digest() == hashlib.sha256(payload).digest()
    from interceptor.pump import DEFAULT_BUFFER_SIZE

    # a bulk stream: the pump reading TLS records grew its buffer too
    assert len(spliced[0][0].get_protocol().get_buffer(-1)) == DEFAULT_BUFFER_SIZE
    writer.close()
    await asyncio.wait_for(spliced[0][2], timeout=10)  # both sides closed when the client left
    relay.close()
    echo.close()


def test_slow_reader_pauses_the_source(tls_pair, run_loop):
    """A consumer that does not read makes the relay stop reading, not buffer forever."""
    run_loop(slow_reader_pauses_the_source(*tls_pair))


async def slow_reader_pauses_the_source(server_ctx, client_ctx):
    loop = asyncio.get_running_loop()
    sink_connected = asyncio.Event()
    sink_transports = []

    class Sink(asyncio.Protocol):
        def connection_made(self, transport):
            # Never reads: the kernel buffers fill, then ours. (uvloop ignores a
            # pause_reading() made inside connection_made, so pause on the next tick.)
            asyncio.get_running_loop().call_soon(transport.pause_reading)
            sink_transports.append(transport)
            sink_connected.set()

    sink = await loop.create_server(Sink, "127.0.0.1", 0)
    spliced: list = []
    relay = await loop.create_server(
        lambda: HeaderThenSplice(sink.sockets[0].getsockname()[1], spliced), "127.0.0.1", 0, ssl=server_ctx
    )
    reader, writer = await asyncio.open_connection(
        "127.0.0.1", relay.sockets[0].getsockname()[1], ssl=client_ctx, server_hostname="localhost"
    )
    writer.write(b"header\n")
    await asyncio.wait_for(sink_connected.wait(), timeout=10)
    chunk = b"x" * (1 << 20)
    sent = 0
    # Offer 64 MiB; the client's own drain() blocks once the relay stops reading.
    try:
        for _ in range(64):
            writer.write(chunk)
            await asyncio.wait_for(writer.drain(), timeout=2)
            sent += len(chunk)
    except asyncio.TimeoutError:
        pass
    upstream = spliced[0][1]
    assert sent < 64 * len(chunk), "the relay kept reading although nobody consumed"
    assert upstream.get_write_buffer_size() <= HIGH_WATER + (1 << 20)
    writer.transport.abort()
    for t in sink_transports:
        t.close()
    relay.close()
    sink.close()


def test_frame_counter_walks_prefixes_split_anywhere():
    from interceptor.pump import FrameCounter

    frames = b"".join(len(b).to_bytes(4, "little") + b for b in (b"a" * 10, b"", b"bb" * 300, b"c"))
    for split in (1, 3, 4, 7, 100, len(frames)):
        counter, started = FrameCounter(), 0
        for i in range(0, len(frames), split):
            pos, n = counter.take(frames[i : i + split], allowed=1000)
            assert pos == len(frames[i : i + split])
            started += n
        assert started == 4


def test_frame_counter_stops_at_the_allowance():
    from interceptor.pump import FrameCounter

    frame = (5).to_bytes(4, "little") + b"hello"
    counter = FrameCounter()
    assert counter.take(frame * 3, allowed=2) == (2 * len(frame), 2)
    assert counter.take(frame, allowed=1) == (len(frame), 1)


def test_budget_limits_a_flood_to_its_rate(run_loop):
    """A sender flooding small frames through a budgeted pump gets its budget, not more:
    the burst at once, then rate x the time its clock moved (a test clock: no waiting
    out real seconds), whole frames only."""
    run_loop(budget_limits_a_flood())


async def wait_until(done, timeout: float, what: str) -> None:
    deadline = asyncio.get_running_loop().time() + timeout
    while not done():
        assert asyncio.get_running_loop().time() < deadline, f"{what}: not within {timeout} s"
        await asyncio.sleep(0.005)


async def budget_limits_a_flood():
    from interceptor.pump import MessageBudget

    loop = asyncio.get_running_loop()
    received = bytearray()

    class Sink(asyncio.Protocol):
        def data_received(self, data):
            received.extend(data)

    sink = await loop.create_server(Sink, "127.0.0.1", 0)
    clock = Clock()
    budget = MessageBudget(200.0, clock=clock)
    spliced = []

    class Splicer(asyncio.Protocol):
        def connection_made(self, transport):
            self.early = bytearray()  # what arrives before the upstream is connected

            async def go():
                up, _ = await loop.create_connection(asyncio.Protocol, "127.0.0.1", sink.sockets[0].getsockname()[1])
                spliced.append(splice(transport, up, left_pending=bytes(self.early), left_budget=budget))
            asyncio.ensure_future(go())

        def data_received(self, data):
            self.early.extend(data)

    relay = await loop.create_server(Splicer, "127.0.0.1", 0)
    reader, writer = await asyncio.open_connection("127.0.0.1", relay.sockets[0].getsockname()[1])
    frame = (8).to_bytes(4, "little") + b"cmd_vel!"
    writer.write(frame * 20000)  # a flood: 20,000 messages at once
    for allowed in (200, 300, 500):  # the burst, then 0.5 s and 1 s of the clock at 200 a second
        await wait_until(lambda n=allowed: len(received) >= n * len(frame), 10, f"{allowed} messages through")
        # the pump retries every 1/rate s of real time: a few retries, and not one frame more
        # (the clock stands still)
        await asyncio.sleep(20 / budget.rate)
        assert len(received) == allowed * len(frame), (len(received) / len(frame), allowed)
        clock.t += {200: 0.5, 300: 1.0, 500: 0.0}[allowed]
    assert budget.throttled >= 1
    writer.transport.abort()
    relay.close()
    sink.close()


def test_a_gate_sees_whole_frames_and_drops_what_it_refuses(run_loop):
    """Frames written in pieces that split anywhere reach the gate whole; refused ones
    never reach the other side, the rest arrive byte-exact and in order."""
    run_loop(gate_drops_refused_frames())


async def gate_drops_refused_frames():
    from interceptor.pump import FrameCounter

    loop = asyncio.get_running_loop()
    received = bytearray()
    enough = asyncio.Event()
    seen: list[bytes] = []

    def frame(body: bytes) -> bytes:
        return len(body).to_bytes(4, "little") + body

    bodies = [b"good %d " % i * (i % 7 + 1) for i in range(40)]
    bodies[3] = b"bad: a false map"
    bodies[17] = b"bad"
    expected = b"".join(frame(b) for b in bodies if not b.startswith(b"bad"))

    class Sink(asyncio.Protocol):
        def data_received(self, data):
            received.extend(data)
            if len(received) >= len(expected):
                enough.set()

    all_seen = asyncio.Event()

    def gate(body: bytes) -> bool:
        seen.append(body)
        if len(seen) == len(bodies) + 1:
            all_seen.set()
        return not body.startswith(b"bad")

    sink = await loop.create_server(Sink, "127.0.0.1", 0)

    class Splicer(asyncio.Protocol):
        def connection_made(self, transport):
            self.early = bytearray()

            async def go():
                up, _ = await loop.create_connection(asyncio.Protocol, "127.0.0.1", sink.sockets[0].getsockname()[1])
                splice(transport, up, left_pending=bytes(self.early), left_frames=FrameCounter(max_size=1000),
                       left_gate=gate)
            asyncio.ensure_future(go())

        def data_received(self, data):
            self.early.extend(data)

    relay = await loop.create_server(Splicer, "127.0.0.1", 0)
    _reader, writer = await asyncio.open_connection("127.0.0.1", relay.sockets[0].getsockname()[1])
    stream = b"".join(frame(b) for b in bodies)
    for start in range(0, len(stream), 7):  # pieces that split length fields and bodies
        writer.write(stream[start:start + 7])
        await writer.drain()
    await asyncio.wait_for(enough.wait(), 10)
    writer.write(frame(b"bad again"))  # refused at the end too: nothing more arrives
    await writer.drain()
    await asyncio.wait_for(all_seen.wait(), 10)
    assert bytes(received) == expected
    assert seen == bodies + [b"bad again"]
    with pytest.raises(ValueError, match="frame sizes"):
        splice(writer.transport, writer.transport, left_gate=gate)
    writer.transport.abort()
    relay.close()
    sink.close()


def test_the_read_buffer_starts_small_and_grows_for_a_bulk_stream(run_loop):
    """A stream of small messages keeps a 16 KiB read buffer; the first read that fills
    it (a bulk stream) moves the pump to its full buffer size; bytes stay exact."""
    run_loop(read_buffer_grows())


async def read_buffer_grows():
    from interceptor.pump import DEFAULT_BUFFER_SIZE, FIRST_BUFFER_SIZE

    echo = await echo_server()
    spliced: list = []
    loop = asyncio.get_running_loop()
    relay = await loop.create_server(lambda: HeaderThenSplice(echo.sockets[0].getsockname()[1], spliced),
                                     "127.0.0.1", 0)
    reader, writer = await asyncio.open_connection("127.0.0.1", relay.sockets[0].getsockname()[1])
    writer.write(b"header\nsmall")
    assert await asyncio.wait_for(reader.readexactly(5), 10) == b"small"
    left = spliced[0][0].get_protocol()
    assert len(left.get_buffer(-1)) == FIRST_BUFFER_SIZE
    payload = os.urandom(4 * 1024 * 1024)
    writer.write(payload)
    assert await asyncio.wait_for(reader.readexactly(len(payload)), 30) == payload
    assert len(left.get_buffer(-1)) == DEFAULT_BUFFER_SIZE
    writer.close()
    relay.close()
    echo.close()


def test_a_receiver_that_stops_reading_is_cut_after_the_stall_timeout(tls_pair, run_loop):
    """A subscriber that stops reading (an insider's, or a stuck process) would block the
    sender for good (a rospy publisher with queue_size=None waits for every subscriber):
    once the relay's buffer toward it stayed full for ``stall_timeout``, both sides are
    cut and the refusal is reported (``stalled_stream``); the sender is free."""
    run_loop(stalled_receiver_is_cut(*tls_pair))


async def stalled_receiver_is_cut(server_ctx, client_ctx):
    loop = asyncio.get_running_loop()
    sink_connected = asyncio.Event()
    sink_transports = []

    class Sink(asyncio.Protocol):
        def connection_made(self, transport):
            asyncio.get_running_loop().call_soon(transport.pause_reading)  # never reads
            sink_transports.append(transport)
            sink_connected.set()

    sink = await loop.create_server(Sink, "127.0.0.1", 0)
    spliced: list = []
    denied: list = []
    relay = await loop.create_server(
        lambda: HeaderThenSplice(sink.sockets[0].getsockname()[1], spliced, stall_timeout=0.5, on_deny=denied.append),
        "127.0.0.1", 0, ssl=server_ctx)
    reader, writer = await asyncio.open_connection(
        "127.0.0.1", relay.sockets[0].getsockname()[1], ssl=client_ctx, server_hostname="localhost")
    writer.write(b"header\n")
    await asyncio.wait_for(sink_connected.wait(), timeout=10)
    chunk = b"x" * (1 << 20)
    try:  # the relay fills toward the sink, waits 0.5 s, then cuts the sender's stream too
        for _ in range(256):
            writer.write(chunk)
            await asyncio.wait_for(writer.drain(), timeout=10)  # blocked for good (TimeoutError) if never cut
    except (ConnectionError, OSError):
        pass
    await asyncio.wait_for(spliced[0][2], timeout=10)  # both sides closed
    assert [exc.reason for exc in denied] == ["stalled_stream"], denied
    writer.transport.abort()
    for t in sink_transports:
        t.close()
    relay.close()
    sink.close()
