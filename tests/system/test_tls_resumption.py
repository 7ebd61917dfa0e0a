"""TLS 1.3 session resumption between interceptors, over real TLS sockets:
asyncio and uvloop clients resume through :class:`cryptoros.tls.ResumingContext`, a
session the server cannot use falls back to a full handshake, the certificate checks a
resumed handshake skips run on every stream, and between real interceptor processes
the second stream to a peer is resumed while a revoked certificate is still refused."""

from __future__ import annotations

import asyncio
import signal
import ssl
import time
import urllib.request

import pytest
from cryptography import x509

from cryptoros.errors import ConfigError, TokenError
from cryptoros.tls import (
    LIFETIME_SLACK,
    FullHandshakes,
    PeerCertificateCheck,
    SessionCache,
    TLSConfig,
    client_context,
    offering,
    server_context,
)
from cryptoros.pemfiles import cert_der
from cryptoros.tunnel import Preamble, PreambleReader, PreambleReply, encode
from tests.interceptor_harness import NODE, SYS_PY, got, read_lines, robot_network
from tests.support import running

ENDPOINT = ("127.0.0.1", 0)


def tls_config(issued, pki, **kw) -> TLSConfig:
    return TLSConfig(ca_file=pki.ca_cert, cert_file=issued.cert_path, key_file=issued.key_path, crl_file=pki.crl, **kw)


@pytest.fixture
def pair(pki):
    pki.pki.write_crl()
    server = pki.issue("icp_server", kind="interceptor", sans=("IP:127.0.0.1",))
    client = pki.issue("icp_client", kind="interceptor", sans=("IP:127.0.0.1",))
    return tls_config(server, pki), tls_config(client, pki)


class EchoServer:
    """An asyncio TLS server that answers each connection with whether it was resumed
    and the SHA-256 of the client certificate it sees, then closes."""

    def __init__(self, ctx: ssl.SSLContext) -> None:
        self.ctx = ctx
        self.seen: list[tuple[bool, bytes]] = []

    async def __aenter__(self) -> EchoServer:
        async def handle(reader, writer):
            tls = writer.get_extra_info("ssl_object")
            self.seen.append((tls.session_reused, tls.getpeercert(binary_form=True)))
            await reader.read(16)
            writer.write(b"resumed" if tls.session_reused else b"full")
            await writer.drain()
            writer.close()

        self.server = await asyncio.start_server(handle, "127.0.0.1", 0, ssl=self.ctx)
        self.port = self.server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *exc) -> None:
        self.server.close()
        await self.server.wait_closed()


async def connect(port: int, ctx: ssl.SSLContext, cache: SessionCache) -> tuple[bool, bytes, bytes]:
    """One connection the way the gateway opens a tunnel: offer the kept session, read
    the answer (the TLS 1.3 ticket arrives before it), keep the new session."""
    offer = cache.get(("127.0.0.1", port))
    with offering(ctx, offer):
        reader, writer = await asyncio.open_connection("127.0.0.1", port, ssl=ctx, server_hostname="127.0.0.1")
    try:
        tls = writer.get_extra_info("ssl_object")
        writer.write(b"hi")
        answer = await reader.read(16)
        cache.put(("127.0.0.1", port), tls, offer)
        return tls.session_reused, tls.getpeercert(binary_form=True), answer
    finally:
        writer.close()


def run_on(loop_kind: str, coro_fn):
    if loop_kind == "uvloop":
        import uvloop

        return uvloop.run(coro_fn())
    return asyncio.run(coro_fn())


# ------------------------------------------------------------------ resumption on real sockets


