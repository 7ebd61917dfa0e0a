"""``cryptoros bench insider``: what an insider's exhaustion attacks cost the interceptors.

Builds the test bed of the interceptor tests (real rosmaster, a master's interceptor
and two robots' interceptors, each with its own certificate and manager) and lets
robot B, an insider with a valid certificate and a wildcard subscribe grant, try two
exhaustion attacks by hand over mutual TLS:

- relay exhaustion: ``--names`` fresh node names registered with fresh endpoint
  names, and as many ``unregisterSubscriber`` calls naming endpoints never seen, in
  multicalls of 256;
- preamble slowloris: ``--dribblers`` TLS connections that send one byte of their
  preamble and then nothing.

It prints, per interceptor, open fds and RSS before and after, what was refused, and
whether robot A can still register afterwards. Nothing is asserted.
"""

from __future__ import annotations

import os
import shutil
import socket
import ssl
import tempfile
import time
import xmlrpc.client
from pathlib import Path

import click

from cryptoros.lab.network import NetworkError, open_stream
from cryptoros.lab.policy import policy_yaml

POLICY = policy_yaml({
    "master": {},
    "robot_a": {"publish": [("/talker_a", "/chatter", "std_msgs/String")]},
    "robot_b": {"subscribe": [("*", "/chatter", "std_msgs/String")]},
})
HOSTS = {"master": "127.0.0.4", "robot_a": "127.0.0.2", "robot_b": "127.0.0.3"}


def _usage(pid: int) -> tuple[int, int]:
    """(open fds, RSS in KiB) of a process."""
    rss = 0
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            rss = int(line.split()[1])
    return len(os.listdir(f"/proc/{pid}/fd")), rss


class _Insider:
    """Robot B speaking to an interceptor's public port by hand."""

    def __init__(self, net, name: str) -> None:
        self.ctx, self.token = net.client_of(name)

    def connect(self, host: str, port: int) -> ssl.SSLSocket:
        raw = socket.create_connection((host, port), timeout=10)
        return self.ctx.wrap_socket(raw, server_hostname=host)

    def master_stream(self, host: str, port: int):
        try:
            return open_stream(self.ctx, self.token, host, port, "master")
        except NetworkError as exc:
            raise click.ClickException(f"the master's interceptor: {exc}") from None

    @staticmethod
    def call(sock, request):
        from cryptoros.ros1.xmlrpc import NEED_DATA, Role, XmlRpcConnection

        conn = XmlRpcConnection(Role.CLIENT)
        sock.sendall(conn.send(request))
        while (event := conn.next_event()) is NEED_DATA:
            conn.receive_data(sock.recv(65536))
        return event


@click.command("insider")
@click.option("--names", type=click.IntRange(1, 100_000), default=20_000, show_default=True,
              help="Fresh node names (and never-seen unregister endpoints) the insider sends.")
@click.option("--dribblers", type=click.IntRange(0, 1000), default=60, show_default=True,
              help="TLS connections that dribble their preamble.")
def insider(names: int, dribblers: int) -> None:
    """Interceptor fds and RSS under an insider's relay-exhaustion and slowloris attacks."""
    from cryptoros.lab.network import lab_network
    from cryptoros.ros1.xmlrpc import Request, make_multicall

    if shutil.which("rosmaster") is None:
        raise click.ClickException("rosmaster is not installed (scripts/install-system-parts installs it as root)")
    work = Path(tempfile.mkdtemp(prefix="cryptoros-bench-insider-"))
    try:
        with lab_network(work, POLICY, hosts=HOSTS, master="rosmaster", progress=lambda m: click.echo(f"... {m}")) as net:
            procs = {name: h.proc for name, h in net.hosts.items()}
            before = {name: _usage(p.pid) for name, p in procs.items()}
            me = _Insider(net, "robot_b")
            master = net.hosts["master"]
            b = net.hosts["robot_b"]
            click.echo(f"... relay exhaustion: {names} fresh names and {names} unknown unregisters")
            refused = accepted = 0
            t0 = time.perf_counter()
            with me.master_stream(master.address, master.public_port) as s:
                for start in range(0, names, 256):
                    count = min(256, names - start)
                    for method in ("registerSubscriber", "unregisterSubscriber"):
                        calls = []
                        for i in range(start, start + count):
                            uri = f"cryptoros://{b.address}:{b.public_port}/x/{10_000_000 + i}"
                            params = (f"/fresh_{i}", "/chatter", "std_msgs/String", uri) if method.startswith("reg") \
                                else (f"/fresh_{i}", "/nothing", uri)
                            calls.append(Request(method=method, params=params))
                        reply = me.call(s, make_multicall(calls))
                        for item in reply.value:
                            ok = isinstance(item, list) and item[0][0] == 1
                            accepted += ok
                            refused += not ok
            elapsed = time.perf_counter() - t0
            click.echo(f"... slowloris: {dribblers} dribbling TLS connections")
            a = net.hosts["robot_a"]
            held = []
            for _ in range(dribblers):
                try:
                    sock = me.connect(a.address, a.public_port)
                    sock.sendall(b"C")
                    held.append(sock)
                except OSError:
                    pass
            deadline = time.monotonic() + 30
            open_after = len(held)
            for sock in held:
                sock.settimeout(max(0.1, deadline - time.monotonic()))
                try:
                    while sock.recv(100):
                        pass
                    open_after -= 1
                except OSError:
                    open_after -= 1
                sock.close()
            slowloris_s = 30 - max(0.0, deadline - time.monotonic())
            after = {name: _usage(p.pid) for name, p in procs.items()}
            local = xmlrpc.client.ServerProxy(a.master_uri)
            code, _msg, _ = local.registerPublisher("/talker_a", "/chatter", "std_msgs/String", "http://127.0.0.1:9/")
            local.unregisterPublisher("/talker_a", "/chatter", "http://127.0.0.1:9/")
    finally:
        shutil.rmtree(work, ignore_errors=True)

    click.echo("")
    click.echo(f"relay exhaustion: {2 * names} calls in {elapsed:.1f} s: {accepted} accepted, {refused} refused")
    click.echo(f"slowloris: {dribblers} dribblers, {open_after} still open after {slowloris_s:.1f} s")
    click.echo(f"robot A registers a publisher afterwards: {'yes' if code == 1 else 'NO'}")
    click.echo("")
    click.echo(f"{'interceptor':12} {'fds before':>10} {'fds after':>10} {'RSS before MiB':>15} {'RSS after MiB':>14}")
    for name in procs:
        (f0, r0), (f1, r1) = before[name], after[name]
        click.echo(f"{name:12} {f0:>10} {f1:>10} {r0 / 1024:>15.1f} {r1 / 1024:>14.1f}")
