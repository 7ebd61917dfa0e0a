"""Replicas behind ONE DNS name. Two ``cryptoros-authz serve`` replicas, each
on its own host (a Linux network namespace with its own address on a bridge), over one
registry; an interceptor's client on a third host whose resolver gives the name
``authz.fleet.test`` both addresses (that host's own /etc/hosts: ``ip netns exec``
mounts ``/etc/netns/<ns>/hosts`` over it, as a DNS server with two A records would
answer). Its ``[authz] url`` is that one name. Each replica in turn is SIGKILLed while
the client holds a long-poll of the feed: its tokens keep coming, and a revocation made
after the kill reaches it through the other replica.

Needs root (network namespaces; CI runs as root); without root it skips and says why.
"""

from __future__ import annotations

import contextlib
import json
import queue
import shutil
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from cryptoros.lab.netns import NetnsLab
from tests.authz_support import PASSPHRASE, authz, build_team, ok
from tests.interceptor_harness import separate_hosts
from tests.support import free_port, script, stop, wait_for_port

NAME = "authz.fleet.test"

# The client: the interceptor's own AuthzClient, one url naming the service; commands on
# stdin, one JSON line per answer on stdout.
CLIENT = r"""
import asyncio, json, sys
from pathlib import Path
from cryptoros.errors import TokenError
from cryptoros.tls import TLSConfig, client_context
from interceptor.authz_client import AuthzClient
from interceptor.config import AuthzSettings

url, ca, cert, key = sys.argv[1:5]

def say(**kw):
    print(json.dumps(kw), flush=True)

def peers(client):
    # the replica addresses this client has connections to, in use or kept (aiohttp's
    # private fields, read for the test only)
    conn = client._session.connector if client._session else None
    protos = list(getattr(conn, "_acquired", ())) + [p for kept in getattr(conn, "_conns", {}).values()
                                                     for p, _t in kept]
    return sorted({p.transport.get_extra_info("peername")[0] for p in protos if p.transport})

async def main():
    ctx = client_context(TLSConfig(ca_file=Path(ca), cert_file=Path(cert), key_file=Path(key)), check_hostname=True)
    client = AuthzClient(AuthzSettings(url=url, request_timeout=5.0), ctx)
    loop = asyncio.get_running_loop()
    held = []

    async def hold():
        try:
            feed = await client.fetch_revocations(wait=30)
            say(kind="hold", ok=True, revoked=sorted(feed.revoked_jtis) if feed else None)
        except TokenError as exc:
            say(kind="hold", ok=False, error=exc.detail)

    while (line := (await loop.run_in_executor(None, sys.stdin.readline)).strip()):
        try:
            if line == "token":
                token = await client.fetch_token()
                say(kind="token", ok=True, token=token.token, peers=peers(client))
            elif line == "feed":
                feed = await client.fetch_revocations()
                say(kind="feed", ok=True, revoked=sorted(feed.revoked_jtis) if feed else None)
            elif line == "hold":
                held.append(asyncio.ensure_future(hold()))
                deadline = loop.time() + 10
                while not peers(client) and loop.time() < deadline:  # its connection is acquired
                    await asyncio.sleep(0.01)
                say(kind="holding", peers=peers(client))
        except TokenError as exc:
            say(kind=line, ok=False, error=exc.detail)
    await client.close()

asyncio.run(main())
"""


def _jti(token: str) -> str:
    import base64

    payload = token.split(".")[1]
    return json.loads(base64.urlsafe_b64decode(payload + "=" * (-len(payload) % 4)))["jti"]


class _Client:
    def __init__(self, argv: list[str]) -> None:
        self.proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, bufsize=1)
        self.lines: queue.Queue = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(json.loads(line))

    def ask(self, command: str, kind: str | None = None, timeout: float = 30.0) -> dict:
        if command:
            self.proc.stdin.write(command + "\n")
            self.proc.stdin.flush()
        return self.next(kind or command, timeout)

    def next(self, kind: str, timeout: float = 30.0) -> dict:
        """The next answer of this kind (a bound for a slow machine, not a timing claim)."""
        while True:
            try:
                answer = self.lines.get(timeout=timeout)
            except queue.Empty:
                raise AssertionError(f"no {kind} answer; client stderr: {self.proc.stderr.read()[-2000:]}") from None
            if answer.get("kind") == kind:
                return answer
            self.lines.put(answer)  # another kind's answer: keep it for its reader