@pytest.mark.parametrize("loop_kind", ["asyncio", "uvloop"])
def test_the_second_connection_resumes_and_both_ends_still_see_the_peer_certificate(pair, loop_kind):
    server_cfg, client_cfg = pair
    ctx = client_context(client_cfg, resumable=True)
    cache = SessionCache(ctx, lifetime=300)

    async def main():
        async with EchoServer(server_context(server_cfg, tickets=1)) as server:
            first = await connect(server.port, ctx, cache)
            kept = cache.get(("127.0.0.1", server.port))
            second = await connect(server.port, ctx, cache)
            third = await connect(server.port, ctx, cache)
            # the full handshake's ticket resumed both: it is kept, not replaced by their new ones
            assert cache.get(("127.0.0.1", server.port)) is kept
        return first, second, third, server.seen

    first, second, third, seen = run_on(loop_kind, main)
    assert (first[0], first[2]) == (False, b"full")
    assert (second[0], second[2]) == (True, b"resumed")
    assert (third[0], third[2]) == (True, b"resumed")  # the same ticket, offered again
    # after resumption each end still has the other's certificate (from the session)
    assert first[1] and second[1] == first[1] == third[1]
    assert [reused for reused, _ in seen] == [False, True, True]
    assert seen[0][1] and seen[1][1] == seen[0][1] == seen[2][1]


def test_a_session_the_server_cannot_use_falls_back_to_a_full_handshake(pair):
    """A ticket sealed by another server context (a restart or a reload draws new ticket
    keys, as a tampered ticket fails to open): the handshake is simply full."""
    server_cfg, client_cfg = pair
    ctx = client_context(client_cfg, resumable=True)

    async def main():
        cache = SessionCache(ctx, lifetime=300)
        async with EchoServer(server_context(server_cfg, tickets=1)) as old:
            await connect(old.port, ctx, cache)
            offer = cache.get(("127.0.0.1", old.port))
        assert offer is not None
        async with EchoServer(server_context(server_cfg, tickets=1)) as new:
            moved = SessionCache(ctx, lifetime=300)
            with offering(ctx, offer):  # the old server's session, offered to the new one
                reader, writer = await asyncio.open_connection("127.0.0.1", new.port, ssl=ctx,
                                                               server_hostname="127.0.0.1")
            writer.write(b"hi")
            answer = await reader.read(16)
            reused = writer.get_extra_info("ssl_object").session_reused
            moved.put(("127.0.0.1", new.port), writer.get_extra_info("ssl_object"), offer)
            writer.close()
            again = await connect(new.port, ctx, moved)
        return reused, answer, again

    reused, answer, again = asyncio.run(main())
    assert (reused, answer) == (False, b"full")
    assert (again[0], again[2]) == (True, b"resumed")  # and the new ticket resumes


def test_a_session_past_its_lifetime_is_not_offered_and_the_handshake_is_full(pair):
    server_cfg, client_cfg = pair
    ctx = client_context(client_cfg, resumable=True)
    cache = SessionCache(ctx, lifetime=30)

    async def main():
        async with EchoServer(server_context(server_cfg, tickets=1)) as server:
            await connect(server.port, ctx, cache)
            endpoint = ("127.0.0.1", server.port)
            origin = cache.get(endpoint).origin
            resumed = await connect(server.port, ctx, cache)
            # the resumed connection's new ticket keeps the full handshake's time
            assert cache.get(endpoint).origin == origin
            assert cache.get(endpoint, now=origin + 31) is None  # too old: dropped
            late = await connect(server.port, ctx, cache)
        return resumed, late

    resumed, late = asyncio.run(main())
    assert resumed[0] is True
    assert (late[0], late[2]) == (False, b"full")


def test_tls12_sessions_are_never_kept(pki, pair):
    """A TLS 1.2 resumption has no fresh key exchange (no forward secrecy): not offered."""
    server_cfg, client_cfg = pair
    ctx = client_context(client_cfg, resumable=True)
    cache = SessionCache(ctx, lifetime=300)
    pinned = TLSConfig(ca_file=server_cfg.ca_file, cert_file=server_cfg.cert_file, key_file=server_cfg.key_file,
                       crl_file=server_cfg.crl_file, pin_tls12=True)

    async def main():
        async with EchoServer(server_context(pinned, tickets=1)) as server:
            first = await connect(server.port, ctx, cache)
            second = await connect(server.port, ctx, cache)
        return first, second

    first, second = asyncio.run(main())
    assert len(cache) == 0
    assert (first[0], second[0]) == (False, False)


