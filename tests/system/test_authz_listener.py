"""The authorization server's public socket (authz_server/listener.py): connections in
their TLS handshake are capped per source address from accept, and in all, where the
oldest gives its place to a new one; a source a verified client came from is not
counted in all. Real TLS sockets on loopback
addresses (as distinct sources), real certificates."""

from __future__ import annotations

import asyncio
import socket
import ssl

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


def test_failed_handshakes_are_counted_and_summed_up_in_one_warning(pki, tmp_path, caplog):
    """No client certificate, a self-signed one, bytes that are not TLS: each failed
    handshake counted (the server's /metrics counter is called), and one WARNING line for
    the lot naming the latest source and reason, not one per handshake."""
    import logging
    import subprocess

    server = pki.issue("authz", kind="server", sans=("IP:127.0.0.1",))
    ctx = server_context(TLSConfig(ca_file=pki.ca_cert, cert_file=server.cert_path, key_file=server.key_path))
    subprocess.run(["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
                    "-subj", "/CN=stranger", "-days", "1", "-keyout", str(tmp_path / "self.key"),
                    "-out", str(tmp_path / "self.pem")], check=True, capture_output=True)
    counted = []

    async def scenario() -> None:
        loop = asyncio.get_running_loop()
        listener = TLSListener("127.0.0.1", 0, ctx, Hello, failed_summary_seconds=0.5,
                               on_failed_handshake=lambda: counted.append(1))
        listener.start()
        port = listener._sock.getsockname()[1]

        async def attempt(client: ssl.SSLContext | None, source: str) -> None:
            if client is None:  # not TLS at all
                sock = socket.socket()
                sock.bind((source, 0))
                sock.setblocking(False)
                await loop.sock_connect(sock, ("127.0.0.1", port))
                await loop.sock_sendall(sock, b"GET / HTTP/1.1\r\n\r\n")
                await loop.sock_recv(sock, 1)
                sock.close()
                return
            try:
                reader, writer = await asyncio.open_connection("127.0.0.1", port, ssl=client, local_addr=(source, 0),
                                                               server_hostname="127.0.0.1")
                await asyncio.wait_for(reader.read(2), 5)  # TLS 1.3: the refusal comes after the client's Finished
                writer.close()
            except (OSError, ssl.SSLError):
                pass

        anonymous = ssl.create_default_context(cafile=str(pki.ca_cert))
        anonymous.check_hostname = False
        self_signed = ssl.create_default_context(cafile=str(pki.ca_cert))
        self_signed.check_hostname = False
        self_signed.load_cert_chain(tmp_path / "self.pem", tmp_path / "self.key")
        try:
            await attempt(anonymous, "127.0.0.11")
            await attempt(self_signed, "127.0.0.12")
            await attempt(None, "127.0.0.13")
            for _ in range(100):
                if listener.failed == 3:
                    break
                await asyncio.sleep(0.02)
            assert listener.failed == 3 and len(counted) == 3
            await asyncio.sleep(0.8)  # the summary due 0.5 s after the first failure
        finally:
            await listener.close()

    with caplog.at_level(logging.WARNING, logger="cryptoros.authz"):
        asyncio.run(scenario())
    lines = [r.getMessage() for r in caplog.records if "TLS handshakes refused" in r.getMessage()]
    assert len(lines) == 1 and lines[0].startswith("3 TLS handshakes refused in the last 1 s, latest from 127.0.0.13: "), \
        lines