@dataclass
class _OneName:
    """Two replicas on their own hosts behind NAME, and a client on a third."""

    hosts: dict
    replicas: dict[str, subprocess.Popen]
    start: Callable[[str], None]
    client: _Client
    by_address: dict[str, str]
    port: int


@contextlib.contextmanager
def _one_name(tmp_path: Path, team, dbs: dict[str, str]) -> Iterator[_OneName]:
    """Replicas ``authz1`` and ``authz2`` (registries ``dbs``) at one port on their own
    hosts, NAME resolving to both on the client's host; everything stopped and deleted
    in a ``finally`` (the namespaces, and /etc/netns/<ns> this made)."""
    separate_hosts()
    server = team.pki.issue("authz-fleet", kind="server", sans=(f"DNS:{NAME}",))
    pass_file = tmp_path / "signing.pass"
    pass_file.write_text(PASSPHRASE + "\n")
    for db in set(dbs.values()):  # one key per registry, before any replica
        ok(authz("rotate-key", "--signing-key-passphrase-file", str(pass_file), db=db))
    port = free_port()
    replicas: dict[str, subprocess.Popen] = {}
    client: _Client | None = None
    netns_etc: Path | None = None
    with NetnsLab() as lab:
        try:
            hosts = {name: lab.add_host(name) for name in ("authz1", "authz2", "robot")}
            netns_etc = Path("/etc/netns") / hosts["robot"].ns
            netns_etc.mkdir(parents=True)
            (netns_etc / "hosts").write_text(f"127.0.0.1 localhost\n{hosts['authz1'].address} {NAME}\n"
                                             f"{hosts['authz2'].address} {NAME}\n")

            def start(name: str) -> None:
                host = hosts[name]
                log = (tmp_path / f"{name}.log").open("a")
                replicas[name] = subprocess.Popen(host.argv([
                    script("cryptoros-authz"), "--db", dbs[name], "serve", "--host", host.address, "--port", str(port),
                    "--ca", str(team.pki.ca_cert), "--cert", str(server.cert_path), "--key", str(server.key_path),
                    "--crl", str(team.pki.crl), "--signing-key-passphrase-file", str(pass_file)]),
                    stdout=log, stderr=subprocess.STDOUT)
                wait_for_port(host.address, port, timeout=30, proc=replicas[name])  # through the bridge

            for name in ("authz1", "authz2"):
                start(name)
            cert, key = team.pki.pki.cert_path_for("alice"), team.pki.pki.key_path_for("alice")
            client = _Client(hosts["robot"].argv([sys.executable, "-c", CLIENT, f"https://{NAME}:{port}",
                                                  str(team.pki.ca_cert), str(cert), str(key)]))
            yield _OneName(hosts, replicas, start, client, {hosts[n].address: n for n in ("authz1", "authz2")}, port)
        finally:
            if client is not None:
                client.proc.stdin.close()
                stop(client.proc, timeout=10)
            for proc in replicas.values():
                stop(proc, timeout=10)
            if netns_etc is not None and netns_etc.exists():
                shutil.rmtree(netns_etc)
                with contextlib.suppress(OSError):  # another run's namespace may have one there now
                    netns_etc.parent.rmdir()


def test_replicas_behind_one_name_keep_tokens_and_the_feed_coming_when_one_is_killed(tmp_path):
    team = build_team(tmp_path)  # one registry (SQLite: every host sees the same file)
    with _one_name(tmp_path, team, {"authz1": team.db, "authz2": team.db}) as fleet:
        client, by_address = fleet.client, fleet.by_address
        first = client.ask("token")
        assert first["ok"], first
        assert client.ask("feed")["ok"]
        killed = []
        for _round in range(2):
            holding = client.ask("hold", "holding")  # a long-poll, held by the replica the client uses
            assert len(holding["peers"]) == 1, holding
            victim = by_address[holding["peers"][0]]
            killed.append(victim)
            fleet.replicas[victim].send_signal(signal.SIGKILL)
            fleet.replicas[victim].wait(timeout=10)
            tokens = [client.ask("token") for _ in range(3)]
            assert all(t["ok"] for t in tokens), tokens  # no request failed: the other address answered
            assert all(victim not in (by_address[a] for a in t["peers"]) for t in tokens), tokens
            revoked = _jti(tokens[0]["token"])
            ok(authz("revoke-token", revoked, db=team.db))
            held = client.next("hold")
            assert held["ok"] and revoked in held["revoked"], held  # the feed, through the survivor
            fleet.start(victim)  # back, before the other one goes
        assert sorted(killed) == ["authz1", "authz2"], killed  # each held it once


