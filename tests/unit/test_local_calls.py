"""Calls to a local master or node over kept-alive connections: reused, and made again on a new one when the
master closed a kept connection meanwhile (a real loopback server speaking our codec)."""

from __future__ import annotations

import asyncio

import pytest

from cryptoros.errors import RemoteProtocolError
from cryptoros.ros1.xmlrpc import ConnectionClosed, Request, Response, Role, XmlRpcConnection
from cryptoros.sansio import NEED_DATA
from interceptor.ros1.localcalls import LocalCalls, LocalXmlRpc


class Master:
    """Answers ``[1, "", <connection number>]``; ``close_after``: close each connection
    after that many answers (as a restarted or impatient master would)."""

    def __init__(self, close_after: int | None = None, answer: bool = True, extra: bool = False) -> None:
        self.extra = extra  # a second, unasked-for answer right behind each
        self.connections = 0
        self.requests = 0
        self.close_after = close_after
        self.answer = answer
        self.writers: list[asyncio.StreamWriter] = []

    async def serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        me = self.connections
        self.writers.append(writer)
        conn = XmlRpcConnection(Role.SERVER)
        answered = 0
        try:
            while True:
                event = conn.next_event()
                if event is NEED_DATA:
                    conn.receive_data(await reader.read(65536))
                    continue
                if isinstance(event, ConnectionClosed):
                    return
                self.requests += 1
                if not self.answer:
                    return  # closes without answering
                writer.write(conn.send(Response(value=[1, "", me])) +
                             (conn.send(Response(value=[1, "unasked", me])) if self.extra else b""))
                await writer.drain()
                answered += 1
                if self.close_after is not None and answered >= self.close_after:
                    return
        finally:
            writer.close()


@pytest.fixture
async def running():
    servers = []

    async def start(master: Master) -> str:
        server = await asyncio.start_server(master.serve, "127.0.0.1", 0)
        servers.append(server)
        return f"http://127.0.0.1:{server.sockets[0].getsockname()[1]}/"

    yield start
    for server in servers:
        server.close()


def call(n: int = 0) -> Request:
    return Request(method="getPid", params=(f"/caller{n}",))


async def test_calls_in_a_row_share_one_connection(running):
    master = Master()
    upstream = LocalXmlRpc(await running(master), max_body=1 << 20)
    replies = [await upstream.call(call(i)) for i in range(5)]
    assert [r.value for r in replies] == [[1, "", 1]] * 5
    assert master.connections == upstream.opened == 1
    upstream.close()


async def test_a_burst_opens_a_few_and_keeps_at_most_max_idle(running):
    master = Master()
    upstream = LocalXmlRpc(await running(master), max_body=1 << 20, max_idle=3)
    replies = await asyncio.gather(*(upstream.call(call(i)) for i in range(10)))
    assert all(r.value[0] == 1 for r in replies) and master.requests == 10
    again = await asyncio.gather(*(upstream.call(call(i)) for i in range(3)))
    assert {r.value[2] for r in again} <= {r.value[2] for r in replies}  # kept ones reused
    assert master.connections == 10  # the burst: one each; then the 3 kept
    upstream.close()


async def test_a_connection_the_master_closed_while_idle_is_replaced_and_the_call_made(running):
    master = Master(close_after=1)
    upstream = LocalXmlRpc(await running(master), max_body=1 << 20)
    first = await upstream.call(call())
    await asyncio.sleep(0.05)  # the master's close reaches us
    second = await upstream.call(call())
    assert (first.value[2], second.value[2]) == (1, 2) and master.requests == 2
    upstream.close()


async def test_calls_right_behind_a_master_that_closes_each_connection_are_all_answered(running):
    """No pause: the close may arrive before the next call (the kept connection is
    dropped) or after its request was written (the call is made again on a new one)."""
    master = Master(close_after=1)
    upstream = LocalXmlRpc(await running(master), max_body=1 << 20, idle_seconds=60)
    replies = [await upstream.call(call(i)) for i in range(20)]
    assert [r.value[2] for r in replies] == list(range(1, 21))
    upstream.close()


async def test_a_connection_with_an_unasked_for_answer_behind_its_answer_is_not_kept(running):
    master = Master(extra=True)
    upstream = LocalXmlRpc(await running(master), max_body=1 << 20)
    first = await upstream.call(call())
    second = await upstream.call(call())
    assert (first.value[1:], second.value[1:]) == (["", 1], ["", 2])  # never the stray answer
    upstream.close()


async def test_a_new_connection_closed_without_an_answer_is_an_error_not_a_loop(running):
    master = Master(answer=False)
    upstream = LocalXmlRpc(await running(master), max_body=1 << 20)
    with pytest.raises(RemoteProtocolError):
        await upstream.call(call())
    assert master.connections == 1


async def test_a_kept_connection_unused_for_idle_seconds_is_closed(running):
    master = Master()
    upstream = LocalXmlRpc(await running(master), max_body=1 << 20, idle_seconds=0.1)
    await upstream.call(call())
    assert upstream.idle_count == 1
    server_side = master.writers[0]
    deadline = asyncio.get_running_loop().time() + 5
    while not server_side.transport.is_closing():  # the master sees it close (bounded wait)
        assert asyncio.get_running_loop().time() < deadline, "the idle connection was never closed"
        await asyncio.sleep(0.02)
    assert upstream.idle_count == 0


async def test_local_calls_keep_one_server_per_uri_and_close_the_least_recently_used(running):
    masters = [Master() for _ in range(3)]
    uris = [await running(m) for m in masters]
    calls = LocalCalls(max_body=1 << 20, max_servers=2)
    for uri in (*uris, uris[2], uris[1]):
        assert (await calls.call(uri, call())).value[0] == 1
    assert [m.connections for m in masters] == [1, 1, 1]  # each reused its kept connection
    assert (await calls.call(uris[0], call())).value[2] == 2  # the first was closed past max_servers
    calls.close()
