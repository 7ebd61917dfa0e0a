"""``cryptoros bench fleet``: many interceptors against replicas of the authz server.

Builds a throwaway fleet on loopback: a PostgreSQL cluster (:mod:`cryptoros.lab.postgres`;
SQLite only where PostgreSQL's binaries are missing, said loudly), a CA issuing one EC
certificate per simulated interceptor, a registry holding each as a manager with two
grants (``cryptoros-authz import``), and ``--replicas`` real ``cryptoros-authz serve``
processes over that one database. The clients run in this process: each is the
interceptor's own :class:`interceptor.authz_client.AuthzClient` with its own mutual-TLS
context and the list of every replica (its own preferred one first, as DNS round robin
would spread them). Phases, in order:

1. baseline: the replicas' CPU with no client at all (their feed watchers);
2. tokens: every client asks for tokens in a loop (latency p50/p99, aggregate rate,
   tokens issued per replica from its /metrics);
3. propagation: every client holds a long-poll of ``/revocations`` (``If-None-Match``,
   ``?wait=``); a token is revoked with ``cryptoros-authz revoke-token`` and the time
   from its commit until each client holds a feed naming it is taken; repeated;
4. idle: the clients only hold their long-polls; the replicas' CPU from /proc;
5. polling: the same clients poll the feed once a second, no wait; the replicas' CPU;
6. held polls: the same clients long-poll with a 1 s wait, so that the CPU of one held
   long-poll can be told from the replicas' baseline (the idle phase's few requests
   cannot): the idle target is judged per request (:func:`_idle_ratio`);
7. failover: every client asks for a token once a second and holds a long-poll; the
   first replica is killed (SIGKILL); failed requests and each affected client's time
   to its first token from another replica are counted, and a revocation made after
   the kill must reach every client.

Figures are printed next to the issue's targets; nothing is asserted. Progress goes to
stderr; ``--json FILE`` writes every figure.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import logging
import os
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import click

from cryptoros.lab.network import clean_env, cpu_seconds, tool
from cryptoros.lab.policy import policy_yaml
from cryptoros.lab.processes import NetworkError, free_port, log_tail, stop, wait_port
from cryptoros.outputs import write_output

SIGNING_PASSPHRASE = "bench-fleet-signing-passphrase"
#: the issue's targets
TARGET_RATE = 1000.0  # tokens/s across the replicas
TARGET_PROPAGATION = 2.0  # s, p99
TARGET_IDLE_RATIO = 0.01  # idle long-poll cost per interceptor / 1 Hz polling cost


def _progress(message: str) -> None:
    click.echo(f"[bench fleet {time.strftime('%H:%M:%S')}] {message}", err=True)


def _pct(values: list[float], p: float) -> float | None:
    if not values:
        return None
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(round(p / 100 * (len(ordered) - 1))))]


def _ms(value: float | None) -> float | None:
    return None if value is None else round(value * 1e3, 1)


def _jti_of(token: str) -> str:
    """The ``jti`` claim of a token we were just issued (read, not verified: it only
    names the token to revoke)."""
    payload = token.split(".")[1]
    return json.loads(base64.urlsafe_b64decode(payload + "=" * (-len(payload) % 4)))["jti"]


def _tree_cpu(pid: int) -> float:
    """CPU seconds of ``pid``, its reaped children and its live children (PostgreSQL:
    the postmaster and its backends)."""
    tick = os.sysconf("SC_CLK_TCK")

    def stat(p: int | str) -> list[str] | None:
        try:
            return Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            return None

    own = stat(pid)
    if own is None:
        return 0.0
    total = sum(int(own[i]) for i in (11, 12, 13, 14))
    for entry in os.listdir("/proc"):
        if entry.isdigit() and (fields := stat(entry)) is not None and fields[1] == str(pid):
            total += int(fields[11]) + int(fields[12])
    return total / tick


# ---------------------------------------------------------------------------- the fleet
@dataclass
class Fleet:
    workdir: Path
    db: str
    backend: str
    urls: list[str]
    procs: list[subprocess.Popen]
    logs: list[Path]
    certs: list[tuple[str, Path, Path]]  # (manager, cert, key) per client
    ca: Path
    postgres_pid: int | None = None
    setup_seconds: dict = field(default_factory=dict)

    def replica_cpu(self) -> list[float]:
        return [cpu_seconds(p.pid) or 0.0 for p in self.procs]

    def postgres_cpu(self) -> float | None:
        return _tree_cpu(self.postgres_pid) if self.postgres_pid else None

    def admin(self, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
        result = subprocess.run([tool("cryptoros-authz"), "--db", self.db, *args], capture_output=True, text=True,
                                timeout=timeout, env=clean_env())
        if result.returncode != 0:
            raise NetworkError(f"cryptoros-authz {args[0]} failed: {result.stderr.strip() or result.stdout.strip()}")
        return result


def _policy(managers: list[tuple[str, str]]) -> str:
    return policy_yaml({name: {"publish": [(f"/robot{i}/talker", f"/robot{i}/pose", "std_msgs/String")],
                               "subscribe": [(f"/robot{i}/planner", "/fleet/goals", "std_msgs/String")]}
                        for i, (name, _fingerprint) in enumerate(managers)}, fingerprints=dict(managers))


@contextlib.contextmanager
def _fleet(workdir: Path, clients: int, replicas: int, feed_wait: float) -> Iterator[Fleet]:
    """PKI, registry, PostgreSQL (or the SQLite fallback) and the replicas; everything
    is stopped in a ``finally``."""
    from certs.pki import PKI
    from cryptoros.lab.postgres import create_database, postgres_cluster, postgres_unavailable, postmaster_pid

    with contextlib.ExitStack() as stack:
        setup: dict[str, float] = {}
        postgres_pid = None
        if (reason := postgres_unavailable()) is None:
            t0 = time.monotonic()
            _progress("starting a throwaway PostgreSQL cluster")
            server = stack.enter_context(postgres_cluster(max_connections=max(100, 12 * replicas + 20)))
            db, backend = create_database(server, "fleet"), "postgresql"
            postgres_pid = postmaster_pid(server)
            setup["postgresql_s"] = round(time.monotonic() - t0, 2)
        else:
            db, backend = f"sqlite:///{workdir / 'registry.db'}", "sqlite"
            banner = "!" * 78
            for line in (banner, f"NO POSTGRESQL: {reason}",
                         "falling back to SQLite: replicas share one file, figures are NOT those of a fleet deployment",
                         banner):
                click.echo(line, err=True)

        t0 = time.monotonic()
        _progress(f"issuing {clients} client certificates (EC P-256) from a throwaway CA")
        pki = PKI.init(workdir / "pki", unsafe_no_passphrase=True)
        server_cert = pki.issue("authz", kind="server", sans=("IP:127.0.0.1", "DNS:localhost"),
                                unsafe_no_passphrase=True)
        certs, managers = [], []
        for i in range(clients):
            name = f"robot{i:04d}"
            issued = pki.issue(name, kind="interceptor", sans=("IP:127.0.0.1",), unsafe_no_passphrase=True)
            certs.append((name, issued.cert_path, issued.key_path))
            managers.append((name, issued.fingerprint_sha256))
        setup["certificates_s"] = round(time.monotonic() - t0, 2)

        t0 = time.monotonic()
        _progress(f"registering {clients} managers (2 grants each) in the {backend} registry")
        policy = workdir / "policy.yaml"
        policy.write_text(_policy(managers))
        fleet = Fleet(workdir=workdir, db=db, backend=backend, urls=[], procs=[], logs=[], certs=certs,
                      ca=pki.ca_cert_path, postgres_pid=postgres_pid, setup_seconds=setup)
        fleet.admin("import", str(policy))
        pass_file = workdir / "signing.pass"
        pass_file.write_text(SIGNING_PASSPHRASE + "\n")
        fleet.admin("rotate-key", "--signing-key-passphrase-file", str(pass_file))
        setup["registry_s"] = round(time.monotonic() - t0, 2)

        # One configuration file for every replica; only the port differs (a flag).
        config = workdir / "authz.toml"
        config.write_text("\n".join([
            f'db = "{db}"', 'host = "127.0.0.1"', f'ca = "{pki.ca_cert_path}"', f'cert = "{server_cert.cert_path}"',
            f'key = "{server_cert.key_path}"', f'crl = "{pki.crl_path}"', f'signing_key_passphrase_file = "{pass_file}"',
            # the token loop is synthetic (an interceptor asks every few minutes): the
            # per-certificate limit (20/s) is raised so it measures issuing, not 429s
            "token_rate = 1000.0", "token_burst = 10000", f"max_feed_wait = {max(300.0, feed_wait):g}", "",
        ]))
        t0 = time.monotonic()
        _progress(f"starting {replicas} cryptoros-authz serve replicas")
        try:
            taken: set[int] = set()
            for i in range(replicas):
                port = free_port(taken=taken)
                log = workdir / f"authz-{i}.log"
                proc = subprocess.Popen([tool("cryptoros-authz"), "serve", "--config", str(config), "--port", str(port),
                                         "--log-level", "warning"],
                                        stdout=log.open("w"), stderr=subprocess.STDOUT, env=clean_env())
                fleet.procs.append(proc)
                fleet.logs.append(log)
                fleet.urls.append(f"https://127.0.0.1:{port}")
            for proc, log, url in zip(fleet.procs, fleet.logs, fleet.urls):
                wait_port("127.0.0.1", int(url.rsplit(":", 1)[1]), 60, proc, "cryptoros-authz serve", log)
            setup["replicas_s"] = round(time.monotonic() - t0, 2)
            yield fleet
        finally:
            for proc in fleet.procs:
                stop(proc, timeout=10)


# ---------------------------------------------------------------------------- clients
@dataclass(eq=False)
class Client:
    index: int
    name: str
    authz: object  # interceptor.authz_client.AuthzClient
    preferred: int  # the replica listed first
    latencies: list[float] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    tokens: int = 0
    last_token: str | None = None
    seen: dict[str, float] = field(default_factory=dict)  # revoked jti -> first seen (monotonic)
    feed_requests: int = 0
    feed_heartbeats: int = 0
    feed_errors: int = 0
    requests: list[tuple[float, float, bool]] = field(default_factory=list)  # failover: (start, end, ok)


def _clients(fleet: Fleet, timeout: float) -> list[Client]:
    from cryptoros.tls import TLSConfig, client_context
    from interceptor.authz_client import AuthzClient
    from interceptor.config import AuthzSettings

    out = []
    n = len(fleet.urls)
    for i, (name, cert, key) in enumerate(fleet.certs):
        ctx = client_context(TLSConfig(ca_file=fleet.ca, cert_file=cert, key_file=key))
        order = tuple(fleet.urls[(i + k) % n] for k in range(n))
        settings = AuthzSettings(url=order[0], urls=order, request_timeout=timeout)
        out.append(Client(i, name, AuthzClient(settings, ctx), preferred=i % n))
    return out


async def _token_loop(c: Client, until: float, *, interval: float = 0.0, delay: float = 0.0) -> None:
    from cryptoros.errors import TokenError

    await asyncio.sleep(delay)
    while (start := time.monotonic()) < until:
        try:
            token = await c.authz.fetch_token()
        except TokenError as exc:
            end = time.monotonic()
            c.errors.append(exc.detail[:200])
            c.requests.append((start, end, False))
            await asyncio.sleep(0.05)  # a refused request must not spin
        else:
            end = time.monotonic()
            c.latencies.append(end - start)
            c.requests.append((start, end, True))
            c.tokens += 1
            c.last_token = token.token
        if interval:
            await asyncio.sleep(max(0.0, start + interval - time.monotonic()))


async def _follow_feed(c: Client, wait: float, changed: asyncio.Event, heartbeat: float = 0.0) -> None:
    """Hold long-polls of the feed forever (``wait`` 0: poll once a second), with the
    server's heartbeats every ``heartbeat`` seconds (0: none), counted."""
    from cryptoros.errors import TokenError

    def alive() -> None:
        c.feed_heartbeats += 1

    while True:
        started = time.monotonic()
        try:
            c.feed_requests += 1
            feed = await c.authz.fetch_revocations(wait=wait, heartbeat=heartbeat if wait else 0.0, alive=alive)
        except TokenError:
            c.feed_errors += 1
            await asyncio.sleep(0.2)
            continue
        if feed is not None:
            now = time.monotonic()
            for jti in feed.revoked_jtis:
                c.seen.setdefault(jti, now)
            changed.set()
        if not wait:
            await asyncio.sleep(max(0.0, started + 1.0 - time.monotonic()))