def test_a_plain_client_context_never_offers_a_session(pair):
    server_cfg, client_cfg = pair
    resuming = client_context(client_cfg, resumable=True)
    plain = client_context(client_cfg)
    cache = SessionCache(resuming, lifetime=300)

    async def main():
        async with EchoServer(server_context(server_cfg, tickets=1)) as server:
            await connect(server.port, resuming, cache)
            offer = cache.get(("127.0.0.1", server.port))
            with offering(resuming, offer):  # offered to the resuming context, not to ``plain``
                reader, writer = await asyncio.open_connection("127.0.0.1", server.port, ssl=plain,
                                                               server_hostname="127.0.0.1")
            writer.write(b"hi")
            await reader.read(16)
            reused = writer.get_extra_info("ssl_object").session_reused
            writer.close()
        return reused

    assert asyncio.run(main()) is False


# ------------------------------------------------------------------ what a resumed handshake skips


def test_full_handshakes_refuses_a_resumed_stream_past_the_lifetime_or_never_seen(pki):
    der = cert_der(pki.issue("peer").cert_path)
    record = FullHandshakes(60)
    with pytest.raises(TokenError) as info:
        record.admit(der, resumed=True, now=100.0)  # no full handshake seen (a restart, evicted)
    assert info.value.reason == "session_too_old"
    record.admit(der, resumed=False, now=100.0)
    record.admit(der, resumed=True, now=100.0 + 60 + LIFETIME_SLACK - 0.5)
    with pytest.raises(TokenError) as info:
        record.admit(der, resumed=True, now=100.0 + 60 + LIFETIME_SLACK)
    assert info.value.reason == "session_too_old"
    with pytest.raises(TokenError) as info:
        record.admit(der, resumed=True, version="TLSv1.2", now=101.0)
    assert info.value.reason == "session_not_tls13"
    off = FullHandshakes(0)
    off.admit(der, resumed=False, now=1.0)
    with pytest.raises(TokenError):
        off.admit(der, resumed=True, now=1.0)


def _der(issued) -> bytes:
    return cert_der(issued.cert_path)


def test_peer_certificate_check_refuses_expired_not_yet_valid_and_crl_revoked(pki):
    good, gone = pki.issue("good"), pki.issue("gone")
    check = PeerCertificateCheck(pki.revoke("gone"))
    cert = x509.load_pem_x509_certificate(good.cert_path.read_bytes())
    check.check(_der(good))  # valid now, not on the CRL
    for now, reason in ((cert.not_valid_after_utc.timestamp() + 1, "certificate_expired"),
                        (cert.not_valid_before_utc.timestamp() - 1, "certificate_not_yet_valid")):
        with pytest.raises(TokenError) as info:
            check.check(_der(good), now=now)
        assert info.value.reason == reason
    with pytest.raises(TokenError) as info:
        check.check(_der(gone))
    assert info.value.reason == "certificate_revoked"
    assert PeerCertificateCheck(None).check(_der(gone)) is None  # no CRL configured: validity only


def test_peer_certificate_check_reads_every_crl_of_a_bundle_by_issuer(pki, other_pki, tmp_path):
    """A CRL file holding several CRLs (as OpenSSL reads one) revokes what any of them
    revokes, each for its own issuer: another CA's revocation of the same serial does not
    touch ours."""
    ours, gone = pki.issue("ours"), pki.issue("gone")
    theirs = other_pki.issue("theirs")
    bundle = tmp_path / "bundle.crl"
    bundle.write_bytes(other_pki.revoke("theirs").read_bytes() + pki.revoke("gone").read_bytes())
    check = PeerCertificateCheck(bundle)
    assert len(check.revoked) == 2
    check.check(_der(ours))
    for revoked in (gone, theirs):
        with pytest.raises(TokenError) as info:
            check.check(_der(revoked))
        assert info.value.reason == "certificate_revoked"
    theirs_serial = x509.load_pem_x509_certificate(theirs.cert_path.read_bytes()).serial_number
    ours_issuer = x509.load_pem_x509_certificate(ours.cert_path.read_bytes()).issuer.public_bytes()
    assert (ours_issuer, theirs_serial) not in check.revoked  # a serial counts for its issuer only
    (tmp_path / "empty.crl").write_bytes(b"-----BEGIN NOTHING-----\n")
    with pytest.raises(ConfigError, match="no PEM CRL"):
        PeerCertificateCheck(tmp_path / "empty.crl")


