"""The interceptor's reads of a peer's XML-RPC: one deadline per message, not per read
(real sockets on loopback, both event loops)."""

from __future__ import annotations

import asyncio
import time

import pytest

from cryptoros.ros1.xmlrpc import Request, Role, XmlRpcConnection
from interceptor.ros1 import read_xmlrpc


@pytest.fixture(params=["asyncio", "uvloop"])
def run_loop(request):
    if request.param == "uvloop":
        uvloop = pytest.importorskip("uvloop")
        return uvloop.run
    return asyncio.run


async def _dribbled(every: float, timeout: float, whole: bool) -> tuple[object, float]:
    """A client sends a request a byte every ``every`` s (all at once with ``whole``);
    the server reads it with ``read_xmlrpc(..., timeout)``: (event or exception, seconds)."""
    request = XmlRpcConnection(Role.CLIENT).send(Request(method="getPid", params=("/x",)))
    outcome: asyncio.Future = asyncio.get_running_loop().create_future()

    async def serve(reader, writer):
        started = time.monotonic()
        try:
            event = await read_xmlrpc(reader, XmlRpcConnection(Role.SERVER), timeout)
        except BaseException as exc:  # noqa: BLE001 - the outcome under test
            event = exc
        outcome.set_result((event, time.monotonic() - started))
        writer.close()

    server = await asyncio.start_server(serve, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    _reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        if whole:
            writer.write(request)
        else:
            for i in range(len(request)):
                if outcome.done():
                    break
                writer.write(request[i:i + 1])
                await asyncio.sleep(every)
        return await asyncio.wait_for(outcome, 10)
    finally:
        writer.close()
        server.close()


def test_a_request_dribbled_a_byte_at_a_time_is_cut_at_the_overall_deadline(run_loop):
    # each read comes well within the deadline; the whole request never does
    event, took = run_loop(_dribbled(every=0.02, timeout=0.5, whole=False))
    assert isinstance(event, TimeoutError), event
    assert 0.45 <= took < 2.0  # (libuv timers fire to the millisecond, maybe a hair early)


def test_a_request_sent_whole_is_read_well_within_the_deadline(run_loop):
    event, took = run_loop(_dribbled(every=0, timeout=5, whole=True))
    assert isinstance(event, Request) and event.method == "getPid" and event.params == ("/x",)
    assert took < 5