@contextlib.asynccontextmanager
async def _following(clients: list[Client], wait: float, changed: asyncio.Event, *, stagger: float = 0.0,
                     heartbeat: float = 0.0):
    async def one(c: Client, delay: float) -> None:
        await asyncio.sleep(delay)
        await _follow_feed(c, wait, changed, heartbeat)

    n = len(clients)
    tasks = [asyncio.ensure_future(one(c, stagger * i / n)) for i, c in enumerate(clients)]
    try:
        yield tasks
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)


async def _revoke_and_time(fleet: Fleet, clients: list[Client], jti: str, changed: asyncio.Event,
                           timeout: float) -> dict:
    """Revoke ``jti`` with the admin CLI; seconds from the commit until each client saw it.

    The commit's time is when the CLI's line ``token ... revoked`` arrives (printed
    unbuffered right after the transaction commits; its exit comes a good 0.1 s
    later, interpreter teardown, and its start 0.5 s earlier, imports)."""
    t_start = time.monotonic()
    proc = await asyncio.create_subprocess_exec(tool("cryptoros-authz"), "--db", fleet.db, "revoke-token", jti,
                                                stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
                                                env=clean_env(PYTHONUNBUFFERED="1"))
    try:
        line = await asyncio.wait_for(proc.stdout.readline(), 120)
        t_done = time.monotonic()
        out, err = await asyncio.wait_for(proc.communicate(), 60)
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    if proc.returncode != 0 or b"revoked" not in line:
        raise NetworkError(f"cryptoros-authz revoke-token failed: {(line + out + err).decode().strip()}")
    t_exit = time.monotonic()
    deadline = t_done + timeout
    while not all(jti in c.seen for c in clients) and time.monotonic() < deadline:
        changed.clear()
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(changed.wait(), 0.1)
    delays = [c.seen[jti] - t_done for c in clients if jti in c.seen]
    return {"jti": jti, "cli_to_commit_s": round(t_done - t_start, 3), "cli_exit_after_commit_s": round(t_exit - t_done, 3),
            "seen_by": len(delays), "clients": len(clients), "min_ms": _ms(min(delays, default=None)),
            "p50_ms": _ms(_pct(delays, 50)), "p99_ms": _ms(_pct(delays, 99)), "max_ms": _ms(max(delays, default=None)),
            "delays": delays}