# ------------------------------------------------------------------ between real interceptors

@pytest.fixture(scope="module")
def network(tmp_path_factory):
    spares = "[limits]\nspare_connections = true"  # B keeps spare connections (the default, said here)
    with robot_network(tmp_path_factory.mktemp("net"), start=("master", "robot_a", "robot_b"),
                       extra={"robot_b": spares}) as net:
        yield net


def counters(network, host: str, family: str) -> dict[tuple[str, ...], float]:
    """One counter family of ``host``'s interceptor, by its label values."""
    text = urllib.request.urlopen(f"http://127.0.0.1:{network.hosts[host].metrics_port}/metrics", timeout=5).read()
    out = {}
    for line in text.decode().splitlines():
        if line.startswith(f"cryptoros_interceptor_{family}_total{{"):
            labels, value = line.split("} ")
            fields = dict(part.split("=") for part in labels.split("{", 1)[1].split(","))
            out[tuple(v.strip('"') for _k, v in sorted(fields.items()))] = float(value)
    return out


def handshakes(network, host: str) -> dict[tuple[str, str], float]:
    return counters(network, host, "tls_handshakes")  # (direction, kind)


def flow(network) -> list[str]:
    """A talker on A and a listener on B (fresh processes, granted names) exchange 3 messages."""
    with running([SYS_PY, NODE, "sub", "/rospy_listener", "/chatter", "20"], env=network.ros_env("robot_b")) as sub:
        read_lines(sub, "READY", 20)
        with running([SYS_PY, NODE, "pub", "/talker_a", "/chatter", "3", "20", "1"], env=network.ros_env("robot_a")):
            return got(read_lines(sub, "GOT secret-2", 30))


@pytest.mark.ros1
def test_the_second_topic_stream_between_two_interceptors_is_resumed(network):
    assert flow(network)
    before_b, before_a = handshakes(network, "robot_b"), handshakes(network, "robot_a")
    assert before_b.get(("out", "full"), 0) >= 1
    assert flow(network)
    after_b, after_a = handshakes(network, "robot_b"), handshakes(network, "robot_a")
    assert after_b.get(("out", "resumed"), 0) > before_b.get(("out", "resumed"), 0)
    assert after_a.get(("in", "resumed"), 0) > before_a.get(("in", "resumed"), 0)


