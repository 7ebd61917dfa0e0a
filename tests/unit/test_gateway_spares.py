"""Spare connections across a reload (a real gateway, real TLS to a real peer socket).

A spare still in its TLS handshake when a reload drops the spares was made with the
old client context: a token bound to the new certificate is refused over it. The
handshake is held by a relay in front of the peer until the test lets it through, so
the race (the drop lands while the spare is connecting) happens every time, no sleep.
"""

from __future__ import annotations

import asyncio
import contextlib

import pytest

from cryptoros.tls import TLSConfig, server_context
from interceptor.config import parse
from interceptor.gateway import Gateway


@pytest.fixture
def gateway_cfg(pki, tmp_path):
    own = pki.issue("robot1", kind="interceptor", sans=("IP:127.0.0.1",))
    return parse({
        "manager": "robot1",
        "tls": {"ca": str(pki.ca_cert), "cert": str(own.cert_path), "key": str(own.key_path)},
        "authz": {"url": "https://127.0.0.1:9"},  # never asked: no token is needed to connect
        "listen": {"public": "127.0.0.1:9", "local_master": "127.0.0.1:9"},
        "master": {"interceptor": "127.0.0.1:9"},
    }, base=tmp_path)


@contextlib.asynccontextmanager
async def held_peer(pki):
    """A peer interceptor's TLS endpoint behind a relay that holds each connection
    (accepted, nothing forwarded: the client's handshake waits) until ``release`` is set."""
    issued = pki.issue("robot2", kind="interceptor", sans=("IP:127.0.0.1",))
    ctx = server_context(TLSConfig(ca_file=pki.ca_cert, cert_file=issued.cert_path, key_file=issued.key_path))
    accepted, release = asyncio.Event(), asyncio.Event()
    held: list[asyncio.StreamWriter] = []

    async def peer(reader, writer):
        held.append(writer)
        await reader.read()  # a spare: TLS done, no preamble until it is used

    async def pipe(reader, writer):
        with contextlib.suppress(OSError):
            while data := await reader.read(65536):
                writer.write(data)
                await writer.drain()
        writer.close()

    async def relay(reader, writer):
        held.append(writer)
        accepted.set()
        await release.wait()
        up_reader, up_writer = await asyncio.open_connection("127.0.0.1", peer_port)
        held.append(up_writer)
        await asyncio.gather(pipe(reader, up_writer), pipe(up_reader, writer))

    peer_server = await asyncio.start_server(peer, "127.0.0.1", 0, ssl=ctx)
    peer_port = peer_server.sockets[0].getsockname()[1]
    relay_server = await asyncio.start_server(relay, "127.0.0.1", 0)
    try:
        yield ("127.0.0.1", relay_server.sockets[0].getsockname()[1]), accepted, release
    finally:
        for writer in held:
            writer.close()
        for server in (relay_server, peer_server):
            server.close()


async def spare_made(gateway_cfg, pki, *, reload_meanwhile: bool):
    """Make one spare to the held peer; ``reload_meanwhile``: drop the spares (as a
    reload does) while its handshake is under way. Returns the gateway once the spare
    finished connecting, and the task keeping it."""
    gw = Gateway(gateway_cfg)
    async with held_peer(pki) as (endpoint, accepted, release):
        keeper = asyncio.ensure_future(gw.keep_spare(endpoint))
        await asyncio.wait_for(accepted.wait(), 10)  # TCP connected, TLS handshake waiting
        (connecting,) = gw.spares_connecting(endpoint)
        if reload_meanwhile:
            gw.drop_spares()
        release.set()
        await asyncio.wait_for(connecting, 10)  # handshake done: listed as a spare, or not
        listed = gw.spares_ready(endpoint)
        if reload_meanwhile:
            await asyncio.wait_for(keeper, 10)  # nothing kept: the task ends at once
        keeper.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await keeper
        gw.drop_spares()
        await gw.authz.close()
    return gw, listed


async def test_a_spare_connected_across_a_reload_is_closed_not_listed(gateway_cfg, pki):
    gw, listed = await spare_made(gateway_cfg, pki, reload_meanwhile=True)
    assert listed == []
    assert 'cryptoros_interceptor_spare_connections_total{outcome="stale"} 1.0' in gw.metrics.render().decode()
    assert 'outcome="made"' not in gw.metrics.render().decode()


async def test_a_spare_connected_without_a_reload_is_listed(gateway_cfg, pki):
    gw, listed = await spare_made(gateway_cfg, pki, reload_meanwhile=False)
    assert len(listed) == 1 and listed[0].ssl_object is not None
    assert 'cryptoros_interceptor_spare_connections_total{outcome="made"} 1.0' in gw.metrics.render().decode()