async def _issued_per_replica(fleet: Fleet, ctx) -> list[float | None]:
    """``cryptoros_authz_tokens_issued_total`` of each replica (None: it does not answer)."""
    import aiohttp

    out: list[float | None] = []
    async with aiohttp.ClientSession(connector=aiohttp.TCPConnector(ssl=ctx),
                                     timeout=aiohttp.ClientTimeout(total=10)) as session:
        for url in fleet.urls:
            try:
                async with session.get(f"{url}/metrics") as resp:
                    text = await resp.text()
            except (aiohttp.ClientError, asyncio.TimeoutError, OSError):
                out.append(None)
                continue
            value = None
            for line in text.splitlines():
                if line.startswith("cryptoros_authz_tokens_issued_total "):
                    value = float(line.split()[1])
            out.append(value)
    return out


async def _cpu_window(fleet: Fleet, seconds: float) -> dict:
    """The replicas', PostgreSQL's and this process's CPU seconds over ``seconds``."""
    r0, p0, b0, t0 = fleet.replica_cpu(), fleet.postgres_cpu(), time.process_time(), time.monotonic()
    await asyncio.sleep(seconds)
    r1, p1, b1, t1 = fleet.replica_cpu(), fleet.postgres_cpu(), time.process_time(), time.monotonic()
    return {"seconds": round(t1 - t0, 2), "replica_cpu_s": [round(b - a, 3) for a, b in zip(r0, r1)],
            "replicas_cpu_s": round(sum(r1) - sum(r0), 3),
            "postgres_cpu_s": None if p0 is None or p1 is None else round(p1 - p0, 3),
            "bench_process_cpu_s": round(b1 - b0, 3)}


# ---------------------------------------------------------------------------- phases
@dataclass(frozen=True)
class Plan:
    clients: int
    replicas: int
    baseline_s: float
    token_s: float
    revocations: int
    feed_wait: float
    idle_s: float
    poll_s: float
    failover_s: float
    dense_s: float = 20.0
    #: the server's heartbeats on held long-polls (the interceptor's feed_heartbeat; 0: none)
    feed_heartbeat: float = 0.0
    failover_interval: float = 1.0
    request_timeout: float = 15.0
    propagation_timeout: float = 30.0


