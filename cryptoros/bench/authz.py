"""``cryptoros bench authz``: token issuing over real HTTPS, and token verification.

Starts ``cryptoros-authz serve`` as a subprocess on a free loopback port with a
throwaway CA and registry (SQLite in a temp dir, or ``--db URL``), then:

- tokens per second with N concurrent clients, each on a kept-alive mutual-TLS
  connection, and again with a new TLS handshake per token;
- latency percentiles of those requests;
- ``verify_access_token`` time in microseconds (one core, no I/O), with and without
  a revocation set, next to RS256 signing;
- the interceptor's verification per stream (``PeerVerifier.verify``) with its
  verified-token cache missing (a full verify) and hitting, and which checks ran.

It prints figures; nothing is asserted.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import shutil
import signal
import socket
import ssl
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import click

from cryptoros.lab.network import free_port


def _authz_exe() -> str:
    exe = Path(sys.executable).parent / "cryptoros-authz"
    return str(exe) if exe.exists() else (shutil.which("cryptoros-authz") or "cryptoros-authz")


async def _run_clients(url: str, ctx: ssl.SSLContext, clients: int, total: int, keepalive: bool) -> tuple[float, list[float], int]:
    import aiohttp

    latencies: list[float] = []
    errors = 0
    per_client = [total // clients + (1 if i < total % clients else 0) for i in range(clients)]
    connector = aiohttp.TCPConnector(ssl=ctx, limit=0, force_close=not keepalive)
    async with aiohttp.ClientSession(connector=connector, timeout=aiohttp.ClientTimeout(total=60)) as session:
        async def client(n: int) -> None:
            nonlocal errors
            for _ in range(n):
                t0 = time.perf_counter()
                try:
                    async with session.post(url, data={"grant_type": "client_credentials"}) as r:
                        await r.read()
                        if r.status != 200:
                            errors += 1
                except (aiohttp.ClientError, asyncio.TimeoutError):
                    errors += 1
                latencies.append(time.perf_counter() - t0)

        # warm-up: one request per client opens its connection (and fills caches)
        await asyncio.gather(*(client(1) for _ in range(clients)))
        latencies.clear()
        started = time.perf_counter()
        await asyncio.gather(*(client(n) for n in per_client))
        elapsed = time.perf_counter() - started
    return elapsed, latencies, errors


def _pct(values: list[float], p: float) -> float:
    if not values:
        return float("nan")
    values = sorted(values)
    return values[min(len(values) - 1, int(round(p / 100 * (len(values) - 1))))]


def _time_us(fn, n: int) -> float:
    fn()
    best = []
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        best.append((time.perf_counter() - t0) / n * 1e6)
    return min(best)


@click.command("authz")
@click.option("--clients", type=click.IntRange(1, 1000), default=32, show_default=True,
              help="Concurrent HTTPS clients.")
@click.option("--requests", "total", type=click.IntRange(1, 1_000_000), default=2000, show_default=True,
              help="Token requests per mode.")
@click.option("--db", "db_url", help="Registry URL (default: SQLite in a temp dir).")
@click.option("--verify-iterations", type=click.IntRange(10, 1_000_000), default=2000, show_default=True)
@click.option("--key-bits", type=click.Choice(["2048", "3072"]), default="2048", show_default=True,
              help="RSA size of the signing key.")
def authz(clients: int, total: int, db_url: str | None, verify_iterations: int, key_bits: str) -> None:
    """Tokens per second over real mutual TLS, and token verification time."""
    from certs.pki import PKI
    from cryptoros.tls import TLSConfig, client_context
    from cryptoros.tokens import KeySet, Revocations, sign_token, verify_access_token

    work = Path(tempfile.mkdtemp(prefix="cryptoros-bench-authz-"))
    proc: subprocess.Popen | None = None
    try:
        pki = PKI.init(work / "pki", unsafe_no_passphrase=True)
        server = pki.issue("authz", kind="server", sans=("IP:127.0.0.1", "DNS:localhost"), unsafe_no_passphrase=True)
        alice = pki.issue("alice", kind="manager", sans=(), unsafe_no_passphrase=True)
        db = db_url or f"sqlite:///{work / 'registry.db'}"
        env = {k: v for k, v in os.environ.items() if not k.startswith("CRYPTOROS_AUTHZ")}
        exe = _authz_exe()

        def admin(*args: str) -> None:
            r = subprocess.run([exe, "--db", db, *args], capture_output=True, text=True, timeout=120, env=env)
            if r.returncode != 0:
                raise click.ClickException(f"cryptoros-authz {args[0]} failed: {r.stderr.strip()}")

        (work / "signing.pass").write_text("bench-signing-passphrase\n")
        admin("add-manager", "alice", "--cert", str(alice.cert_path))
        for i in range(4):  # a realistic grants claim: 8 nodes
            admin("grant", "alice", "publish", f"/talker{i}", f"/robot1/topic{i}", "std_msgs/String")
            admin("grant", "alice", "subscribe", f"/listener{i}", f"/robot1/topic{i}", "std_msgs/String")
        admin("rotate-key", "--signing-key-passphrase-file", str(work / "signing.pass"), "--bits", key_bits)
        port = free_port()
        # the per-certificate limit of token requests (20/s, burst 300) would answer this
        # benchmark's single client with 429: it measures issuing, not the limiter
        (work / "serve.toml").write_text("token_rate = 10000.0\ntoken_burst = 100000\n")
        log = (work / "authz.log").open("w")
        proc = subprocess.Popen(
            [exe, "--db", db, "serve", "--config", str(work / "serve.toml"), "--port", str(port),
             "--ca", str(pki.ca_cert_path),
             "--cert", str(server.cert_path), "--key", str(server.key_path),
             "--signing-key-passphrase-file", str(work / "signing.pass"), "--log-level", "warning"],
            stdout=log, stderr=subprocess.STDOUT, env=env)
        ctx = client_context(TLSConfig(ca_file=pki.ca_cert_path, cert_file=alice.cert_path, key_file=alice.key_path))
        url = f"https://127.0.0.1:{port}"
        deadline = time.monotonic() + 30
        while True:
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=1) as raw, \
                        ctx.wrap_socket(raw, server_hostname="127.0.0.1"):
                    break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise click.ClickException(f"daemon did not start: {(work / 'authz.log').read_text()[-500:]}")
                time.sleep(0.1)

        rows = []
        for label, keepalive in (("kept-alive connections", True), ("new TLS handshake per token", False)):
            elapsed, lat, errors = asyncio.run(_run_clients(f"{url}/token", ctx, clients, total, keepalive))
            rows.append((label, total / elapsed, _pct(lat, 50) * 1e3, _pct(lat, 99) * 1e3, errors))

        # verification, in this process, on a real token from the daemon
        import json
        import urllib.request

        opener = urllib.request.build_opener(urllib.request.HTTPSHandler(context=ctx))
        token = json.loads(opener.open(urllib.request.Request(
            f"{url}/token", data=b"grant_type=client_credentials"), timeout=10).read())["access_token"]
        jwks = json.loads(opener.open(f"{url}/.well-known/jwks.json", timeout=10).read())
        keys = KeySet.from_jwks(jwks)
        der = ssl.PEM_cert_to_DER_cert(alice.cert_path.read_text())
        revs = Revocations(revoked_jtis=frozenset(f"jti{i}" for i in range(10_000)),
                           disabled_subjects=frozenset({"mallory"}))
        kw = dict(keys=keys, issuer="cryptoros-authz", audience="cryptoros", peer_cert_der=der)
        verify_us = _time_us(lambda: verify_access_token(token, **kw), verify_iterations)
        verify_rev_us = _time_us(lambda: verify_access_token(token, revocations=revs, **kw), verify_iterations)
        from cryptography.hazmat.primitives.asymmetric import rsa

        # the interceptor's path: PeerVerifier.verify, once per stream; the same token on
        # many streams is decoded once (its cache), the per-stream checks run every time
        from interceptor.authz_client import AuthzClient
        from interceptor.verifier import PeerVerifier
        from interceptor.config import AuthzSettings

        verifier = PeerVerifier(AuthzClient(AuthzSettings(url=url), ctx), issuer="cryptoros-authz",
                                audience="cryptoros", poll_interval=1.0)
        verifier.keys = keys
        verifier.apply(revs)

        def stream_miss() -> None:
            verifier.token_cache.clear()
            verifier.verify(token, der)

        stream_miss_us = _time_us(stream_miss, verify_iterations)
        stream_hit_us = _time_us(lambda: verifier.verify(token, der), verify_iterations)
        revs_crl = Revocations(revoked_jtis=revs.revoked_jtis, disabled_subjects=revs.disabled_subjects,
                               revoked_serials=frozenset({1, 2, 3}))
        verifier.apply(revs_crl)  # with a CRL in the feed the certificate's serial is read per stream
        stream_hit_crl_us = _time_us(lambda: verifier.verify(token, der), verify_iterations)
        claims = dict(verify_access_token(token, **kw).claims)
        sk = rsa.generate_private_key(public_exponent=65537, key_size=int(key_bits))
        sign_us = _time_us(lambda: sign_token(claims, sk, "bench"), max(10, verify_iterations // 10))
    finally:
        if proc is not None and proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=10)
            if proc.poll() is None:
                proc.kill()
        shutil.rmtree(work, ignore_errors=True)

    backend = (db_url or "sqlite").split(":", 1)[0]
    click.echo(f"cryptoros-authz token issuing: {clients} concurrent clients, {total} tokens per mode, "
               f"RSA-{key_bits}, registry {backend}, {os.cpu_count()} CPUs (daemon and clients share them)")
    click.echo(f"{'mode':30} {'tokens/s':>10} {'p50 ms':>8} {'p99 ms':>8} {'errors':>7}")
    for label, rate, p50, p99, errors in rows:
        click.echo(f"{label:30} {rate:>10.0f} {p50:>8.1f} {p99:>8.1f} {errors:>7}")
    click.echo("")
    click.echo(f"token size: {len(token)} bytes, {len(claims['grants'])} nodes in the grants claim")
    click.echo(f"{'operation (one core, in process)':40} {'us':>8}")
    click.echo(f"{'verify_access_token':40} {verify_us:>8.1f}")
    click.echo(f"{'verify_access_token + 10k revoked jtis':40} {verify_rev_us:>8.1f}")
    click.echo(f"{'sign_token (RS256)':40} {sign_us:>8.1f}")
    click.echo("")
    click.echo("token verification per stream in the interceptor (PeerVerifier.verify, feed of 10k revoked jtis):")
    click.echo(f"{'  without the cache (full verify)':40} {stream_miss_us:>8.1f}")
    click.echo(f"{'  with the cache (same token seen before)':40} {stream_hit_us:>8.1f}")
    click.echo(f"{'  with the cache, CRL serials in the feed':40} {stream_hit_crl_us:>8.1f}")
    click.echo("  checks on every stream, hit or miss: exp/nbf against the clock (5 s leeway), cnf x5t#S256 = the")
    click.echo("  peer's TLS certificate, revoked jti, disabled manager, the certificate's serial in the CA's CRL")
    click.echo("  (read only when the feed lists serials); cached: the RS256 signature, kid, iss, aud, claim shapes")
    click.echo("  and grants, by SHA-256 of the token, emptied when the JWKS, the audiences or the feed change.")
