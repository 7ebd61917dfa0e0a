"""``cryptoros bench scale``: how an interceptor's CPU and memory grow with the streams
and topics it carries, and how the authorization server scales out.

Interceptor curves. One run builds a robot network on loopback
(:mod:`cryptoros.lab.network`: PKI, registry, ``cryptoros-authz`` daemon, Debian's
``rosmaster``, the master's interceptor and robot A's, ROS 1 role, real mutual TLS). For
each point a fresh interceptor A is started with one publisher behind it (our node
client, :mod:`cryptoros.ros1.node`, uvloop) and a light client in this process, holding a
peer manager's certificate and genuine token, opens streams into A as a peer
interceptor would: mutual TLS, the cryptoros preamble (purpose ``topic``), a TCPROS
subscriber header checked by A against both tokens, then A relays the publisher's
messages (std_msgs/String of 64 B) to it. 1,000 rospy subscribers would measure rospy;
this client only counts frames.

``streams``  N streams of one topic (N subscribers of ``/scale/s``) from one peer;
``topics``   N topics (``/scale/tNNNN``) per peer, one stream each, that peer's token
             granting exactly those N topics (its size grows with them);
``token``    N streams of one topic (``/scale/t0000``) from the peer whose token grants
             the most topics (the ``topics`` curve's last point): the streams curve with
             that curve's largest token, which tells the cost of the streams from that of
             the token each stream's preamble carries.

At every point the publisher sends ``--rate`` messages a second in all (a message to N
subscribers counts N times; topics are published round-robin), so every point carries
the same load and only its spread changes. Figures per point, from the interceptor's
own process (``/proc/PID/stat`` utime + stime, ``VmRSS`` of ``/proc/PID/status``):
CPU microseconds per message carried (the load window's CPU over the frames the client
received), the idle CPU with the streams open and nothing sent, RSS before and after the
streams opened, and the time to open them. A least-squares line over the points gives
the cost per stream or topic (slope) and the fixed part (intercept); a curve whose last
step costs more than :data:`SUPERLINEAR` times its first per unit is flagged as growing
faster than linear.

Authorization servers. ``--replicas`` (default 1, 2, 4) ``cryptoros-authz serve``
replicas over one throwaway PostgreSQL cluster (:mod:`cryptoros.lab.postgres`, as in
``cryptoros bench fleet``), ``--authz-clients`` interceptors' own token clients in this
process asking for tokens in a loop, spread over the replicas: tokens/s, p50 and p99
latency, replica and PostgreSQL CPU. Without PostgreSQL this part is skipped and says
why.

Tables go to stdout, progress to stderr; ``--json FILE`` writes every figure,
``--plots DIR`` draws one PNG per curve. Nothing is asserted.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import ssl
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import click

from cryptoros.lab.network import HOSTS, Network, NetworkError, cpu_seconds, lab_network
from cryptoros.outputs import write_output

#: the counts of the interceptor curves (``--quick``: the first two)
COUNTS = (10, 100, 1000)
QUICK_COUNTS = (10, 100)
CURVES = ("streams", "topics", "token")
REPLICAS = (1, 2, 4)
QUICK_REPLICAS = (1, 2)
#: a curve's cost per unit in its last step over that in its first: above this it grows faster than linear
SUPERLINEAR = 1.5
PAYLOAD = 64
STRING_MD5 = "992ce8a1687cec8c8bd883ec73ca41d1"  # std_msgs/String
#: the hosts: the master, robot A (the publisher's interceptor, measured) and the peers
#: whose certificates the light client holds (their interceptors are never started)
PEER_STREAMS = "peer_s"
SCALE_HOSTS = {**{k: v for k, v in HOSTS.items() if k != "robot_b"}, PEER_STREAMS: "127.0.0.7"}


CURVE_TITLES = {"streams": "open streams (one topic, one peer)", "topics": "topics per peer (a stream each)",
                "token": "open streams (one topic), the peer's token of the most topics"}


def _peer_topics(n: int) -> str:
    return f"peer_t{n}"


def _topic(i: int) -> str:
    return f"/scale/t{i:04d}"


def _progress(message: str) -> None:
    click.echo(f"[scale] {message}", err=True)


# ============================================================ the network's policy and limits


def _grant(node: str, topic: str) -> list[str]:
    return [f"    - node: '{node}'", f"      topic: {topic}", "      type: std_msgs/String"]


def policy(counts: tuple[int, ...]) -> str:
    """The registry: robot A publishes /scale/s and every /scale/tNNNN; ``peer_s``
    subscribes /scale/s; each ``peer_tN`` subscribes exactly the first N topics. (Grants
    name topics exactly: a peer of N topics holds a token of N grants.)"""
    most = max(counts)
    lines = ["version: 1", "managers:", "- name: master", "  fingerprint_sha256: {master}",
             "- name: robot_a", "  fingerprint_sha256: {robot_a}", "  grants:", "    publish:",
             *_grant("*", "/scale/s"), "    - node: '*'", "      topic: /rosout", "      type: rosgraph_msgs/Log"]
    for i in range(most):
        lines += _grant("*", _topic(i))
    lines += [f"- name: {PEER_STREAMS}", f"  fingerprint_sha256: {{{PEER_STREAMS}}}", "  grants:", "    subscribe:",
              *_grant("*", "/scale/s")]
    for n in counts:
        name = _peer_topics(n)
        lines += [f"- name: {name}", f"  fingerprint_sha256: {{{name}}}", "  grants:", "    subscribe:"]
        for i in range(n):
            lines += _grant("*", _topic(i))
    return "\n".join(lines) + "\n"


def limits(most: int) -> dict[str, float | bool]:
    """The per-peer limits the bench raises (everything else stays at its default): one
    peer holds up to ``most`` streams at once, opened at up to 200 a second."""
    return {"max_connections_per_peer": most + 64, "max_new_connections_per_second": 200.0}


# ============================================================ the publisher behind robot A


def _publisher() -> None:
    """Entry point of the publisher process (argv: node name, topic count): advertises
    /scale/s and /scale/t0000.. behind robot A's interceptor, prints ``READY``, then on
    stdin: ``LINKS`` (prints ``LINKS n``, its subscriber connections), ``RUN RATE WHICH``
    (publish RATE messages a second in all on /scale/s (``s``) or /scale/t0000 (``o``):
    a message reaches every subscriber, so RATE / subscribers publications a second; or
    round-robin over the topics (``t``)), ``STOP`` (prints ``STOPPED n``, publications
    made), ``quit``."""
    from cryptoros.ros1.node import Node, install_uvloop

    name, count = sys.argv[1], int(sys.argv[2])
    install_uvloop()

    def out(line: str) -> None:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()

    async def main() -> None:
        loop = asyncio.get_running_loop()
        async with Node(name) as node:
            single = await node.advertise("/scale/s", "std_msgs/String")
            topics = [await node.advertise(_topic(i), "std_msgs/String") for i in range(count)]
            msg = node.msg("std_msgs/String", data="x" * PAYLOAD)
            out("READY")
            task: asyncio.Task | None = None
            sent = [0]

            async def run(rate: float, which: str) -> None:
                pubs = [single] if which == "s" else topics[:1] if which == "o" else topics
                links = max(1, sum(p.num_connections for p in pubs))
                per_s = rate / links if which in ("s", "o") else rate
                start, done, k = time.monotonic(), 0, 0
                while True:
                    due = int((time.monotonic() - start) * per_s)
                    for _ in range(due - done):
                        pubs[k].publish(msg)
                        k = (k + 1) % len(pubs)
                    sent[0] += due - done
                    done = due
                    await asyncio.sleep(0.005)

            while True:
                line = await loop.run_in_executor(None, sys.stdin.readline)
                parts = line.split()
                if not parts or parts[0] == "quit":
                    break
                if parts[0] == "LINKS":
                    out(f"LINKS {single.num_connections + sum(p.num_connections for p in topics)}")
                elif parts[0] == "RUN":
                    sent[0] = 0
                    task = asyncio.ensure_future(run(float(parts[1]), parts[2]))
                    out("RUNNING")
                elif parts[0] == "STOP":
                    if task is not None:
                        task.cancel()
                        with contextlib.suppress(asyncio.CancelledError):
                            await task
                    out(f"STOPPED {sent[0]}")

    asyncio.run(main())


# ============================================================ the light client (a peer interceptor by hand)


@dataclass
class Client:
    """Streams into robot A held by one peer: mutual TLS, the preamble, a subscriber's
    TCPROS header, then frames counted."""

    ctx: ssl.SSLContext
    token: str
    host: str
    port: int
    target: str
    frames: int = 0
    failed: list[str] = field(default_factory=list)
    tasks: list[asyncio.Task] = field(default_factory=list)
    writers: list[asyncio.StreamWriter] = field(default_factory=list)

    async def _open(self, topic: str, callerid: str) -> tuple[asyncio.StreamReader, bytes]:
        from cryptoros.ros1.tcpros import ConnectionHeader, TCPROSConnection, encode_header
        from cryptoros.sansio import NEED_DATA
        from cryptoros.tunnel import Preamble, PreambleReader, PreambleReply, encode

        reader, writer = await asyncio.open_connection(self.host, self.port, ssl=self.ctx, server_hostname=self.host)
        self.writers.append(writer)
        writer.write(encode(Preamble(token=self.token, purpose="topic", target=self.target)))
        preamble = PreambleReader(PreambleReply)
        while (event := preamble.next_event()) is NEED_DATA:
            data = await reader.read(65536)
            if not data:
                raise NetworkError("closed before the preamble reply")
            preamble.receive_data(data)
        if not event.ok:
            raise NetworkError("preamble refused")
        rest = preamble.trailing_data.data
        writer.write(encode_header({"callerid": callerid, "topic": topic, "type": "std_msgs/String",
                                    "md5sum": STRING_MD5, "tcp_nodelay": "1"}))
        conn = TCPROSConnection()
        if rest:
            conn.receive_data(rest)
        while not isinstance(event := conn.next_event(), ConnectionHeader):
            data = await reader.read(65536)
            if not data:
                raise NetworkError("closed before the TCPROS header reply")
            conn.receive_data(data)
        if "error" in event.as_dict():
            raise NetworkError(f"refused: {event.as_dict()['error']}")
        return reader, bytes(conn.trailing_data.data)

    async def _count(self, reader: asyncio.StreamReader, buf: bytes) -> None:
        pending = bytearray(buf)
        with contextlib.suppress(ConnectionError, OSError, ssl.SSLError):
            while True:
                pos, size = 0, len(pending)
                while size - pos >= 4:
                    end = pos + 4 + int.from_bytes(pending[pos:pos + 4], "little")
                    if end > size:
                        break
                    pos = end
                    self.frames += 1
                del pending[:pos]
                data = await reader.read(65536)
                if not data:
                    return
                pending += data

    async def open(self, topics: list[str], concurrency: int = 8) -> float:
        """One stream per entry of ``topics`` (at most ``concurrency`` being set up at
        once: the interceptor's default ``max_pending_per_certificate``); seconds taken."""
        gate = asyncio.Semaphore(concurrency)

        async def one(i: int, topic: str) -> None:
            async with gate:
                for attempt in range(3):
                    try:
                        reader, rest = await asyncio.wait_for(self._open(topic, f"/scale_sub_{i}"), 30)
                    except (NetworkError, OSError, ssl.SSLError, asyncio.TimeoutError) as exc:
                        if attempt == 2:
                            self.failed.append(f"{topic}: {exc or type(exc).__name__}")
                            return
                        await asyncio.sleep(0.5)
                    else:
                        self.tasks.append(asyncio.ensure_future(self._count(reader, rest)))
                        return

        t0 = time.monotonic()
        await asyncio.gather(*(one(i, t) for i, t in enumerate(topics)))
        return time.monotonic() - t0

    async def close(self) -> None:
        for w in self.writers:
            w.close()
        for t in self.tasks:
            t.cancel()
        await asyncio.gather(*self.tasks, return_exceptions=True)
        self.tasks.clear()
        self.writers.clear()


# ============================================================ one point of a curve


def rss_kib(pid: int) -> int | None:
    """VmRSS of a process in KiB (None: gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def _xmlrpc(sock, method: str, *params):
    from cryptoros.ros1.xmlrpc import NEED_DATA, Request, Role, XmlRpcConnection

    conn = XmlRpcConnection(Role.CLIENT)
    sock.sendall(conn.send(Request(method=method, params=params)))
    while (event := conn.next_event()) is NEED_DATA:
        conn.receive_data(sock.recv(65536))
    return event.value


def _target_of(net: Network, peer: str, node: str, topic: str) -> tuple[ssl.SSLContext, str, str]:
    """The peer's TLS context and token, and robot A's target id of ``node``'s TCPROS
    server (as a peer learns it: lookupNode at the master, requestTopic at A)."""
    from cryptoros.lab.network import open_stream

    ctx, token = net.client_of(peer)
    master, a = net.hosts["master"], net.hosts["robot_a"]
    deadline = time.monotonic() + 20
    while True:
        with contextlib.closing(open_stream(ctx, token, master.address, master.public_port, "master")) as s:
            code, _, api = _xmlrpc(s, "lookupNode", "/scale_probe", node)
        if code == 1:
            break
        if time.monotonic() > deadline:
            raise NetworkError(f"{node} is not registered at the master: {api!r}")
        time.sleep(0.2)
    with contextlib.closing(open_stream(ctx, token, a.address, a.public_port, "node", api.rsplit("/", 1)[1])) as s:
        code, msg, proto = _xmlrpc(s, "requestTopic", "/scale_probe", topic, [["TCPROS"]])
    if code != 1:
        raise NetworkError(f"requestTopic {topic} at robot A: {msg}")
    return ctx, token, proto[1].rsplit("/", 1)[1]


def _wait_links(pub, want: int, timeout: float) -> int:
    deadline = time.monotonic() + timeout
    while True:
        pub.send("LINKS")
        links = int(pub.expect("LINKS", 10).split()[1])
        if links >= want or time.monotonic() > deadline:
            return links
        time.sleep(0.2)


def measure_point(net: Network, workdir: Path, curve: str, n: int, rate: float, seconds: float,
                  token_peer: int = 0) -> dict:
    """One point: a fresh interceptor A and publisher, ``n`` streams opened, an idle
    window and a load window. ``token_peer``: (``token`` curve) the topic count of the
    peer whose token is used."""
    from cryptoros.bench.chain import Proc

    host = net.start("robot_a")
    pid = host.proc.pid
    name = f"/scale_pub_{curve}{n}"
    topics = {"streams": ["/scale/s"] * n, "topics": [_topic(i) for i in range(n)], "token": [_topic(0)] * n}[curve]
    pub = Proc(f"publisher {name}", [sys.executable, "-c", "from cryptoros.bench.scale import _publisher; _publisher()",
                                      name, str({"streams": 0, "topics": n, "token": 1}[curve])],
               net.ros_env("robot_a"), workdir / f"publisher-{curve}{n}.log")
    try:
        pub.expect("READY", 120)
        peer = {"streams": PEER_STREAMS, "topics": _peer_topics(n), "token": _peer_topics(token_peer)}[curve]
        ctx, token, target = _target_of(net, peer, name, topics[0])
        time.sleep(1.0)  # the interceptor's start-up work (token, feed) is over
        rss_before = rss_kib(pid)
        client = Client(ctx=ctx, token=token, host=host.address, port=host.public_port, target=target)

        async def run() -> dict:
            cpu0 = cpu_seconds(pid)
            open_s = await client.open(topics)
            cpu_open = (cpu_seconds(pid) or 0.0) - (cpu0 or 0.0)
            links = await asyncio.to_thread(_wait_links, pub, len(topics) - len(client.failed), 30)
            await asyncio.sleep(1.0)
            rss_open = rss_kib(pid)
            idle_s = max(1.0, seconds / 2)
            c0, t0 = cpu_seconds(pid), time.monotonic()
            await asyncio.sleep(idle_s)
            idle = ((cpu_seconds(pid) or 0.0) - (c0 or 0.0)) / (time.monotonic() - t0)
            await asyncio.to_thread(pub.send, f"RUN {rate:g} {dict(streams='s', topics='t', token='o')[curve]}")
            await asyncio.to_thread(pub.expect, "RUNNING", 10)
            await asyncio.sleep(0.5)  # the first publications are under way
            f0, c0, t0 = client.frames, cpu_seconds(pid), time.monotonic()
            await asyncio.sleep(seconds)
            f1, c1, t1 = client.frames, cpu_seconds(pid), time.monotonic()
            rss_load = rss_kib(pid)
            await asyncio.to_thread(pub.send, "STOP")
            await asyncio.to_thread(pub.expect, "STOPPED", 10)
            await client.close()
            carried, cpu = f1 - f0, (c1 or 0.0) - (c0 or 0.0)
            return {
                "count": n, "peer": peer, "token_bytes": len(token), "streams_open": links, "failed": len(client.failed), "first_failures": client.failed[:3],
                "open_s": round(open_s, 3), "open_ms_per_stream": round(1000 * open_s / n, 3),
                "open_cpu_ms_per_stream": round(1000 * cpu_open / n, 3),
                "rss_before_kib": rss_before, "rss_open_kib": rss_open, "rss_load_kib": rss_load,
                "rss_added_kib": None if rss_before is None or rss_open is None else rss_open - rss_before,
                "idle_cpu_share": round(idle, 5),
                "window_s": round(t1 - t0, 3), "messages": carried, "msg_per_s": round(carried / (t1 - t0), 1),
                "cpu_s": round(cpu, 3),
                "cpu_us_per_message": round(1e6 * cpu / carried, 2) if carried else None,
                "cpu_share": round(cpu / (t1 - t0), 4),
            }

        return asyncio.run(run())
    finally:
        pub.close()
        net.stop("robot_a")


# ============================================================ fits


def fit(xs: list[float], ys: list[float | None]) -> dict:
    """A least-squares line y = slope x + intercept over the points, and whether the
    last step costs more per unit than :data:`SUPERLINEAR` times the first."""
    pts = [(x, y) for x, y in zip(xs, ys) if y is not None]
    if len(pts) < 2:
        return {"slope": None, "intercept": None, "step_ratio": None, "superlinear": None}
    n = len(pts)
    mx, my = sum(x for x, _ in pts) / n, sum(y for _, y in pts) / n
    sxx = sum((x - mx) ** 2 for x, _ in pts)
    slope = sum((x - mx) * (y - my) for x, y in pts) / sxx
    intercept = my - slope * mx
    steps = [(y1 - y0) / (x1 - x0) for (x0, y0), (x1, y1) in zip(pts, pts[1:])]
    ratio = None
    if len(steps) >= 2 and steps[0] > 0:
        ratio = steps[-1] / steps[0]
    return {"slope": slope, "intercept": intercept, "step_ratio": None if ratio is None else round(ratio, 2),
            "superlinear": None if ratio is None else ratio > SUPERLINEAR}


def curve_fits(points: list[dict]) -> dict:
    xs = [p["count"] for p in points]
    return {
        "rss_kib": fit(xs, [p["rss_added_kib"] for p in points]),
        "cpu_us_per_message": fit(xs, [p["cpu_us_per_message"] for p in points]),
        "idle_cpu_share": fit(xs, [p["idle_cpu_share"] for p in points]),
        "open_cpu_ms": fit(xs, [p["open_cpu_ms_per_stream"] * p["count"] for p in points]),
    }


# ============================================================ authorization replicas


def measure_authz(workdir: Path, replicas: tuple[int, ...], clients: int, seconds: float) -> dict:
    """Tokens/s and latency against 1, 2, 4 replicas on PostgreSQL (skipped without it)."""
    from cryptoros.bench.fleet import _clients, _fleet, _pct, _token_loop, _wait_healthy
    from cryptoros.lab.postgres import postgres_unavailable
    from cryptoros.tls import TLSConfig, client_context

    reason = postgres_unavailable()
    if reason is not None:
        return {"skipped": f"no PostgreSQL: {reason}"}
    rows = []
    for r in replicas:
        _progress(f"authorization: {r} replica(s) on PostgreSQL, {clients} clients for {seconds:g} s")
        with _fleet(workdir / f"authz-{r}", clients, r, 30.0) as fl:
            async def run() -> dict:
                cs = _clients(fl, 10.0)
                try:
                    return await measure(cs)
                finally:  # each client holds an aiohttp session: unclosed, aiohttp warns on stderr
                    await asyncio.gather(*(c.authz.close() for c in cs), return_exceptions=True)

            async def measure(cs: list) -> dict:
                _name, cert, key = fl.certs[0]
                await _wait_healthy(fl, client_context(TLSConfig(ca_file=fl.ca, cert_file=cert, key_file=key)))
                await asyncio.gather(*(_token_loop(c, time.monotonic() + 1.0) for c in cs))  # warm: connections
                for c in cs:
                    c.latencies.clear()
                    c.errors.clear()
                cpu0, pg0, own0 = fl.replica_cpu(), fl.postgres_cpu(), time.process_time()
                start = time.monotonic()
                await asyncio.gather(*(_token_loop(c, start + seconds) for c in cs))
                elapsed = time.monotonic() - start
                cpu1, pg1, own1 = fl.replica_cpu(), fl.postgres_cpu(), time.process_time()
                lat = [x for c in cs for x in c.latencies]
                replica_cpu = sum(cpu1) - sum(cpu0)
                return {"replicas": r, "clients": clients, "seconds": round(elapsed, 2), "tokens": len(lat),
                        "errors": sum(len(c.errors) for c in cs),
                        "tokens_per_s": round(len(lat) / elapsed, 1),
                        "p50_ms": round(1000 * _pct(lat, 50), 2) if lat else None,
                        "p99_ms": round(1000 * _pct(lat, 99), 2) if lat else None,
                        "replica_cpu_ms_per_token": round(1000 * replica_cpu / len(lat), 3) if lat else None,
                        # the clients' side (TLS, HTTP, JSON) runs in this process, on the same cores
                        "client_cpu_ms_per_token": round(1000 * (own1 - own0) / len(lat), 3) if lat else None,
                        "postgres_cpu_ms_per_token": round(1000 * (pg1 - pg0) / len(lat), 3)
                        if lat and pg0 is not None and pg1 is not None else None}
            rows.append(asyncio.run(run()))
    return {"backend": "postgresql", "rows": rows}


# ============================================================ report


def _fmt(v, spec: str = "") -> str:
    return "-" if v is None else format(v, spec)


def render(report: dict) -> None:
    click.echo(f"cryptoros bench scale (load average at the start {report['loadavg_start']}, at the end "
               f"{report['loadavg_end']}; publisher rate {report['rate']:g} messages/s in all at every point, "
               f"{report['seconds']:g} s windows)")
    click.echo("robot A's raised limits (the rest at their defaults): "
               + ", ".join(f"{k} = {v}" for k, v in report["limits"].items()))
    for curve, unit in CURVE_TITLES.items():
        points = report["curves"].get(curve)
        if not points:
            continue
        click.echo(f"\n{curve}: {unit} (the peer's token: {points[-1]['token_bytes']:,} bytes at the last point)")
        click.echo(f"{'N':>6} {'open':>6} {'msg/s':>8} {'CPU us/msg':>11} {'CPU share':>10} {'idle CPU':>9} "
                   f"{'RSS MiB':>8} {'+RSS MiB':>9} {'open ms/N':>10} {'open CPU ms/N':>14}")
        for p in points:
            click.echo(f"{p['count']:>6} {p['streams_open']:>6} {p['msg_per_s']:>8.0f} "
                       f"{_fmt(p['cpu_us_per_message'], '.1f'):>11} {p['cpu_share']:>10.1%} "
                       f"{p['idle_cpu_share']:>9.2%} {_fmt(p['rss_open_kib'] and p['rss_open_kib'] / 1024, '.1f'):>8} "
                       f"{_fmt(p['rss_added_kib'] and p['rss_added_kib'] / 1024, '.2f'):>9} "
                       f"{p['open_ms_per_stream']:>10.2f} {p['open_cpu_ms_per_stream']:>14.2f}")
        f = report["fits"][curve]
        per = "topic" if curve == "topics" else "stream"
        click.echo(f"cost per {per} (least squares over the points): RSS {_fmt(f['rss_kib']['slope'], '.1f')} KiB "
                   f"(+ {_fmt(f['rss_kib']['intercept'], '.0f')} KiB); CPU per message "
                   f"{_fmt(f['cpu_us_per_message']['slope'], '.4f')} us per {per} "
                   f"(+ {_fmt(f['cpu_us_per_message']['intercept'], '.1f')} us); idle CPU "
                   f"{_fmt(f['idle_cpu_share']['slope'] and 1e6 * f['idle_cpu_share']['slope'], '.2f')} us/s per {per}; "
                   f"set-up {_fmt(f['open_cpu_ms']['slope'], '.2f')} ms of CPU per {per}")
        for what, fl in f.items():
            if fl["superlinear"]:
                click.echo(f"  FASTER THAN LINEAR: {what}: its last step costs {fl['step_ratio']}x its first per {per}")
        failed = sum(p["failed"] for p in points)
        if failed:
            click.echo(f"  {failed} streams could not be opened: {[p['first_failures'] for p in points if p['failed']]}")
    authz = report.get("authz")
    if authz is not None:
        click.echo("\nauthorization replicas on PostgreSQL (tokens in a loop)")
        if "skipped" in authz:
            click.echo(f"  skipped: {authz['skipped']}")
        else:
            click.echo(f"{'replicas':>8} {'clients':>8} {'tokens/s':>9} {'p50 ms':>7} {'p99 ms':>7} {'errors':>7} "
                       f"{'replica CPU ms/token':>21} {'PostgreSQL CPU ms/token':>24} {'client CPU ms/token':>20}")
            for r in authz["rows"]:
                click.echo(f"{r['replicas']:>8} {r['clients']:>8} {r['tokens_per_s']:>9.1f} {_fmt(r['p50_ms']):>7} "
                           f"{_fmt(r['p99_ms']):>7} {r['errors']:>7} {_fmt(r['replica_cpu_ms_per_token']):>21} "
                           f"{_fmt(r['postgres_cpu_ms_per_token']):>24} {_fmt(r['client_cpu_ms_per_token']):>20}")


def write_plots(report: dict, out: Path) -> list[Path]:
    """streams.png and topics.png (CPU per message and RSS added against N, with the
    fitted lines), authz.png (tokens/s and p99 against replicas)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    made = []
    axis = {"streams": "open streams (one topic, one peer)", "topics": "topics per peer (a stream each)",
            "token": "open streams (one topic), the largest token"}
    for curve, label in axis.items():
        points = report["curves"].get(curve)
        if not points:
            continue
        xs = [p["count"] for p in points]
        fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9, 3.6))
        for ax, key, scale, ylabel, fkey in (
                (ax1, "cpu_us_per_message", 1.0, "interceptor CPU per message (us)", "cpu_us_per_message"),
                (ax2, "rss_added_kib", 1 / 1024, "RSS added by the streams (MiB)", "rss_kib")):
            ys = [p[key] * scale if p[key] is not None else None for p in points]
            ax.plot(xs, ys, "o-", label="measured")
            f = report["fits"][curve][fkey]
            if f["slope"] is not None:
                grid = [min(xs) * (max(xs) / min(xs)) ** (i / 60) for i in range(61)]  # a line, on a log axis
                ax.plot(grid, [(f["slope"] * x + f["intercept"]) * scale for x in grid], "k:",
                        label=f"fit: {f['slope'] * scale:.3g} per unit + {f['intercept'] * scale:.3g}")
            ax.set_xscale("log")
            ax.set_xlabel(label)
            ax.set_ylabel(ylabel)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
        fig.suptitle(f"robot A's interceptor, {report['rate']:g} messages/s in all (load {report['loadavg_start']})",
                     fontsize=9)
        fig.tight_layout()
        path = out / f"scale-{curve}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        made.append(path)
    authz = report.get("authz") or {}
    if authz.get("rows"):
        rows = authz["rows"]
        fig, ax1 = plt.subplots(figsize=(5, 3.6))
        xs = [r["replicas"] for r in rows]
        ax1.plot(xs, [r["tokens_per_s"] for r in rows], "o-", label="tokens/s")
        ax1.set_xlabel("cryptoros-authz replicas (one PostgreSQL)")
        ax1.set_ylabel("tokens/s")
        ax1.set_xticks(xs)
        ax2 = ax1.twinx()
        ax2.plot(xs, [r["p99_ms"] for r in rows], "s--", color="tab:red", label="p99 ms")
        ax2.set_ylabel("p99 latency (ms)")
        ax1.grid(alpha=0.3)
        fig.legend(loc="lower center", fontsize=8, ncol=2)
        fig.tight_layout(rect=(0, 0.08, 1, 1))
        path = out / "scale-authz.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        made.append(path)
    return made


