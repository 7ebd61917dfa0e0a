"""Helpers for the cryptoros-authz tests (no tests here).

:class:`AuthzDaemon` runs ``cryptoros-authz serve`` as a real subprocess on a free
loopback port with a throwaway PKI, and talks to it over real HTTPS with client
certificates (``http.client`` + our own TLS client context).
"""

from __future__ import annotations

import base64
import contextlib
import http.client
import json
import os
import ssl
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from cryptoros.lab.policy import policy_yaml
from cryptoros.tls import TLSConfig, client_context
from tests.pki_fixtures import TestPKIFactory
from tests.support import free_port, run, script, stop, until, wait_for_port

PASSPHRASE = "test-signing-passphrase"


def authz(*args: str, db: str, timeout: float = 60, input: str | None = None) -> subprocess.CompletedProcess:
    """Run the admin CLI as a subprocess against ``db``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("CRYPTOROS_AUTHZ")}
    return run([script("cryptoros-authz"), "--db", db, *args], timeout=timeout, env=env, input=input)


#: verbs that :func:`authz_here` runs as a subprocess all the same: the daemon, and the
#: policy verbs that read a live graph over the network (an event loop of their own)
SUBPROCESS_VERBS = frozenset({"serve", "policy"})
_HERE = threading.Lock()


def authz_here(*args: str, db: str, input: str | None = None) -> subprocess.CompletedProcess:
    """The admin CLI's verb run in this process (click's runner), as the operator types it
    (``sys.argv`` as its command line: the registry records it), against the real
    ``db``: for the grants a test makes on a running network. The CLI as a program (its
    exit status, its one-line errors, no traceback) is tested by test_authz_cli.py and its
    neighbours, with :func:`authz`; here a process start (0.6 s of CPU, about 500 calls
    a run) is saved. An exception that escapes the CLI is a returncode of 1 with its
    traceback on stderr, as Python prints it."""
    if not args or args[0] in SUBPROCESS_VERBS:
        return authz(*args, db=db, input=input)
    import traceback

    from click.testing import CliRunner

    from authz_server.cli import main

    argv = ["cryptoros-authz", "--db", db, *args]
    env = {k: None for k in os.environ if k.startswith("CRYPTOROS_AUTHZ")}
    with _HERE:
        saved, sys.argv = sys.argv, argv
        try:
            result = CliRunner().invoke(main, argv[1:], input=input, env=env, prog_name="cryptoros-authz")
        finally:
            sys.argv = saved
    stderr = result.stderr
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        stderr += "".join(traceback.format_exception(result.exception))
    return subprocess.CompletedProcess(argv, result.exit_code, result.stdout, stderr)


def ok(result: subprocess.CompletedProcess) -> str:
    assert result.returncode == 0, f"exit {result.returncode}\nstdout:{result.stdout}\nstderr:{result.stderr}"
    return result.stdout


def read_pem_der(path: Path) -> bytes:
    return ssl.PEM_cert_to_DER_cert(Path(path).read_text())


@dataclass
class AuthzDaemon:
    pki: TestPKIFactory
    db: str
    workdir: Path
    port: int = 0
    host: str = "127.0.0.1"
    extra: Sequence[str] = ()
    crl: bool = True
    #: the mode of the server's TLS key and signing-key passphrase file
    secret_mode: int = 0o600
    proc: subprocess.Popen | None = None
    log_path: Path | None = None
    _ctx: dict = field(default_factory=dict)

    @property
    def base(self) -> str:
        return f"https://{self.host}:{self.port}"

    def start(self, timeout: float = 20.0) -> None:
        self.port = self.port or free_port()
        server = self.pki.issue("authz", kind="server", force=True)
        pass_file = self.workdir / "signing.pass"
        pass_file.unlink(missing_ok=True)
        pass_file.touch(mode=0o600)  # the server warns of a secret others may read
        for secret in (pass_file, server.key_path):
            secret.chmod(self.secret_mode)
        pass_file.write_text(PASSPHRASE + "\n")
        self.log_path = self.workdir / f"authz-{self.port}.log"
        env = {k: v for k, v in os.environ.items() if not k.startswith("CRYPTOROS_AUTHZ")}
        args = [script("cryptoros-authz"), "--db", self.db, "serve", "--port", str(self.port),
                "--ca", str(self.pki.ca_cert), "--cert", str(server.cert_path), "--key", str(server.key_path),
                *(("--crl", str(self.pki.crl)) if self.crl else ()),
                "--signing-key-passphrase-file", str(pass_file), *self.extra]
        self.proc = subprocess.Popen(args, stdout=self.log_path.open("w"), stderr=subprocess.STDOUT, env=env)
        wait_for_port("127.0.0.1", self.port, timeout=timeout, proc=self.proc)
        deadline = time.monotonic() + timeout
        probe = self.pki.issue("probe", force=True)
        while True:
            try:
                status, _ = self.request("GET", "/healthz", cert=probe.cert_path, key=probe.key_path)
                if status == 200:
                    return
            except (OSError, ssl.SSLError):
                pass
            if time.monotonic() > deadline or self.proc.poll() is not None:
                raise AssertionError(f"authz daemon not healthy: {self.log()}")
            time.sleep(0.1)

    def stop(self) -> int | None:
        if self.proc is not None:
            stop(self.proc, timeout=10)
            return self.proc.returncode
        return None

    def log(self) -> str:
        return self.log_path.read_text() if self.log_path and self.log_path.exists() else ""

    def context(self, cert: Path, key: Path, *, ca: Path | None = None, tls12: bool = False) -> ssl.SSLContext:
        k = (str(cert), str(key), str(ca), tls12)
        if k not in self._ctx:
            self._ctx[k] = client_context(TLSConfig(ca_file=Path(ca or self.pki.ca_cert), cert_file=Path(cert),
                                                    key_file=Path(key), pin_tls12=tls12))
        return self._ctx[k]

    def request(self, method: str, path: str, *, cert: Path, key: Path, body: str | None = None,
                headers: dict | None = None, ca: Path | None = None) -> tuple[int, bytes]:
        conn = http.client.HTTPSConnection(self.host, self.port, context=self.context(cert, key, ca=ca),
                                           timeout=10)
        try:
            hdrs = dict(headers or {})
            if body is not None:
                hdrs.setdefault("Content-Type", "application/x-www-form-urlencoded")
            conn.request(method, path, body=body, headers=hdrs)
            resp = conn.getresponse()
            self.last_headers = dict(resp.getheaders())
            return resp.status, resp.read()
        finally:
            conn.close()

    def wait_polls_held(self, count: int, timeout: float = 15.0) -> None:
        """Until at least ``count`` long-polls of the feed are held open (the daemon's
        ``cryptoros_authz_feed_polls_held``): readiness seen, not slept for."""
        cert, key = self.cert_of("probe")
        deadline = time.monotonic() + timeout
        held = 0.0
        while True:
            _status, raw = self.request("GET", "/metrics", cert=cert, key=key)
            held = next((float(line.split()[1]) for line in raw.decode().splitlines()
                         if line.startswith("cryptoros_authz_feed_polls_held ")), 0.0)
            if held >= count:
                return
            assert time.monotonic() < deadline, f"{held:g} long-polls held after {timeout:g} s, {count} expected"
            time.sleep(0.05)

    def token(self, name: str, body: str = "grant_type=client_credentials") -> tuple[int, dict]:
        cert, key = self.cert_of(name)
        status, raw = self.request("POST", "/token", cert=cert, key=key, body=body)
        return status, json.loads(raw)

    def get_json(self, path: str, name: str = "probe") -> dict:
        cert, key = self.cert_of(name)
        status, raw = self.request("GET", path, cert=cert, key=key)
        assert status == 200, (status, raw)
        return json.loads(raw)

    def cert_of(self, name: str) -> tuple[Path, Path]:
        return self.pki.pki.cert_path_for(name), self.pki.pki.key_path_for(name)

    def cli(self, *args: str) -> subprocess.CompletedProcess:
        return authz_here(*args, db=self.db)


@contextlib.contextmanager
def running_daemon(pki: TestPKIFactory, db: str, workdir: Path, extra: Sequence[str] = (),
                   crl: bool = True, secret_mode: int = 0o600) -> Iterator[AuthzDaemon]:
    d = AuthzDaemon(pki=pki, db=db, workdir=workdir, extra=tuple(extra), crl=crl, secret_mode=secret_mode)
    try:
        d.start()
        yield d
    finally:
        d.stop()


TEAM_POLICY = policy_yaml({
    "alice": {"publish": [("/talker", "/chatter", "std_msgs/String")],
              "subscribe": [("/listener", "/chatter", "std_msgs/String")],
              "serve": [("/adder", "/add_two_ints", "rospy_tutorials/AddTwoInts")]},
    "bob": {"call": [("/client", "/add_two_ints", "rospy_tutorials/AddTwoInts")]},
    "carol": {"subscribe": [("*", "/scan", "sensor_msgs/msg/LaserScan")]},
    "mallory": {},
})


@dataclass
class Team:
    pki: TestPKIFactory
    other_pki: TestPKIFactory
    db: str
    workdir: Path


def build_team(workdir: Path, db: str | None = None) -> Team:
    """A CA with managers alice, bob, carol, mallory (registered; mallory's certificate
    is then revoked in the CRL), a valid but unregistered 'stranger', an unrelated CA
    issuing another 'alice', and a registry holding their policy."""
    pki = TestPKIFactory(workdir / "pki")
    other = TestPKIFactory(workdir / "other-pki", trust_domain="other.local")
    fps = {n: pki.issue(n).fingerprint_sha256 for n in ("alice", "bob", "carol", "mallory")}
    pki.issue("stranger")
    other.issue("alice")
    pki.revoke("mallory")
    db = db or f"sqlite:///{workdir / 'registry.db'}"
    policy = workdir / "policy.yaml"
    policy.write_text(TEAM_POLICY.format(**fps))
    ok(authz("import", str(policy), db=db))
    return Team(pki, other, db, workdir)


def stale_tokens_after_revokes(asked: AuthzDaemon, changed: AuthzDaemon, manager: str, rounds: int = 3,
                               topic: str = "/race_check") -> list[str]:
    """The jti of every token of ``manager`` asked for from ``asked`` after a ``revoke`` (run
    with ``changed``'s registry) returned, that still carries the revoked grant: ``rounds``
    times a grant given, tokens asked for back to back until they carry it, the grant
    revoked, ten more tokens asked for."""
    tokens: list[tuple[float, str]] = []  # (when its request started, the token)
    stop = threading.Event()

    def ask() -> None:
        while not stop.is_set():
            started = time.monotonic()
            status, body = asked.token(manager)
            if status == 200:
                tokens.append((started, body["access_token"]))

    def claims(token: str) -> dict:
        payload = token.split(".")[1]
        return json.loads(base64.urlsafe_b64decode(payload + "=" * (-len(payload) % 4)))

    def carries(token: str) -> bool:
        return topic in json.dumps(claims(token)["grants"])

    stale: list[str] = []
    for _round in range(rounds):
        ok(changed.cli("grant", manager, "subscribe", "*", topic, "std_msgs/String"))
        tokens.clear()
        stop.clear()
        asker = threading.Thread(target=ask)
        asker.start()
        try:
            # the grant reached the daemon's memory: tokens are served from it
            until(lambda: sum(map(carries, (t for _, t in tokens))) >= 3, 10, "tokens carrying the new grant",
                  every=0.02)
            ok(changed.cli("revoke", manager, "subscribe", "*", topic))
            revoked_at = time.monotonic()
            until(lambda: sum(1 for started, _ in tokens if started >= revoked_at) >= 10, 20,
                  "ten tokens asked for after the revoke", every=0.02)
        finally:
            stop.set()
            asker.join(timeout=30)
        stale += [claims(t)["jti"] for started, t in tokens if started >= revoked_at and carries(t)]
    return stale