async def _run(fleet: Fleet, plan: Plan) -> dict:
    from cryptoros.errors import TokenError

    from cryptoros.tls import TLSConfig, client_context

    result: dict = {}
    clients = _clients(fleet, plan.request_timeout)
    _name, cert, key = fleet.certs[0]
    probe_ctx = client_context(TLSConfig(ca_file=fleet.ca, cert_file=cert, key_file=key))  # /healthz, /metrics
    try:
        await _wait_healthy(fleet, probe_ctx)

        _progress(f"baseline: the replicas' CPU with no client for {plan.baseline_s:g} s")
        result["baseline"] = await _cpu_window(fleet, plan.baseline_s)

        _progress(f"connecting {len(clients)} clients (one token and the feed each)")
        first_errors: list[str] = []

        async def connect(c: Client) -> None:
            try:
                c.last_token = (await c.authz.fetch_token()).token
                await c.authz.fetch_revocations()
            except TokenError as exc:
                first_errors.append(f"{c.name}: {exc.detail[:200]}")

        t0 = time.monotonic()
        await asyncio.gather(*(connect(c) for c in clients))
        result["connect"] = {"seconds": round(time.monotonic() - t0, 2), "errors": len(first_errors),
                             "first_errors": first_errors[:5]}

        # ---- tokens
        _progress(f"tokens: {len(clients)} clients asking in a loop for {plan.token_s:g} s")
        before = await _issued_per_replica(fleet, probe_ctx)
        cpu_before, pg_before, own_before = fleet.replica_cpu(), fleet.postgres_cpu(), time.process_time()
        start = time.monotonic()
        await asyncio.gather(*(_token_loop(c, start + plan.token_s) for c in clients))
        elapsed = time.monotonic() - start
        cpu_after, pg_after, own_after = fleet.replica_cpu(), fleet.postgres_cpu(), time.process_time()
        after = await _issued_per_replica(fleet, probe_ctx)
        lat = [x for c in clients for x in c.latencies]
        errors = [e for c in clients for e in c.errors]
        result["tokens"] = {
            "seconds": round(elapsed, 2), "ok": len(lat), "errors": len(errors), "first_errors": errors[:5],
            "rate_per_s": round(len(lat) / elapsed, 1), "p50_ms": _ms(_pct(lat, 50)), "p99_ms": _ms(_pct(lat, 99)),
            "max_ms": _ms(max(lat, default=None)),
            "clients_with_tokens": sum(1 for c in clients if c.tokens > 0), "clients": len(clients),
            "issued_per_replica": [None if a is None or b is None else int(b - a) for a, b in zip(before, after)],
            "replica_cpu_s": [round(b - a, 2) for a, b in zip(cpu_before, cpu_after)],
            "postgres_cpu_s": None if pg_before is None or pg_after is None else round(pg_after - pg_before, 2),
            "bench_process_cpu_s": round(own_after - own_before, 2),  # the clients' side (TLS, HTTP, JSON)
        }
        for c in clients:
            c.latencies.clear()
            c.errors.clear()
            c.requests.clear()

        # ---- propagation, then idle, on the same held long-polls
        changed = asyncio.Event()
        jtis = [_jti_of(c.last_token) for c in clients if c.last_token]  # one token of each client, distinct
        if not jtis:
            raise NetworkError(f"no client got a token: {errors[:3]}")
        _progress(f"propagation: {len(clients)} long-polls held (wait={plan.feed_wait:g} s), "
                  f"{plan.revocations} revocations")
        async with _following(clients, plan.feed_wait, changed, heartbeat=plan.feed_heartbeat):
            await asyncio.sleep(1.0)  # every long-poll held
            rounds = []
            for k in range(min(plan.revocations, len(jtis))):
                rounds.append(await _revoke_and_time(fleet, clients, jtis[k], changed, plan.propagation_timeout))
                _progress(f"  revocation {k + 1}: seen by {rounds[-1]['seen_by']}/{len(clients)}, "
                          f"p99 {rounds[-1]['p99_ms']} ms")
                await asyncio.sleep(0.5)
            delays = [d for r in rounds for d in r["delays"]]
            result["propagation"] = {
                "revocations": len(rounds), "samples": len(delays), "p50_ms": _ms(_pct(delays, 50)),
                "p99_ms": _ms(_pct(delays, 99)), "max_ms": _ms(max(delays, default=None)),
                "every_client_saw_every_revocation": all(r["seen_by"] == len(clients) for r in rounds),
                "rounds": [{k: v for k, v in r.items() if k != "delays"} for r in rounds],
            }
            # idle: the long-polls are re-held after the last change; let them settle
            await asyncio.sleep(1.0)
            _progress(f"idle: {len(clients)} clients holding long-polls for {plan.idle_s:g} s")
            n0, h0 = sum(c.feed_requests for c in clients), sum(c.feed_heartbeats for c in clients)
            idle = await _cpu_window(fleet, plan.idle_s)
            idle["feed_requests"] = sum(c.feed_requests for c in clients) - n0
            idle["feed_heartbeats"] = sum(c.feed_heartbeats for c in clients) - h0
            idle["feed_wait_s"] = plan.feed_wait
            idle["feed_heartbeat_s"] = plan.feed_heartbeat
            result["idle"] = idle

        # ---- 1 Hz polling
        _progress(f"polling: the same clients polling the feed once a second for {plan.poll_s:g} s")
        async with _following(clients, 0.0, changed, stagger=1.0):
            await asyncio.sleep(1.5)  # everyone polling
            n0 = sum(c.feed_requests for c in clients)
            poll = await _cpu_window(fleet, plan.poll_s)
            poll["feed_requests"] = sum(c.feed_requests for c in clients) - n0
            result["polling"] = poll

        # ---- the cost of one held long-poll, where it can be measured: many of them
        _progress(f"held polls: the same clients long-polling with wait=1 s for {plan.dense_s:g} s "
                  "(the CPU of one held long-poll)")
        async with _following(clients, 1.0, changed, stagger=1.0):
            await asyncio.sleep(2.5)  # everyone holding
            n0 = sum(c.feed_requests for c in clients)
            dense = await _cpu_window(fleet, plan.dense_s)
            dense["feed_requests"] = sum(c.feed_requests for c in clients) - n0
            dense["feed_wait_s"] = 1.0
            result["held_polls"] = dense
        if plan.feed_heartbeat:
            # ---- the cost of one heartbeat, where it can be measured: many of them
            beat = 1.0  # often enough to be measured, far enough apart not to arrive coalesced
            _progress(f"heartbeats: the same clients holding long-polls with a heartbeat every {beat:g} s for "
                      f"{plan.dense_s:g} s (the CPU of one heartbeat)")
            async with _following(clients, max(plan.feed_wait, 60.0), changed, stagger=1.0, heartbeat=beat):
                await asyncio.sleep(2.5)
                n0, h0 = sum(c.feed_requests for c in clients), sum(c.feed_heartbeats for c in clients)
                beats = await _cpu_window(fleet, plan.dense_s)
                beats["feed_requests"] = sum(c.feed_requests for c in clients) - n0
                beats["feed_heartbeats"] = sum(c.feed_heartbeats for c in clients) - h0
                result["heartbeats"] = beats
        result["idle_vs_polling"] = _idle_ratio(result, len(clients))

        # ---- failover
        result["failover"] = await _failover(fleet, clients, plan, changed, {r["jti"] for r in rounds})
    finally:
        await asyncio.gather(*(c.authz.close() for c in clients), return_exceptions=True)
    return result