def _break_registry(path: Path) -> None:
    """Every read of this registry fails from now on (503): each table is renamed in one
    committed transaction. (Zeroing the file's first page did not do it reliably: in WAL
    mode a replica's pooled connection reads pages it holds in its cache until the
    wal-index says the database changed, and overwriting the file says nothing to it.)"""
    with contextlib.closing(sqlite3.connect(path, timeout=30)) as db:
        tables = [row[0] for row in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")]
        assert "registry_state" in tables, tables
        with db:
            for table in tables:
                db.execute(f'ALTER TABLE "{table}" RENAME TO "{table}_gone"')


def test_a_replica_behind_one_name_that_answers_503_is_left_for_the_next_address(tmp_path):
    """A replica that is up but cannot read its registry answers 503 on its kept
    connection; with one url there is no next url, so the client opens new connections
    starting with the name's next address."""
    team = build_team(tmp_path)
    dbs = {"authz1": f"sqlite:///{tmp_path / 'registry1.db'}", "authz2": f"sqlite:///{tmp_path / 'registry2.db'}"}
    for db in dbs.values():  # two registries with one policy: only the one that breaks differs
        ok(authz("import", str(tmp_path / "policy.yaml"), db=db))
    with _one_name(tmp_path, team, dbs) as fleet:
        first = fleet.client.ask("token")
        assert first["ok"] and len(first["peers"]) == 1, first
        victim = fleet.by_address[first["peers"][0]]
        _break_registry(Path(dbs[victim].removeprefix("sqlite:///")))
        # the replica notices on its next read of the feed (every 0.25 s); until then it
        # may still answer a token from the grants it holds: wait until it knows
        log = tmp_path / f"{victim}.log"
        deadline = time.monotonic() + 20
        while "cannot read the revocation feed from the registry" not in log.read_text():
            assert time.monotonic() < deadline, log.read_text()[-2000:]
            time.sleep(0.05)
        after = fleet.client.ask("token")
        assert after["ok"], after
        assert [fleet.by_address[a] for a in after["peers"]] != [victim], after
        assert fleet.replicas[victim].poll() is None  # it was up all along


def test_a_token_request_in_flight_when_its_replica_dies_is_asked_again_at_the_names_next_address(tmp_path):
    """One url, one name: the replica in use hangs (SIGSTOP) with the client's POST /token
    already in its socket, then is SIGKILLed. The reset reaches the client under the
    request, which it asks once more on a new connection: the name's next address, the
    other replica. aiohttp retries only idempotent methods by itself; a POST is asked
    again by the client (a token request is safe to repeat: the first was never
    answered)."""
    team = build_team(tmp_path)
    with _one_name(tmp_path, team, {"authz1": team.db, "authz2": team.db}) as fleet:
        first = fleet.client.ask("token")
        assert first["ok"] and len(first["peers"]) == 1, first
        victim = fleet.by_address[first["peers"][0]]
        proc = fleet.replicas[victim]
        proc.send_signal(signal.SIGSTOP)
        try:
            fleet.client.proc.stdin.write("token\n")
            fleet.client.proc.stdin.flush()
            deadline = time.monotonic() + 15
            while True:  # until the request sits unread in the stopped replica's socket
                out = subprocess.run(fleet.hosts[victim].argv(["ss", "-tnH", "state", "established",
                                                               f"( sport = :{fleet.port} )"]),
                                     capture_output=True, text=True, timeout=10, check=True).stdout
                if sum(int(line.split()[0]) for line in out.splitlines() if line.strip()):
                    break
                assert time.monotonic() < deadline, out
                time.sleep(0.05)
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=10)
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGCONT)
        after = fleet.client.next("token")
        assert after["ok"], after  # no failure reached the caller
        assert [fleet.by_address[a] for a in after["peers"]] != [victim], after