def _loadavg() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "?"


@click.command()
@click.option("--quick", is_flag=True, help="A small run: 10 and 100 streams and topics, 1 and 2 replicas, short windows.")
@click.option("--rate", type=click.FloatRange(1, 100000), default=None,
              help="Messages a second the publisher sends in all at every point (default 2000; --quick 1000).")
@click.option("--seconds", type=click.FloatRange(0.5, 600), default=None,
              help="Length of each point's load window (default 8; --quick 2).")
@click.option("--curves", default=None, help="Which interceptor curves to run (default streams,topics,token; "
              "--quick streams,topics).")
@click.option("--counts", "count_text", default=None, help="Streams and topics per point (default 10,100,1000; "
              "--quick 10,100).")
@click.option("--replicas", "replica_text", default=None, help="Authorization replica counts (default 1,2,4; --quick 1,2; "
              "'' or 0: none).")
@click.option("--authz-clients", type=click.IntRange(1, 1000), default=None,
              help="Token clients (default 16; --quick 4).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write every figure as JSON.")
@click.option("--plots", "plots_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Also draw scale-streams.png, scale-topics.png and scale-authz.png into this directory.")
def scale(quick: bool, rate: float | None, seconds: float | None, curves: str | None, count_text: str | None,
          replica_text: str | None,
          authz_clients: int | None, json_path: Path | None, plots_dir: Path | None) -> None:
    """An interceptor's CPU per message and RSS against open streams and topics per
    peer; authorization replicas on PostgreSQL (tokens/s, p99)."""
    counts = QUICK_COUNTS if quick else COUNTS
    if count_text:
        try:
            counts = tuple(sorted({int(c) for c in count_text.split(",") if c.strip()}))
        except ValueError:
            raise click.BadParameter(f"{count_text!r}: expected counts such as 10,100,1000", param_hint="--counts") \
                from None
        if not counts or min(counts) < 1 or max(counts) > 5000:
            raise click.BadParameter(f"{count_text!r}: counts from 1 to 5000", param_hint="--counts")
    rate = rate or (1000.0 if quick else 2000.0)
    seconds = seconds or (2.0 if quick else 8.0)
    curves = curves if curves is not None else "streams,topics" if quick else ",".join(CURVES)
    wanted = [c.strip() for c in curves.split(",") if c.strip()]
    if any(c not in CURVES for c in wanted):
        raise click.BadParameter(f"{curves!r}: expected some of {', '.join(CURVES)}", param_hint="--curves")
    if replica_text is None:
        replicas = QUICK_REPLICAS if quick else REPLICAS
    else:
        try:
            replicas = tuple(int(r) for r in replica_text.split(",") if r.strip() and int(r) > 0)
        except ValueError:
            raise click.BadParameter(f"{replica_text!r}: expected counts such as 1,2,4", param_hint="--replicas") \
                from None
    clients = authz_clients or (4 if quick else 16)
    report: dict = {"quick": quick, "rate": rate, "seconds": seconds, "counts": list(counts),
                    "limits": limits(max(counts)), "loadavg_start": _loadavg(), "curves": {}, "fits": {},
                    "driver": "a light client in the bench's process: mutual TLS, the cryptoros preamble and a "
                              "TCPROS subscriber header per stream, frames counted (no rospy)"}
    with tempfile.TemporaryDirectory(prefix="cryptoros-bench-scale-") as tmp:
        work = Path(tmp)
        try:
            if wanted:
                hosts = dict(SCALE_HOSTS)
                for i, n in enumerate(counts):
                    hosts[_peer_topics(n)] = f"127.0.0.{8 + i}"
                with lab_network(work / "net", policy(counts), hosts=hosts, limits=report["limits"],
                                 start=["master"], progress=lambda m: _progress(f"network: {m}")) as net:
                    for curve in wanted:
                        points = []
                        for n in counts:
                            _progress(f"{curve}: {n} ... (load {_loadavg()})")
                            p = measure_point(net, work, curve, n, rate, seconds, token_peer=max(counts))
                            _progress(f"{curve}: {n}: {p['streams_open']} open, {p['msg_per_s']:.0f} msg/s, "
                                      f"{_fmt(p['cpu_us_per_message'])} us/msg, +{_fmt(p['rss_added_kib'])} KiB")
                            points.append(p)
                        report["curves"][curve] = points
                        report["fits"][curve] = curve_fits(points)
            if replicas:
                report["authz"] = measure_authz(work, replicas, clients, seconds)
        except NetworkError as exc:
            raise click.ClickException(str(exc)) from None
    report["loadavg_end"] = _loadavg()
    render(report)
    if plots_dir is not None:
        for path in write_plots(report, plots_dir):
            click.echo(f"figure: {path}")
    if json_path is not None:
        write_output(json_path, json.dumps(report, indent=1))


__all__ = ["curve_fits", "fit", "limits", "policy", "scale"]