def _idle_ratio(result: dict, clients: int) -> dict:
    """CPU seconds per interceptor per minute, idle (long-polls) and polling at 1 Hz,
    gross and net of the baseline (what the replicas spend with no client at all)."""
    base = result["baseline"]["replicas_cpu_s"] / result["baseline"]["seconds"]

    def per_client_minute(phase: dict, net: bool) -> float:
        cpu = phase["replicas_cpu_s"] - (base * phase["seconds"] if net else 0.0)
        return cpu / clients / (phase["seconds"] / 60.0)

    out = {"baseline_replicas_cpu_s_per_min": round(base * 60, 4)}
    for label, net in (("gross", False), ("net", True)):
        idle, poll = per_client_minute(result["idle"], net), per_client_minute(result["polling"], net)
        out[f"idle_per_client_per_min_s_{label}"] = round(idle, 6)
        out[f"polling_per_client_per_min_s_{label}"] = round(poll, 6)
        out[f"ratio_{label}"] = round(idle / poll, 4) if poll > 0 else None

    # Per request: the idle phase's few requests cost less CPU than the baseline's own
    # noise, so its net figure can come out near zero or below. The cost of one held
    # long-poll is measured where there are many (wait=1 s), the cost of one poll in the
    # polling phase; each times the requests per client per minute seen in the idle and
    # polling phases. Holding an open connection costs no CPU (epoll); every request does.
    def per_request(phase: dict) -> float | None:
        n = phase["feed_requests"]
        return (phase["replicas_cpu_s"] - base * phase["seconds"]) / n if n else None

    def per_client_per_min(phase: dict) -> float:
        return phase["feed_requests"] / clients / (phase["seconds"] / 60.0)

    held, polled = per_request(result["held_polls"]), per_request(result["polling"])
    out["cpu_ms_per_held_long_poll"] = None if held is None else round(held * 1e3, 4)
    out["cpu_ms_per_poll"] = None if polled is None else round(polled * 1e3, 4)
    out["idle_requests_per_client_per_min"] = round(per_client_per_min(result["idle"]), 3)
    out["polling_requests_per_client_per_min"] = round(per_client_per_min(result["polling"]), 3)
    # heartbeats: their cost measured where there are many (one a second per client), a held request's
    # share of that phase taken off at the held long-poll's cost
    beat_cost = 0.0
    beats = result.get("heartbeats")
    if beats and beats["feed_heartbeats"] and held is not None:
        per_beat = (beats["replicas_cpu_s"] - base * beats["seconds"] - held * beats["feed_requests"]) \
            / beats["feed_heartbeats"]
        out["cpu_ms_per_heartbeat"] = round(per_beat * 1e3, 5)
        idle_beats = result["idle"].get("feed_heartbeats", 0) / clients / (result["idle"]["seconds"] / 60.0)
        out["idle_heartbeats_per_client_per_min"] = round(idle_beats, 3)
        beat_cost = max(0.0, per_beat) * idle_beats
    # a held long-poll is renewed at least every feed_wait seconds: an idle window shorter
    # than the wait may see none renewed, which would count its requests as free
    wait = result["idle"].get("feed_wait_s") or 0.0
    idle_requests = max(per_client_per_min(result["idle"]), 60.0 / wait if wait else 0.0)
    out["idle_requests_per_client_per_min_steady"] = round(idle_requests, 3)
    if held is not None and polled:
        idle_cost = held * idle_requests + beat_cost
        poll_cost = polled * per_client_per_min(result["polling"])
        out["idle_per_client_per_min_s_per_request"] = round(idle_cost, 7)
        out["polling_per_client_per_min_s_per_request"] = round(poll_cost, 7)
        out["ratio_per_request"] = round(idle_cost / poll_cost, 4) if poll_cost > 0 else None
    else:
        out["ratio_per_request"] = None
    return out


