"""What every row of ``cryptoros bench interceptor`` stands on: the worker processes
(rospy and our node client, one protocol of stdin/stdout lines), the stunnel4 chain the
interceptors are compared with, and the interceptors' own counters of which checks ran
(TLS handshakes, certificate and token checks, spare connections)."""

from __future__ import annotations

import contextlib
import queue
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from cryptoros.lab.network import HOSTS, Network, NetworkError, free_port, stop, wait_port

SYS_PY = "/usr/bin/python3"
NODES = Path(__file__).parent / "ros1_nodes"
TRANSPORTS = ("plain", "interceptor", "stunnel")


# ============================================================ processes


class Proc:
    """A subprocess whose stdout lines arrive through a thread (bounded waits)."""

    def __init__(self, name: str, args: list[str], env: dict[str, str], log: Path) -> None:
        self.name = name
        self.log = log
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.seen: list[str] = []
        self.proc = subprocess.Popen(args, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=log.open("w"), text=True, bufsize=1)
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))
        self.lines.put(None)

    def send(self, line: str) -> None:
        assert self.proc.stdin is not None
        with contextlib.suppress(BrokenPipeError, OSError):
            self.proc.stdin.write(line + "\n")
            self.proc.stdin.flush()

    def expect(self, prefix: str, timeout: float) -> str:
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            try:
                line = self.lines.get(timeout=max(0.0, remaining))
            except queue.Empty:
                break
            if line is None:
                break
            self.seen.append(line)
            if line.startswith(prefix):
                return line
        tail = self.log.read_text()[-1500:] if self.log.exists() else ""
        raise NetworkError(f"{self.name}: no {prefix!r} within {timeout:.0f} s; output {self.seen[-5:]}; log:\n{tail}")

    def close(self, timeout: float = 5.0) -> None:
        """``quit`` (a clean unregistration), then SIGTERM/SIGKILL: bounded."""
        self.send("quit")
        with contextlib.suppress(OSError):
            self.proc.stdin.close()  # type: ignore[union-attr]
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            stop(self.proc)


def worker_cmd(impl: str, role: str) -> list[str]:
    if impl == "rospy":
        return [SYS_PY, str(NODES / "rospy_worker.py"), role]
    return [sys.executable, "-c", "from cryptoros.bench.interceptor import _our_worker; _our_worker()", role]


# ============================================================ stunnel


