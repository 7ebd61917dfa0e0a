"""The authorization server's public socket (authz_server/listener.py): connections in
their TLS handshake are capped per source address from accept, and in all, where the
oldest gives its place to a new one; a source a verified client came from is not
counted in all. Real TLS sockets on loopback
addresses (as distinct sources), real certificates."""

from __future__ import annotations

import asyncio
import socket

from authz_server.listener import TLSListener
from cryptoros.tls import TLSConfig, client_context, server_context


class Hello(asyncio.Protocol):
    def connection_made(self, transport) -> None:
        transport.write(b"ok")


def test_half_open_connections_are_capped_per_source_and_in_all_and_known_sources_still_get_in(pki):
    server = pki.issue("authz", kind="server", sans=("IP:127.0.0.1",))
    robot = pki.issue("robot")
    ctx = server_context(TLSConfig(ca_file=pki.ca_cert, cert_file=server.cert_path, key_file=server.key_path))
    client_ctx = client_context(TLSConfig(ca_file=pki.ca_cert, cert_file=robot.cert_path, key_file=robot.key_path),
                                check_hostname=False)

    async def scenario() -> None:
        loop = asyncio.get_running_loop()
        listener = TLSListener("127.0.0.1", 0, ctx, Hello, per_source=4, in_all=6, handshake_timeout=60,
                               uncapped_source=lambda _source: False)
        listener.start()
        port = listener._sock.getsockname()[1]

        async def robot_from(source: str) -> bytes:
            reader, writer = await asyncio.open_connection("127.0.0.1", port, ssl=client_ctx, local_addr=(source, 0),
                                                           server_hostname="127.0.0.1")
            try:
                return await asyncio.wait_for(reader.read(2), 5)
            finally:
                writer.close()

        def half_open(source: str) -> socket.socket:  # no ClientHello: the stranger's connection
            sock = socket.socket()
            sock.bind((source, 0))
            sock.connect(("127.0.0.1", port))
            sock.setblocking(False)
            return sock

        async def closed(sock: socket.socket) -> bool:  # asked once the listener decided on every one
            try:
                return await asyncio.wait_for(loop.sock_recv(sock, 1), 0.2) == b""
            except asyncio.TimeoutError:
                return False  # held open
            except OSError:
                return True

        try:
            assert await robot_from("127.0.0.1") == b"ok"  # known from now on
            strangers = [half_open("127.0.0.98") for _ in range(6)] + [half_open("127.0.0.97") for _ in range(4)]
            for _ in range(250):
                if listener.pending() + listener.refused + listener.evicted == len(strangers):
                    break
                await asyncio.sleep(0.02)
            verdicts = [await closed(sock) for sock in strangers]
            # .98: 4 taken (its cap; 2 more closed at accept); .97's 4 fill the 6 in all, the
            # last two taking the places of the oldest of the source holding the most (.98's
            # first two, closed)
            assert verdicts == [True] * 2 + [False] * 2 + [True] * 2 + [False] * 4, verdicts
            assert listener.pending() == 6 and listener.refused == 2 and listener.evicted == 2
            assert await robot_from("127.0.0.1") == b"ok"  # a known source is not counted in all
            # a new source with all full: it takes the place of the oldest connection of the
            # source holding the most (.97's 4 against .98's 2), and gets in
            assert await robot_from("127.0.0.96") == b"ok"
            assert listener.evicted == 3 and await closed(strangers[6]) and not await closed(strangers[2])
            for sock in strangers:
                sock.close()
            for _ in range(100):  # the held handshakes end with their sockets
                if listener.pending() == 0:
                    break
                await asyncio.sleep(0.02)
            assert listener.pending() == 0
            assert await robot_from("127.0.0.96") == b"ok"
        finally:
            await listener.close()

    asyncio.run(scenario())