async def _failover(fleet: Fleet, clients: list[Client], plan: Plan, changed: asyncio.Event,
                    revoked: set[str]) -> dict:
    """Tokens every ``failover_interval`` and held long-polls; the first replica is SIGKILLed a third
    of the way in; a token is revoked 2 s after the kill and must reach every client."""
    switches: list[str] = []

    class Count(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if "does not answer; using" in record.getMessage():
                switches.append(record.getMessage())

    handler = Count()
    authz_log = logging.getLogger("cryptoros.interceptor.authz")
    authz_log.addHandler(handler)
    victim = 0
    _progress(f"failover: a token every {plan.failover_interval:g} s per client and held long-polls for "
              f"{plan.failover_s:g} s; "
              f"replica {fleet.urls[victim]} is killed after {plan.failover_s / 3:.1f} s")
    for c in clients:
        c.requests.clear()
        c.errors.clear()
    try:
        async with _following(clients, plan.feed_wait, changed):
            start = time.monotonic()
            until = start + plan.failover_s
            # one every interval each, spread over the interval (not 200 requests at once)
            every = plan.failover_interval
            loops = [asyncio.ensure_future(_token_loop(c, until, interval=every, delay=every * i / len(clients)))
                     for i, c in enumerate(clients)]
            try:
                await asyncio.sleep(plan.failover_s / 3)
                switched_before = len(switches)
                killed_at = time.monotonic()
                fleet.procs[victim].send_signal(signal.SIGKILL)
                await asyncio.to_thread(fleet.procs[victim].wait, 10)
                _progress(f"  replica {victim} killed (SIGKILL) at t={killed_at - start:.1f} s")
                await asyncio.sleep(2.0)
                # a token issued during this phase (none of them was revoked before)
                jti = next(_jti_of(c.last_token) for c in clients if c.last_token and _jti_of(c.last_token) not in
                           revoked)
                after_kill = await _revoke_and_time(fleet, clients, jti, changed, plan.propagation_timeout)
                _progress(f"  revocation after the kill: seen by {after_kill['seen_by']}/{len(clients)}")
                await asyncio.gather(*loops)
            finally:
                for t in loops:
                    t.cancel()
                await asyncio.gather(*loops, return_exceptions=True)
    finally:
        authz_log.removeHandler(handler)

    affected = [c for c in clients if c.preferred == victim]
    recovery, to_first_token = [], []
    for c in affected:
        # its first token after the kill: how long that request took from the kill (or
        # from its start, if it started later: the loop asks once a second), and the
        # time from the kill to it (which includes up to 1 s of that pacing)
        first = min(((s, end) for s, end, ok in c.requests if ok and end > killed_at), key=lambda r: r[1],
                    default=None)
        if first is not None:
            recovery.append(first[1] - max(first[0], killed_at))
            to_first_token.append(first[1] - killed_at)
    requests = [r for c in clients for r in c.requests]
    failed = [r for r in requests if not r[2]]
    spanning = [r for r in requests if r[0] <= killed_at <= r[1]]
    after = [r for r in requests if r[0] > killed_at]
    # token latency with both replicas, and on the survivor alone once settled (the last third)
    both = [e - s for s, e, ok in requests if ok and e < killed_at]
    survivor = [e - s for s, e, ok in requests if ok and s >= start + 2 * plan.failover_s / 3]
    return {
        "killed_replica": fleet.urls[victim], "killed_at_s": round(killed_at - start, 2),
        "seconds": plan.failover_s, "token_interval_s": plan.failover_interval, "token_requests": len(requests), "failed_requests": len(failed),
        "first_errors": [e for c in clients for e in c.errors][:5],
        "in_flight_at_kill": len(spanning), "in_flight_at_kill_ok": sum(1 for r in spanning if r[2]),
        "requests_after_kill": len(after), "requests_after_kill_ok": sum(1 for r in after if r[2]),
        "affected_clients": len(affected), "recovered_clients": len(recovery),
        "recovery_p50_ms": _ms(_pct(recovery, 50)), "recovery_p99_ms": _ms(_pct(recovery, 99)),
        "recovery_max_ms": _ms(max(recovery, default=None)),
        "kill_to_first_token_p50_ms": _ms(_pct(to_first_token, 50)),
        "kill_to_first_token_max_ms": _ms(max(to_first_token, default=None)),
        "latency_before_kill_p50_ms": _ms(_pct(both, 50)), "latency_before_kill_p99_ms": _ms(_pct(both, 99)),
        "latency_survivor_alone_p50_ms": _ms(_pct(survivor, 50)),
        "latency_survivor_alone_p99_ms": _ms(_pct(survivor, 99)),
        "switch_log_lines_before_kill": switched_before, "switch_log_lines": len(switches),
        "feed_errors": sum(c.feed_errors for c in clients),
        "revocation_after_kill": None if after_kill is None else
        {k: v for k, v in after_kill.items() if k != "delays"},
    }


async def _wait_healthy(fleet: Fleet, ctx, timeout: float = 60.0) -> None:
    import aiohttp

    deadline = time.monotonic() + timeout
    async with aiohttp.ClientSession(connector=aiohttp.TCPConnector(ssl=ctx),
                                     timeout=aiohttp.ClientTimeout(total=5)) as session:
        for proc, log, url in zip(fleet.procs, fleet.logs, fleet.urls):
            while True:
                with contextlib.suppress(aiohttp.ClientError, asyncio.TimeoutError, OSError):
                    async with session.get(f"{url}/healthz") as resp:
                        if resp.status == 200:
                            break
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise NetworkError(f"replica {url} is not healthy{log_tail(log)}")
                await asyncio.sleep(0.2)


# ---------------------------------------------------------------------------- report
def _targets(result: dict) -> list[dict]:
    rate = result["tokens"]["rate_per_s"]
    p99 = result["propagation"]["p99_ms"]
    ratio = result["idle_vs_polling"]["ratio_per_request"]
    return [
        {"name": "token rate across the replicas", "target": f">= {TARGET_RATE:,.0f} tokens/s",
         "value": f"{rate:,.0f} tokens/s", "met": rate >= TARGET_RATE},
        {"name": "revocation propagation p99", "target": f"<= {TARGET_PROPAGATION:g} s",
         "value": "none seen" if p99 is None else f"{p99 / 1e3:.2f} s",
         "met": p99 is not None and p99 / 1e3 <= TARGET_PROPAGATION and
         result["propagation"]["every_client_saw_every_revocation"]},
        {"name": "idle cost per interceptor vs 1 Hz polling", "target": f"< {TARGET_IDLE_RATIO:.0%}",
         "measure": "per request: CPU of one held long-poll x idle requests, over CPU of one poll x polls",
         "value": "n/a" if ratio is None else f"{ratio:.2%}", "met": ratio is not None and ratio < TARGET_IDLE_RATIO},
    ]


def _report(result: dict) -> None:
    cfg, tok, prop = result["config"], result["tokens"], result["propagation"]
    iv, fo = result["idle_vs_polling"], result["failover"]
    echo = click.echo
    echo(f"cryptoros bench fleet: {cfg['clients']} interceptors (mutual TLS, EC P-256), {cfg['replicas']} "
         f"cryptoros-authz replicas, registry {cfg['database']}, {cfg['cpus']} CPUs shared by all "
         f"(load average {cfg['loadavg_before'][0]:g} before, {cfg['loadavg_after'][0]:g} after)")
    if cfg["database"] != "postgresql":
        echo("!!! NOT PostgreSQL: the replicas share a SQLite file; not a fleet deployment's figures !!!")
    echo("")
    echo(f"tokens ({tok['seconds']:g} s loop)       rate {tok['rate_per_s']:>8,.0f}/s   p50 {tok['p50_ms']} ms   "
         f"p99 {tok['p99_ms']} ms   errors {tok['errors']}   per replica {tok['issued_per_replica']}")
    echo(f"  CPU s in that loop: replicas {tok['replica_cpu_s']}, PostgreSQL {tok['postgres_cpu_s']}, "
         f"the clients (this process) {tok['bench_process_cpu_s']}, of {cfg['cpus'] * tok['seconds']:.0f} available")
    echo(f"propagation ({prop['revocations']} revocations) p50 {prop['p50_ms']} ms   p99 {prop['p99_ms']} ms   "
         f"max {prop['max_ms']} ms   every client saw every one: {prop['every_client_saw_every_revocation']}")
    echo("  (from the commit of cryptoros-authz revoke-token until each client's long-poll answered with the feed "
         "naming the token)")
    idle, poll = result["idle"], result["polling"]
    echo(f"{'authz CPU, s per interceptor per min':40} {'idle long-poll':>15} {'1 Hz polling':>14} {'ratio':>8}")
    for label in ("gross", "net"):
        ratio = iv[f"ratio_{label}"]
        echo(f"{'  ' + label + (' (minus the no-client baseline)' if label == 'net' else ''):40} "
             f"{iv[f'idle_per_client_per_min_s_{label}']:>15.5f} {iv[f'polling_per_client_per_min_s_{label}']:>14.5f} "
             f"{'n/a' if ratio is None else f'{ratio:.2%}':>8}")
    ratio = iv["ratio_per_request"]
    if ratio is not None:
        echo(f"{'  per request (judged)':40} {iv['idle_per_client_per_min_s_per_request']:>15.5f} "
             f"{iv['polling_per_client_per_min_s_per_request']:>14.5f} {ratio:>8.2%}")
    echo(f"  (idle {idle['seconds']:g} s, {idle['feed_requests']} feed requests, wait={idle['feed_wait_s']:g} s; "
         f"polling {poll['seconds']:g} s, {poll['feed_requests']} requests; baseline "
         f"{iv['baseline_replicas_cpu_s_per_min']:.3f} CPU s/min for the replicas together;")
    echo(f"   one held long-poll {iv['cpu_ms_per_held_long_poll']} ms CPU, one poll {iv['cpu_ms_per_poll']} ms; "
         f"requests per client per minute: idle {iv['idle_requests_per_client_per_min']} (judged at "
         f"{iv['idle_requests_per_client_per_min_steady']}: one per wait at least), "
         f"polling {iv['polling_requests_per_client_per_min']})")
    if "cpu_ms_per_heartbeat" in iv:
        echo(f"   heartbeats every {idle.get('feed_heartbeat_s', 0):g} s: {idle.get('feed_heartbeats', 0)} while idle, "
             f"{iv['idle_heartbeats_per_client_per_min']} per client per minute, one {iv['cpu_ms_per_heartbeat']} ms "
             f"CPU (counted in the judged figure)")
    rev = fo["revocation_after_kill"] or {}
    echo(f"failover: {fo['killed_replica']} SIGKILLed at {fo['killed_at_s']} s; {fo['failed_requests']} of "
         f"{fo['token_requests']} token requests failed; {fo['recovered_clients']}/{fo['affected_clients']} affected "
         f"clients recovered, p50 {fo['recovery_p50_ms']} ms, max {fo['recovery_max_ms']} ms; "
         f"revocation after the kill seen by {rev.get('seen_by')}/{cfg['clients']}")
    echo(f"  (recovery: each affected client's first token after the kill, from the kill or that request's start; "
         f"token latency p50/p99, one token every {fo['token_interval_s']:g} s per client: "
         f"{fo['latency_before_kill_p50_ms']}/"
         f"{fo['latency_before_kill_p99_ms']} ms on both replicas, {fo['latency_survivor_alone_p50_ms']}/"
         f"{fo['latency_survivor_alone_p99_ms']} ms on the survivor alone)")
    echo("")
    echo(f"{'target':45} {'wanted':>16} {'measured':>18}  ")
    for t in result["targets"]:
        echo(f"{t['name']:45} {t['target']:>16} {t['value']:>18}  {'met' if t['met'] else 'NOT MET'}")


# ---------------------------------------------------------------------------- command
@click.command("fleet")
@click.option("--clients", type=click.IntRange(1, 2000), default=200, show_default=True,
              help="Simulated interceptors (each its own certificate and manager).")
@click.option("--replicas", type=click.IntRange(2, 8), default=2, show_default=True,
              help="cryptoros-authz serve processes over the one database.")
@click.option("--baseline-seconds", type=click.FloatRange(1, 600), default=30.0, show_default=True,
              help="The replicas' CPU with no client, subtracted for the net idle/polling figures.")
@click.option("--token-seconds", type=click.FloatRange(1, 600), default=20.0, show_default=True)
@click.option("--revocations", type=click.IntRange(1, 100), default=5, show_default=True)
@click.option("--feed-wait", type=click.FloatRange(1, 600), default=None, show_default="the interceptor's "
              "[authz] feed_wait default", help="Long-poll wait (?wait=) of the clients (the replicas' max_feed_wait "
              "is set to at least this).")
@click.option("--feed-heartbeat", type=click.FloatRange(0, 300), default=None, show_default="the interceptor's "
              "[authz] feed_heartbeat default", help="Seconds between the server's heartbeats on a held long-poll "
              "(0: none).")
@click.option("--idle-seconds", type=click.FloatRange(1, 3600), default=120.0, show_default=True)
@click.option("--poll-seconds", type=click.FloatRange(1, 3600), default=30.0, show_default=True)
@click.option("--failover-seconds", type=click.FloatRange(3, 600), default=15.0, show_default=True)
@click.option("--failover-interval", type=click.FloatRange(0.1, 60), default=1.0, show_default=True,
              help="Seconds between one client's token requests in the failover phase.")
@click.option("--quick", is_flag=True, help="20 clients and short phases (the test's run).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), help="Write every figure to this file.")
@click.option("--keep", is_flag=True, help="Keep the work directory (logs, PKI) and print its path.")
def fleet(clients: int, replicas: int, baseline_seconds: float, token_seconds: float, revocations: int,
          feed_wait: float | None, feed_heartbeat: float | None, idle_seconds: float,
          poll_seconds: float, failover_seconds: float, failover_interval: float, quick: bool, json_path: str | None,
          keep: bool) -> None:
    """A fleet of interceptors against authz replicas: tokens, revocation propagation,
    idle cost of long-polls vs polling, failover."""
    if feed_wait is None:
        import dataclasses

        from interceptor.config import AuthzSettings

        feed_wait = next(f.default for f in dataclasses.fields(AuthzSettings) if f.name == "feed_wait")
    if feed_heartbeat is None:
        import dataclasses

        from interceptor.config import AuthzSettings

        feed_heartbeat = next(f.default for f in dataclasses.fields(AuthzSettings) if f.name == "feed_heartbeat")
    if quick:
        plan = Plan(clients=min(clients, 20), replicas=replicas, baseline_s=1.0, token_s=2.0, revocations=2,
                    feed_wait=3.0, idle_s=4.0, poll_s=3.0, failover_s=5.0, dense_s=3.0,
                    feed_heartbeat=min(feed_heartbeat, 1.0), failover_interval=failover_interval)
    else:
        plan = Plan(clients=clients, replicas=replicas, baseline_s=baseline_seconds, token_s=token_seconds,
                    revocations=revocations, feed_wait=feed_wait, idle_s=idle_seconds, poll_s=poll_seconds,
                    failover_s=failover_seconds, feed_heartbeat=feed_heartbeat, failover_interval=failover_interval)
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = min(hard, max(soft, 8 * plan.clients + 256))
    if want > soft:
        resource.setrlimit(resource.RLIMIT_NOFILE, (want, hard))
    client_log = logging.getLogger("cryptoros.interceptor.authz")
    client_log.setLevel(logging.WARNING)
    client_log.propagate = False  # failovers are counted, not printed once per client
    client_log.addHandler(logging.NullHandler())
    workdir = Path(tempfile.mkdtemp(prefix="cryptoros-bench-fleet-"))
    started = time.monotonic()
    load_before = os.getloadavg()
    try:
        with _fleet(workdir, plan.clients, plan.replicas, plan.feed_wait) as the_fleet:
            try:
                import uvloop  # type: ignore[import-not-found]

                runner = uvloop.run
            except ImportError:  # pragma: no cover
                runner = asyncio.run
            result = runner(_run(the_fleet, plan))
            result["config"] = {"clients": plan.clients, "replicas": plan.replicas, "database": the_fleet.backend,
                                "cpus": os.cpu_count(), "quick": quick, "urls": the_fleet.urls,
                                "phases": {k: v for k, v in plan.__dict__.items() if k not in ("clients", "replicas")},
                                "setup_seconds": the_fleet.setup_seconds,
                                # other work on the machine shares the cores: say how busy it was
                                "loadavg_before": [round(x, 2) for x in load_before],
                                "loadavg_after": [round(x, 2) for x in os.getloadavg()]}
            failed = [log.name for proc, log in zip(the_fleet.procs[1:], the_fleet.logs[1:]) if proc.poll() is not None]
            if failed:
                raise NetworkError(f"a surviving replica exited during the run: {failed}")
    except NetworkError as exc:
        raise click.ClickException(str(exc)) from exc
    finally:
        if keep:
            _progress(f"work directory kept: {workdir}")
        else:
            shutil.rmtree(workdir, ignore_errors=True)
    result["targets"] = _targets(result)
    result["total_seconds"] = round(time.monotonic() - started, 1)
    _report(result)
    if json_path:
        write_output(json_path, json.dumps(result, indent=2, sort_keys=True) + "\n")
        _progress(f"figures written to {json_path}")
    sys.stdout.flush()
