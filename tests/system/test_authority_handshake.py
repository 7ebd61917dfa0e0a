"""A revoked certificate is refused at the TLS handshake on an interceptor's public
port, not only when its stream's token is checked: with no SIGHUP, as soon as the
revocation feed lists its serial (``cryptoros-certs revoke`` writes the CRL, the
authorization server re-reads it), and on a resumed handshake too (OpenSSL does not
verify a resumed session's certificate again). Real interceptors, real daemon, real
TLS sockets.
"""

from __future__ import annotations

import re
import socket
import ssl
import time
import urllib.request

import pytest

from cryptoros.tunnel import Preamble, encode
from tests.interceptor_harness import robot_network, rogue_preamble

pytestmark = [pytest.mark.ros1]


def client(network, cert, key) -> ssl.SSLContext:
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.check_hostname = False
    ctx.load_verify_locations(cafile=str(network.pki.ca_cert))
    ctx.load_cert_chain(str(cert), str(key))
    return ctx


def handshake_refused(ctx: ssl.SSLContext, host: str, port: int, session=None) -> bool:
    """True when the server fails the handshake. Under TLS 1.3 its verdict on the client
    certificate comes after the client's side of the handshake is done: an alert or the
    connection closed with nothing sent, on the first read. A stream refused after the
    handshake answers the preamble instead."""
    raw = socket.create_connection((host, port), timeout=10)
    try:
        with ctx.wrap_socket(raw, server_hostname=host, session=session) as s:
            s.sendall(encode(Preamble(token="x", purpose="node", target="1")))
            return s.recv(1) == b""
    except (ssl.SSLError, ConnectionError):
        return True
    finally:
        raw.close()


def test_a_certificate_revoked_by_the_ca_fails_the_handshake_without_a_reload(tmp_path):
    with robot_network(tmp_path, start=("master", "robot_a")) as network:
        host = network.hosts["robot_a"]
        revoked = network.pki.issue("revoked_robot", kind="interceptor", sans=("IP:127.0.0.9",))
        ctx = client(network, revoked.cert_path, revoked.key_path)
        # before its revocation the certificate passes the handshake; the stream is then
        # refused for its token (not a handshake failure) and the session kept
        raw = socket.create_connection((host.address, host.public_port), timeout=10)
        with ctx.wrap_socket(raw, server_hostname=host.address) as s:
            assert rogue_preamble(s, "x", "node", "1").ok is False
            session = s.session
        assert session is not None and session.has_ticket
        assert not handshake_refused(ctx, host.address, host.public_port)
        network.pki.revoke("revoked_robot")  # the CRL file changes; nobody is signalled
        deadline = time.monotonic() + 10
        while not handshake_refused(ctx, host.address, host.public_port):
            assert time.monotonic() < deadline, "a revoked certificate still passed the handshake 10 s later"
            time.sleep(0.2)
        assert handshake_refused(ctx, host.address, host.public_port, session=session)  # resumed: refused too
        assert host.proc.poll() is None
        assert re.search(r"DENY tls handshake: certificate_revoked: .*revoked by the CA", host.logs())
        text = urllib.request.urlopen(f"http://127.0.0.1:{host.metrics_port}/metrics", timeout=5).read().decode()
        assert re.search(r'cryptoros_interceptor_denied_total\{kind="tls",reason="certificate_revoked"\} [2-9]', text)