@contextlib.contextmanager
def stunnel_chain(net: Network, target_port: int, workdir: Path, tag: str,
                  pids: list[int] | None = None) -> Iterator[tuple[int, int]]:
    """stunnel4 server on 127.0.0.2 (-> 127.0.0.1:target_port) and client on 127.0.0.1
    (-> the server), mutual certificates from the network's CA. Yields (client accept
    port, server accept port); ``pids`` gets the two processes' ids."""
    binary = shutil.which("stunnel4") or shutil.which("stunnel")
    if binary is None:
        raise NetworkError("stunnel4 is not installed (scripts/install-system-parts)")
    server_port, client_port = free_port(HOSTS["robot_a"]), free_port()
    common = [
        "foreground = yes", "pid =", "debug = 3", "syslog = no",
        "socket = l:TCP_NODELAY=1", "socket = r:TCP_NODELAY=1",
    ]
    sides = {
        "server": (net.cert("stunnel_a"), [
            f"accept = {HOSTS['robot_a']}:{server_port}", f"connect = 127.0.0.1:{target_port}",
        ]),
        "client": (net.cert("stunnel_b"), [
            "client = yes", f"accept = 127.0.0.1:{client_port}", f"connect = {HOSTS['robot_a']}:{server_port}",
            f"checkIP = {HOSTS['robot_a']}",
        ]),
    }
    procs = []
    try:
        for side, ((cert, key), lines) in sides.items():
            conf = workdir / f"stunnel-{tag}-{side}.conf"
            conf.write_text("\n".join([
                *common, f"output = {workdir / f'stunnel-{tag}-{side}.log'}",
                f"[{tag}-{side}]", *lines,
                f"cert = {cert}", f"key = {key}", f"CAfile = {net.ca}", f"CRLfile = {net.pki.crl_path}",
                "verifyChain = yes", "requireCert = yes", "sslVersionMin = TLSv1.2",
                "ciphers = ECDHE+AESGCM:ECDHE+CHACHA20:!aNULL",
            ]) + "\n")
            procs.append(subprocess.Popen([binary, str(conf)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            if pids is not None:
                pids.append(procs[-1].pid)
        wait_port(HOSTS["robot_a"], server_port, 10, procs[0], "stunnel server")
        wait_port("127.0.0.1", client_port, 10, procs[1], "stunnel client")
        yield client_port, server_port
    finally:
        for proc in procs:
            stop(proc)


# ============================================================ which checks ran


def interceptor_checks(net: Network, hosts: tuple[str, ...] = ("robot_a", "robot_b")) -> dict[str, float]:
    """The interceptors' counters of TLS handshakes (full, resumed) and per-stream checks
    (certificate: validity and CRL; token: signature or cache, time, binding, feed),
    summed over ``hosts`` and both directions, read from their /metrics."""
    import urllib.request

    totals: dict[str, float] = {}
    for name in hosts:
        port = net.hosts[name].metrics_port
        if port is None:
            continue
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as reply:
            text = reply.read().decode()
        for line in text.splitlines():
            for family, label in (("cryptoros_interceptor_tls_handshakes_total{", "kind"),
                                  ("cryptoros_interceptor_stream_checks_total{", "check"),
                                  ("cryptoros_interceptor_spare_connections_total{", "outcome")):
                if line.startswith(family):
                    labels, value = line[len(family):].split("} ")
                    fields = dict(part.split("=", 1) for part in labels.split(","))
                    key = fields[label].strip('"')
                    if family.startswith("cryptoros_interceptor_tls"):
                        key = f"{fields['direction'].strip(chr(34))}_{key}"
                    elif family.startswith("cryptoros_interceptor_spare"):
                        key = f"spare_{key}"
                    totals[key] = totals.get(key, 0.0) + float(value)
    return totals


def settled_checks(net: Network, timeout: float = 5.0) -> dict[str, float]:
    """:func:`interceptor_checks` once they held still for 0.4 s (three reads 0.2 s apart;
    bounded by ``timeout``): the spare that replaces a used one is counted by the accepting
    interceptor when its handshake ends and by the connecting one a moment later; read
    between the two, one spare looks like a stream that skipped its token check."""
    import time

    deadline = time.monotonic() + timeout
    last, still = interceptor_checks(net), 0
    while still < 2 and time.monotonic() < deadline:
        time.sleep(0.2)
        now = interceptor_checks(net)
        still = still + 1 if now == last else 0
        last = now
    return last


def checks_delta(before: dict[str, float], after: dict[str, float]) -> dict[str, int]:
    return {k: int(after.get(k, 0) - before.get(k, 0)) for k in sorted(set(before) | set(after))
            if after.get(k, 0) - before.get(k, 0)}


def describe_checks(delta: dict[str, int]) -> str:
    """One line: handshakes accepted (full, resumed) and the checks every stream got
    (a spare connection still waiting when the counters were read is accepted, its
    certificate checked by the peer, but no stream yet: see :func:`spares_waiting`)."""
    full, resumed = delta.get("in_full", 0), delta.get("in_resumed", 0)
    waiting = spares_waiting(delta)
    return (f"{full + resumed} streams accepted between interceptors: {full} full handshakes, {resumed} resumed"
            f"{f' ({waiting} of them spare connections not used yet)' if waiting else ''}; "
            f"peer certificate (validity + CRL) checked {delta.get('certificate', 0)} times, "
            f"token (signature or cache, time, cnf binding, feed incl. revoked serials) {delta.get('token', 0)} times "
            f"(both ends of each stream); spare connections made {delta.get('spare_made', 0)}, used "
            f"{delta.get('spare_used', 0)}, expired into a token exchange {delta.get('spare_expired', 0)}")


def spares_waiting(delta: dict[str, int]) -> int:
    """Spare connections made but neither used nor expired yet when the counters were read."""
    return max(0, delta.get("spare_made", 0) - delta.get("spare_used", 0) - delta.get("spare_expired", 0))



__all__ = ["NODES", "Proc", "SYS_PY", "TRANSPORTS", "checks_delta", "describe_checks", "interceptor_checks",
           "settled_checks", "spares_waiting", "stunnel_chain", "worker_cmd"]