@pytest.mark.ros1
def test_a_revoked_certificate_is_refused_on_a_resumed_stream_and_after_a_reload(network):
    """robot_c (not running) resumes to A by hand with its genuine certificate and
    token. Once the CA revokes the certificate, the feed carries its serial: the next
    stream is resumed at the TLS layer (A's CRL is as loaded) but refused by the check
    every stream gets. After A reloads (SIGHUP: new CRL, new ticket keys) the old session
    is not resumed and the full handshake fails on the CRL."""
    a = network.hosts["robot_a"]
    cert, key = network.pki.pki.cert_path_for("robot_c"), network.pki.pki.key_path_for("robot_c")
    ctx = client_context(TLSConfig(ca_file=network.pki.ca_cert, cert_file=cert, key_file=key), check_hostname=False,
                         resumable=True)
    cache = SessionCache(ctx, lifetime=300)
    status, body = network.daemon.token("robot_c")
    assert status == 200, body
    token = body["access_token"]

    async def stream() -> tuple[bool, bool | None]:
        """(resumed, preamble accepted) of one refresh stream to A; None: A closed (a FIN,
        or a reset when our preamble reached a socket A had closed already: which of the
        two a refusal in the handshake gives depends on timing alone)."""
        offer = cache.get((a.address, a.public_port))
        with offering(ctx, offer):
            reader, writer = await asyncio.wait_for(asyncio.open_connection(
                a.address, a.public_port, ssl=ctx, server_hostname=a.address), 10)
        try:
            tls = writer.get_extra_info("ssl_object")
            writer.write(encode(Preamble(token=token, purpose="refresh", target="")))
            preamble = PreambleReader(PreambleReply)
            while (event := preamble.next_event()) is not None and not isinstance(event, PreambleReply):
                try:
                    data = await asyncio.wait_for(reader.read(65536), 10)
                except ConnectionResetError:
                    data = b""
                if not data:
                    return tls.session_reused, None
                preamble.receive_data(data)
            cache.put((a.address, a.public_port), tls, offer)
            return tls.session_reused, event.ok
        finally:
            writer.close()

    async def main():
        assert await stream() == (False, True)
        assert await stream() == (True, True)
        network.pki.revoke("robot_c")
        deadline = time.monotonic() + 20
        while True:  # the daemon reads the CRL, A polls the feed (0.5 s)
            resumed, ok = await stream()
            assert resumed is True
            if not ok:
                break
            assert time.monotonic() < deadline, "the revoked certificate was still accepted"
            await asyncio.sleep(0.3)
        deadline = time.monotonic() + 5  # logged as robot A handles the refused handshake, after the client saw it
        while "certificate_revoked" not in a.logs():
            assert time.monotonic() < deadline, a.logs()[-2000:]
            await asyncio.sleep(0.1)
        a.proc.send_signal(signal.SIGHUP)
        deadline = time.monotonic() + 20
        while "reloaded" not in a.logs():
            assert time.monotonic() < deadline
            await asyncio.sleep(0.2)
        try:  # the old ticket is worthless, and the full handshake fails on the CRL
            outcome = await stream()
        except (ssl.SSLError, ConnectionError):
            outcome = None
        assert outcome in (None, (False, None))
        deadline = time.monotonic() + 5  # its log line comes as robot A handles it (the next test counts lines)
        while "is on the CRL" not in a.logs():
            assert time.monotonic() < deadline, a.logs()[-2000:]
            await asyncio.sleep(0.1)
        assert a.proc.poll() is None

    asyncio.run(main())


@pytest.mark.ros1
def test_spare_connections_are_used_or_carry_a_token_exchange_and_are_no_denial(network):
    """After a stream to A, B keeps one spare connection to A (TLS done, no preamble).
    The next stream (or a token exchange) goes over it; left unused for 0.4 x the
    preamble timeout (2 s) it carries a token exchange and closes. Either way A logs no
    denial for it (no preamble timeout), and streams keep working."""
    denials_before = [line for line in network.hosts["robot_a"].logs().splitlines() if "DENY" in line]
    spares_before = sum(counters(network, "robot_b", "spare_connections").values())
    assert flow(network)

    def settled(spares: dict) -> bool:
        """Spares were made, and each was used or, past its age, carried a token exchange
        and closed: nothing is left waiting at A."""
        made = spares.get(("made",), 0.0)
        return sum(spares.values()) > spares_before and made <= spares.get(("used",), 0.0) + \
            spares.get(("expired",), 0.0)

    deadline = time.monotonic() + 3 * 0.4 * 5.0 + 5.0
    while not settled(spares_after := counters(network, "robot_b", "spare_connections")):
        assert time.monotonic() < deadline, spares_after
        time.sleep(0.2)
    assert sum(spares_after.values()) >= spares_before + 1, spares_after
    assert "spare connection to 127.0.0.2" in network.hosts["robot_b"].logs()
    denials_after = [line for line in network.hosts["robot_a"].logs().splitlines() if "DENY" in line]
    assert denials_after == denials_before
    assert flow(network)
