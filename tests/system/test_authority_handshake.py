"""A revoked certificate is refused at the TLS handshake on an interceptor's public
port, not only when its stream's token is checked: with no SIGHUP, as soon as the
revocation feed lists its serial (``cryptoros-certs revoke`` writes the CRL, the
authorization server re-reads it), and on a resumed handshake too (OpenSSL does not
verify a resumed session's certificate again). Real interceptors, real daemon, real
TLS sockets.
"""

from __future__ import annotations

import json
import re
import signal
import socket
import ssl
import time
import urllib.request

import pytest

from cryptoros.tunnel import Preamble, encode
from tests.interceptor_harness import robot_network, rogue_preamble
from tests.support import until

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
        until(lambda: re.search(r"DENY tls from \S+: certificate_revoked: handshake: .*revoked by the CA", host.logs()),
              5, "the revoked handshake logged")
        text = urllib.request.urlopen(f"http://127.0.0.1:{host.metrics_port}/metrics", timeout=5).read().decode()
        assert re.search(r'cryptoros_interceptor_denied_total\{kind="tls",reason="certificate_revoked"\} [2-9]', text)


def test_an_out_of_date_crl_stops_no_valid_peer_and_an_older_crl_unrevokes_nothing(tmp_path):
    """The CRL's next-update time passed (nobody re-signed it in its 7 days): OpenSSL
    would refuse every peer from then on and the fleet stopped. Now every valid peer
    still passes the handshake, the serials the CRL lists are still refused, and
    ``cryptoros status`` warns. The authorization server keeps its newer CRL when an
    older one is copied over it (the older one would un-revoke what came after)."""
    with robot_network(tmp_path, start=("master", "robot_a")) as network:
        host = network.hosts["robot_a"]
        revoked = network.pki.issue("revoked_robot", kind="interceptor", sans=("IP:127.0.0.9",))
        valid = network.pki.issue("valid_robot", kind="interceptor", sans=("IP:127.0.0.9",))
        network.pki.revoke("valid_robot")  # the CRL in use: number 2, valid_robot on it
        authz_log = network.workdir / "authz.log"

        def feed_serials() -> list[str]:
            return network.daemon.get_json("/revocations", "robot_a")["revoked_serials"]

        deadline = time.monotonic() + 10
        while format(valid.serial, "x") not in feed_serials():
            assert time.monotonic() < deadline, "the authorization server never read the new CRL"
            time.sleep(0.2)
        network.pki.expired_crl(network.pki.crl, revoked.serial)  # older, out of date: lists revoked_robot only
        host.proc.send_signal(signal.SIGHUP)
        deadline = time.monotonic() + 15
        while "reloaded" not in host.logs():
            assert time.monotonic() < deadline, host.logs()[-2000:]
            time.sleep(0.1)
        assert "is out of date" in host.logs()
        assert handshake_refused(client(network, revoked.cert_path, revoked.key_path), host.address, host.public_port)
        robot_b = network.pki.pki  # a valid peer: robot B's own certificate passes the handshake
        ok_ctx = client(network, robot_b.cert_path_for("robot_b"), robot_b.key_path_for("robot_b"))
        assert not handshake_refused(ok_ctx, host.address, host.public_port)
        status = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{host.metrics_port}/status", timeout=5).read())
        assert status["health"] == "ok" and "out of date" in status["crl"]["warning"], status["crl"]
        # the authorization server kept CRL number 2: valid_robot is still revoked in its feed
        deadline = time.monotonic() + 10
        while "older than the CRL in use" not in authz_log.read_text():
            feed_serials()  # a feed request re-reads the CRL
            assert time.monotonic() < deadline, authz_log.read_text()[-2000:]
            time.sleep(0.2)
        assert feed_serials() == [format(valid.serial, "x")]
        # a CRL due within three days is logged on SIGHUP too, as the runbook says
        # (a README deployment audit: only `cryptoros status` said it)
        network.pki.expired_crl(network.pki.crl, revoked.serial, due_days=1)
        reloads = host.logs().count("reloaded")
        host.proc.send_signal(signal.SIGHUP)
        deadline = time.monotonic() + 15
        while host.logs().count("reloaded") == reloads:
            assert time.monotonic() < deadline, host.logs()[-2000:]
            time.sleep(0.1)
        assert "is due for re-signing by" in host.logs()
