"""``cryptoros bench interceptor``: plain ROS 1, our interceptors and stunnel4, side by side.

One run builds a robot network on loopback (:mod:`cryptoros.lab.network`: PKI,
registry, ``cryptoros-authz`` daemon, Debian ``rosmaster``, interceptors for hosts
M 127.0.0.4, A 127.0.0.2, B 127.0.0.3) and measures, for real rospy nodes (Debian's
``/usr/bin/python3``) and for our node client (:mod:`cryptoros.ros1.node`, uvloop):

``plain``        talker and listener straight to rosmaster; TCPROS straight from the
                 listener to the talker's port.
``interceptor``  talker on host A (``ROS_MASTER_URI`` = A's interceptor), listener on
                 host B: every XML-RPC call and the TCPROS stream go listener -> B's
                 relay -> mutual TLS + token preamble -> A's interceptor (header
                 checked against both tokens) -> talker. Discovery is ROS's own.
``stunnel``      the generic alternative as a fixed chain: talker's fixed TCPROS port
                 <- ``stunnel4`` server on 127.0.0.2 (TLS 1.3, mutual certificates from
                 the same CA) <- ``stunnel4`` client on 127.0.0.1 <- listener. ROS's
                 discovery cannot be pointed through stunnel (dynamic ports), so the
                 listener's TCPROS connect is redirected to the client's accept port
                 (``BENCH_VIA``); XML-RPC stays plain. Only the data path is tunnelled.

Rows: one-way latency at 1 kHz (p50/p99; the sender stamps CLOCK_MONOTONIC into a
std_msgs/String), small std_msgs/String throughput (sender unthrottled), MB/s for
sensor_msgs/Image of 80 KB and 1 MB, TCPROS connection set-up time (connect to the
publisher's header reply: TLS handshake + token check on the interceptor and stunnel
rows), a non-persistent service call (connect + header + request + reply, the common
case of ROS service clients) and requestTopic time, bytes on the wire per set-up (tcpdump on ``lo``), a robot's
bring-up (50 subscribers starting at once against a latched publisher, and a launch file of
30 stock nodes: :mod:`cryptoros.bench.bringup`), and the
paper's own experiment (section IV: N std_msgs/String at 10 Hz, the listener timed
from launch to exit as with ``time``, with and without interceptors).

Which checks ran on the interceptor rows is printed from the interceptors' own
counters (/metrics): streams accepted with a full or a resumed TLS handshake, peer
certificate checks (validity, CRL) and token checks, spare connections used.
``--tls-session-lifetime 0`` gives a full handshake on every stream; ``--no-spares``
turns the interceptors' spare connections off (on by default).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shutil
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import click

from cryptoros.bench.chain import (NODES, SYS_PY, TRANSPORTS, Proc, checks_delta, describe_checks, interceptor_checks,
                                   settled_checks, stunnel_chain, worker_cmd)
from cryptoros.lab.capture import Capture, CaptureError, flows
from cryptoros.lab.network import (HOSTS, UNTHROTTLED, Network, NetworkError, lab_network, free_port,
                                   stop)
from cryptoros.lab.policy import policy_yaml
from cryptoros.consoles import for_logs
from cryptoros.outputs import write_output
from cryptoros.ros1.uri import host_port

IMPLS = ("rospy", "ours")
PAPER = {100: (10.534, 10.711), 250: (25.588, 25.713), 500: (50.628, 50.747)}
PAPER_SETUP_BYTES = (2478, 14478)
PAPER_SLOTS = 24
#: robot_a/robot_b carry the throughput rows and the set-up probes (tokens with only
#: the grants those need); robot_c/robot_d run the paper's experiment.
BENCH_HOSTS = {**HOSTS, "robot_c": "127.0.0.5", "robot_d": "127.0.0.6"}

def _policy() -> str:
    rosout = ("*", "/rosout", "rosgraph_msgs/Log")
    string, image = ("*", "/bench_str", "std_msgs/String"), ("*", "/bench_img", "sensor_msgs/Image")
    trigger = ("*", "/bench_srv", "std_srvs/Trigger")
    paper = [("*", f"/paper_{i}", "std_msgs/String") for i in range(PAPER_SLOTS)]
    return policy_yaml({
        "master": {},
        "robot_a": {"publish": [string, image, rosout], "serve": [trigger]},
        # roslaunch's own parameters (the launch bring-up row): `grant-tools --roslaunch`
        "robot_b": {"publish": [rosout], "subscribe": [string, image], "call": [trigger],
                    "write_param": [("/roslaunch", ns, None)
                                    for ns in ("/run_id", "/roslaunch", "/rosdistro", "/rosversion")]},
        "robot_c": {"publish": [rosout, *paper]},
        "robot_d": {"publish": [rosout], "subscribe": paper},
    })


# ============================================================ our node client's worker


def _our_worker() -> None:
    """Entry point of our talker/listener processes; the same protocol as
    ``ros1_nodes/rospy_worker.py`` (argv: ROLE), plus ROLE ``idle``: advertise
    /bench_str, print ``URI <xmlrpc uri> <tcpros port>`` and wait for ``quit``, and ROLE
    ``latched``: the same with /bench_str latched and one message published (every new
    subscriber receives it at once: the bring-up row)."""
    from cryptoros.bench.ros1 import publish_workload, record_message
    from cryptoros.ros1 import msgs
    from cryptoros.memory import tune_malloc
    from cryptoros.ros1.node import Node, install_uvloop

    role = sys.argv[1]
    install_uvloop()
    tune_malloc()
    via = os.environ.get("BENCH_VIA")
    if via:
        via_host, via_port = via.rsplit(":", 1)
        original = Node.call_api

        async def call_api(self, uri, method, *params):  # the stunnel chain: TCPROS to the tunnel
            reply = await original(self, uri, method, *params)
            if method == "requestTopic" and isinstance(reply, list) and len(reply) == 3:
                reply = [reply[0], via_host, int(via_port)]
            return reply

        Node.call_api = call_api  # type: ignore[method-assign]

    def out(line: str) -> None:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()

    async def lines():
        loop = asyncio.get_running_loop()
        while True:
            line = await loop.run_in_executor(None, sys.stdin.readline)
            if not line or line.split()[:1] == ["quit"]:
                return
            if line.split():
                yield line.split()

    async def listen() -> None:
        st: dict = {"mode": None, "n": 0, "want": 0, "t0": 0, "t1": 0, "bytes": 0, "lat": []}
        done = asyncio.Event()
        clock = time.monotonic_ns

        def on_msg(m, mode: str) -> None:
            now = clock()
            if st["mode"] != mode:
                return
            if record_message(st, m.data, mode, now) >= st["want"]:
                done.set()

        async with Node("/bench_listener_ours") as node:
            await node.subscribe("/bench_str", "std_msgs/String",
                                 lambda m: on_msg(m, "latency" if st["mode"] == "latency" else "small"))
            await node.subscribe("/bench_img", "sensor_msgs/Image", lambda m: on_msg(m, "image"))
            out("SUBSCRIBED")
            async for parts in lines():
                mode, n = parts[0], int(parts[1])
                done.clear()
                st.update(mode=mode, n=0, want=n, t0=0, t1=0, bytes=0, lat=[])
                out("ARMED")
                last, deadline = -1, time.monotonic() + 120
                while time.monotonic() < deadline:
                    with contextlib.suppress(asyncio.TimeoutError):
                        await asyncio.wait_for(done.wait(), 3.0)
                    if done.is_set() or st["n"] == last:
                        break
                    last = st["n"]
                st["mode"] = None
                out("RESULT " + json.dumps({k: st[k] for k in ("n", "t0", "t1", "bytes", "lat")}))

    async def talk() -> None:
        port = int(os.environ.get("BENCH_TCPROS_PORT", "0"))
        async with Node("/bench_talker_ours", tcpros_port=port) as node:
            pub_str = await node.advertise("/bench_str", "std_msgs/String")
            pub_img = await node.advertise("/bench_img", "sensor_msgs/Image")
            try:
                await pub_str.wait_for_subscribers(1, 60)
                await pub_img.wait_for_subscribers(1, 60)
            except asyncio.TimeoutError:
                out("TIMEOUT no subscriber")
                return
            await asyncio.sleep(0.3)
            out("READY")
            async for parts in lines():
                mode, n, size = parts[0], int(parts[1]), int(parts[2])
                await publish_workload(mode, n, size, pub_str, pub_img)
                out("SENT")

    async def idle() -> None:
        async with Node("/bench_idle", tcpros_port=int(os.environ.get("BENCH_TCPROS_PORT", "0"))) as node:
            await node.advertise("/bench_str", "std_msgs/String")
            trigger = msgs.service_type("std_srvs/Trigger", node.store)
            await node.advertise_service("/bench_srv", "std_srvs/Trigger",
                                         lambda _req: trigger.response_class()(success=True, message="ok"))
            out(f"URI {node.uri} {node.tcpros_port}")
            async for _ in lines():
                pass

    async def latched() -> None:
        from cryptoros.bench.bringup import worker_endpoint

        async with Node("/bench_latched", tcpros_port=int(os.environ.get("BENCH_TCPROS_PORT", "0")),
                        tcpros_endpoint=worker_endpoint()) as node:
            pub = await node.advertise("/bench_str", "std_msgs/String", latch=True)
            pub.publish(node.msg("std_msgs/String", data="bring-up"))
            out(f"URI {node.uri} {node.tcpros_port}")
            async for _ in lines():
                pass

    asyncio.run({"listen": listen, "talk": talk, "idle": idle, "latched": latched}[role]())


# ============================================================ throughput and latency


@dataclass
class Mode:
    key: str
    label: str
    mode: str
    n: int
    size: int = 0


def _summary(mode: Mode, raw: dict) -> dict:
    got = raw["n"]
    span = max(raw["t1"] - raw["t0"], 1) / 1e9
    out: dict = {"received": got, "sent": mode.n}
    if mode.mode == "small":
        out["msg_per_s"] = (got - 1) / span if got > 1 else 0.0
    elif mode.mode == "latency":
        lat = sorted(raw["lat"])
        if lat:
            out["p50_us"] = lat[len(lat) // 2] / 1e3
            out["p99_us"] = lat[min(len(lat) - 1, int(len(lat) * 0.99))] / 1e3
            out["samples_us"] = [round(x / 1e3, 1) for x in lat]  # for --plots
    else:
        per = raw["bytes"] / got if got else 0
        out["mb_per_s"] = (raw["bytes"] - per) / span / 1e6 if got > 1 else 0.0
    return out


def run_pair(net: Network, impl: str, transport: str, modes: list[Mode], workdir: Path,
             progress: Callable[[str], None]) -> dict[str, dict]:
    """One talker and one listener process over ``transport``; every mode in turn."""
    tag = f"{impl}-{transport}"
    talker_env_host, listener_env_host = ("robot_a", "robot_b") if transport == "interceptor" else (None, None)
    talker_port = free_port() if transport == "stunnel" else 0
    results: dict[str, dict] = {}
    with contextlib.ExitStack() as stack:
        listener_extra: dict[str, str] = {}
        talker_extra: dict[str, str] = {}
        if transport == "stunnel":
            client_port, _server_port = stack.enter_context(stunnel_chain(net, talker_port, workdir, tag))
            listener_extra["BENCH_VIA"] = f"127.0.0.1:{client_port}"
            talker_extra["BENCH_TCPROS_PORT"] = str(talker_port)
        listener = Proc(f"{tag} listener", worker_cmd(impl, "listen"), net.ros_env(listener_env_host, **listener_extra),
                        workdir / f"{tag}-listener.log")
        stack.callback(listener.close)
        listener.expect("SUBSCRIBED", 60)
        talker = Proc(f"{tag} talker", worker_cmd(impl, "talk"), net.ros_env(talker_env_host, **talker_extra),
                      workdir / f"{tag}-talker.log")
        stack.callback(talker.close)
        talker.expect("READY", 60)
        for mode in modes:
            listener.send(f"{mode.mode} {mode.n} {mode.size}")
            listener.expect("ARMED", 10)
            talker.send(f"{mode.mode} {mode.n} {mode.size}")
            raw = json.loads(listener.expect("RESULT ", 180)[7:])
            talker.expect("SENT", 60)
            results[mode.key] = _summary(mode, raw)
            progress(f"{impl:5s} {transport:11s} {mode.label:28s} {_short(results[mode.key])}")
    return results


def _short(r: dict) -> str:
    parts = []
    for k, fmt in (("p50_us", "p50 {:,.0f} us"), ("p99_us", "p99 {:,.0f} us"), ("msg_per_s", "{:,.0f} msg/s"),
                   ("mb_per_s", "{:,.0f} MB/s")):
        if k in r:
            parts.append(fmt.format(r[k]))
    if r.get("received") != r.get("sent"):
        parts.append(f"received {r.get('received')}/{r.get('sent')}")
    return ", ".join(parts)


# ============================================================ connection set-up


async def _tcpros_probe(host: str, port: int, topic: str = "/bench_str") -> tuple[float, asyncio.StreamWriter]:
    """Connect, send a subscriber header, read the publisher's reply header: seconds."""
    from cryptoros.ros1 import msgs
    from cryptoros.ros1.tcpros import encode_header

    header = encode_header({
        "callerid": "/bench_probe", "md5sum": msgs.md5sum("std_msgs/String"),
        "message_definition": msgs.message_definition("std_msgs/String"), "tcp_nodelay": "1",
        "topic": topic, "type": "std_msgs/String",
    })
    t0 = time.perf_counter()
    _reader, writer, body = await _open_with_header(host, port, header)
    elapsed = time.perf_counter() - t0
    if b"error=" in body:
        writer.close()
        raise NetworkError(f"publisher refused the probe: {body[:200]!r}")
    return elapsed, writer


async def _open_with_header(host: str, port: int, header: bytes) -> tuple[asyncio.StreamReader,
                                                                          asyncio.StreamWriter, bytes]:
    """Connect, send a TCPROS connection header, read the reply header (each step
    bounded): the streams and the reply's bytes. Closed on failure."""
    reader, writer = await asyncio.wait_for(asyncio.open_connection(host, port), 10)
    try:
        writer.write(header)
        (length,) = struct.unpack("<I", await asyncio.wait_for(reader.readexactly(4), 10))
        return reader, writer, await asyncio.wait_for(reader.readexactly(length), 10)
    except BaseException:
        writer.close()
        raise


async def _service_probe(host: str, port: int, service: str = "/bench_srv") -> float:
    """One non-persistent service call as a ROS client makes it: connect, header, the
    server's header, the request (std_srvs/Trigger), the response: seconds."""
    from cryptoros.ros1 import msgs
    from cryptoros.ros1.tcpros import encode_frame, encode_header

    srv = msgs.service_type("std_srvs/Trigger")
    header = encode_header({"callerid": "/bench_probe", "md5sum": srv.md5sum, "persistent": "0", "service": service})
    t0 = time.perf_counter()
    reader, writer, body = await _open_with_header(host, port, header)
    try:
        if b"error=" in body:
            raise NetworkError(f"service server refused the probe: {body[:200]!r}")
        writer.write(encode_frame(b""))
        ok, length = struct.unpack("<BI", await asyncio.wait_for(reader.readexactly(5), 10))
        await asyncio.wait_for(reader.readexactly(length), 10)
        elapsed = time.perf_counter() - t0
    finally:
        writer.close()
    if ok != 1:
        raise NetworkError("the service call failed")
    return elapsed


async def _request_topic(uri: str, topic: str = "/bench_str") -> tuple[float, tuple[str, int]]:
    from cryptoros.ros1.node import call

    t0 = time.perf_counter()
    reply = await call(uri, "requestTopic", "/bench_probe", topic, [["TCPROS"]], timeout=10)
    elapsed = time.perf_counter() - t0
    if not (isinstance(reply, list) and len(reply) == 3):
        raise NetworkError(f"requestTopic answered {reply!r}")
    return elapsed, (reply[1], int(reply[2]))


def _stats(samples: list[float]) -> dict:
    ms = sorted(s * 1e3 for s in samples)
    return {"median_ms": statistics.median(ms), "p90_ms": ms[min(len(ms) - 1, int(len(ms) * 0.9))], "n": len(ms),
            "samples_ms": [round(x, 3) for x in ms]}


def _bytes_entry(fl: list[dict], labels: list[str]) -> dict:
    out: dict = {}
    for label, flow in zip(labels, fl, strict=False):
        out[label] = {k: flow[k] for k in ("frames", "frame_bytes", "ip_bytes", "payload_bytes")}
    out["total"] = {k: sum(flow[k] for flow in fl[: len(labels)]) for k in ("frames", "frame_bytes", "ip_bytes",
                                                                           "payload_bytes")}
    return out


def token_sizes(net: Network, names: tuple[str, ...] = ("robot_a", "robot_b")) -> dict[str, int]:
    """Bytes of each manager's access token as the daemon issues it (what a preamble carries)."""
    import http.client

    from cryptoros.tls import TLSConfig, client_context

    sizes = {}
    host, port = host_port(net.authz_url, ("https",))
    for name in names:
        cert, key = net.cert(name)
        ctx = client_context(TLSConfig(ca_file=net.ca, cert_file=cert, key_file=key))
        conn = http.client.HTTPSConnection(host, int(port), context=ctx, timeout=10)
        try:
            conn.request("POST", "/token", body="grant_type=client_credentials",
                         headers={"Content-Type": "application/x-www-form-urlencoded"})
            body = json.loads(conn.getresponse().read())
            sizes[name] = len(body.get("access_token", ""))
        finally:
            conn.close()
    return sizes


def measure_setup(net: Network, reps: int, workdir: Path, progress: Callable[[str], None]) -> dict:
    """TCPROS connection set-up time and bytes, plus requestTopic time, per transport.

    An idle talker of our node client publishes /bench_str; a probe in this process
    does what a subscriber does. Plain: requestTopic on the talker, TCPROS to its port.
    Interceptor: the probe registers through B's interceptor (gets B's relay URI),
    then requestTopic and TCPROS through B's relays, tunnelled to A. Stunnel: TCPROS to
    the stunnel client's port (the talker's fixed port behind the server)."""
    result: dict = {}
    with contextlib.suppress(Exception):
        result["token_bytes"] = token_sizes(net)
    talker_port = free_port()
    # -------- plain and stunnel: one idle talker registered straight with rosmaster
    idle = Proc("idle talker (plain)", worker_cmd("ours", "idle"), net.ros_env(None, BENCH_TCPROS_PORT=str(talker_port)),
                workdir / "idle-plain.log")
    try:
        _, uri, port_text = idle.expect("URI ", 30).split()
        xml_port = host_port(uri)[1]
        with stunnel_chain(net, talker_port, workdir, "setup") as (client_port, server_port):

            async def plain_and_stunnel() -> dict:
                out: dict = {"plain": {}, "stunnel": {}}
                rt, tc, st, sc, ssc = [], [], [], [], []
                for _ in range(reps):
                    t, (host, port) = await _request_topic(uri)
                    rt.append(t)
                    t, w = await _tcpros_probe(host, port)
                    tc.append(t)
                    w.close()
                    t, w = await _tcpros_probe("127.0.0.1", client_port)
                    st.append(t)
                    w.close()
                    sc.append(await _service_probe(host, port))
                    ssc.append(await _service_probe("127.0.0.1", client_port))
                    await asyncio.sleep(0.02)
                out["plain"]["request_topic"] = _stats(rt)
                out["plain"]["tcpros_connect"] = _stats(tc)
                out["plain"]["service_call"] = _stats(sc)
                out["stunnel"]["tcpros_connect"] = _stats(st)
                out["stunnel"]["service_call"] = _stats(ssc)
                cap = Capture(workdir / "plain.pcap", f"tcp and host 127.0.0.1 and (port {xml_port} or port {port_text})", snaplen=128)
                try:
                    _, (host, port) = await _request_topic(uri)
                    await asyncio.sleep(0.1)
                    _, w = await _tcpros_probe(host, port)
                finally:
                    await asyncio.to_thread(cap.stop, 0.3)
                    fl = flows(cap.path)
                w.close()
                out["plain"]["bytes"] = _bytes_entry(fl, ["request_topic", "tcpros"])
                cap = Capture(workdir / "stunnel.pcap", f"tcp and port {server_port}", snaplen=128)
                try:
                    _, w = await _tcpros_probe("127.0.0.1", client_port)
                finally:
                    await asyncio.to_thread(cap.stop, 0.3)
                    fl = flows(cap.path)
                w.close()
                out["stunnel"]["bytes"] = _bytes_entry(fl, ["tcpros"])
                return out

            result.update(asyncio.run(plain_and_stunnel()))
    finally:
        idle.close()
    progress(f"set-up plain:   requestTopic {result['plain']['request_topic']['median_ms']:.2f} ms, "
             f"TCPROS {result['plain']['tcpros_connect']['median_ms']:.2f} ms, "
             f"service call {result['plain']['service_call']['median_ms']:.2f} ms, "
             f"{result['plain']['bytes']['total']['frame_bytes']:,} B")
    progress(f"set-up stunnel: TCPROS {result['stunnel']['tcpros_connect']['median_ms']:.2f} ms, "
             f"service call {result['stunnel']['service_call']['median_ms']:.2f} ms, "
             f"{result['stunnel']['bytes']['total']['frame_bytes']:,} B")
    # -------- interceptor: idle talker on A, probe on B
    idle = Proc("idle talker (A)", worker_cmd("ours", "idle"), net.ros_env("robot_a"), workdir / "idle-icpt.log")
    try:
        idle.expect("URI ", 30)

        async def intercepted() -> dict:
            from cryptoros.ros1.node import Node

            out: dict = {}
            a_public = net.hosts["robot_a"].public_port
            async with Node("/bench_probe", net.hosts["robot_b"].master_uri) as node:
                pubs = await node.master("registerSubscriber", "/bench_str", "std_msgs/String", node.uri)
                if not pubs:
                    raise NetworkError("no publisher of /bench_str reached B's interceptor")
                relay = pubs[0]
                service_host, service_port = host_port(await node.master("lookupService", "/bench_srv"), ("rosrpc",))
                before = interceptor_checks(net)
                rt, tc, sc = [], [], []
                for _ in range(reps):
                    t, (host, port) = await _request_topic(relay)
                    rt.append(t)
                    t, w = await _tcpros_probe(host, port)
                    tc.append(t)
                    w.close()
                    sc.append(await _service_probe(service_host, int(service_port)))
                    await asyncio.sleep(0.05)  # keep below the per-peer new-stream rate limit
                out["request_topic"] = _stats(rt)
                out["tcpros_connect"] = _stats(tc)
                out["service_call"] = _stats(sc)
                out["checks"] = checks_delta(before, await asyncio.to_thread(settled_checks, net))
                await asyncio.sleep(0.3)
                cap = Capture(workdir / "interceptor.pcap", f"tcp and host {HOSTS['robot_a']} and port {a_public}", snaplen=128)
                try:
                    _, (host, port) = await _request_topic(relay)
                    await asyncio.sleep(0.1)
                    _, w = await _tcpros_probe(host, port)
                finally:
                    await asyncio.to_thread(cap.stop, 0.3)
                    fl = flows(cap.path)
                w.close()
                out["bytes"] = _bytes_entry(fl, ["request_topic", "tcpros"])
                with contextlib.suppress(Exception):
                    await node.master("unregisterSubscriber", "/bench_str", node.uri)
            return out

        result["interceptor"] = asyncio.run(intercepted())
    finally:
        idle.close()
    progress(f"set-up interceptor: requestTopic {result['interceptor']['request_topic']['median_ms']:.2f} ms, "
             f"TCPROS {result['interceptor']['tcpros_connect']['median_ms']:.2f} ms, "
             f"service call {result['interceptor']['service_call']['median_ms']:.2f} ms, "
             f"{result['interceptor']['bytes']['total']['frame_bytes']:,} B")
    progress(f"set-up interceptor checks: {describe_checks(result['interceptor']['checks'])}")
    return result


# ============================================================ the paper's experiment


@dataclass
class PaperRun:
    n: int
    variant: str  # "without" | "with"
    slot: int
    elapsed: float | None = None
    to_first: float | None = None
    received: int = 0
    error: str = ""
    started: threading.Event = field(default_factory=threading.Event)


def _paper_one(net: Network, run: PaperRun, workdir: Path) -> None:
    talker_host, listener_host = ("robot_c", "robot_d") if run.variant == "with" else (None, None)
    topic = f"/paper_{run.slot}"
    name = f"paper_{run.slot}_{run.variant}"
    talker = Proc(f"paper talker {run.slot}", [SYS_PY, str(NODES / "paper_talker.py"), f"talker_{name}", topic,
                                                str(run.n)], net.ros_env(talker_host), workdir / f"{name}-talker.log")
    listener = None
    try:
        talker.expect("REGISTERED", 60)
        t0 = time.monotonic()
        listener = subprocess.Popen([SYS_PY, str(NODES / "paper_listener.py"), f"listener_{name}", topic, str(run.n)],
                                    env=net.ros_env(listener_host), stdout=subprocess.PIPE, text=True,
                                    stderr=(workdir / f"{name}-listener.log").open("w"))
        assert listener.stdout is not None
        for line in listener.stdout:  # bounded: the listener gives up after n * 0.1 + 60 s
            if line.startswith("FIRST"):
                run.to_first = float(line.split()[1]) - t0
                run.started.set()
            elif line.startswith("DONE"):
                run.received = int(line.split()[1])
        listener.wait(30)
        run.elapsed = time.monotonic() - t0
    except Exception as exc:  # reported in the table, never hidden
        run.error = str(exc)[:300]
    finally:
        run.started.set()
        if listener is not None:
            stop(listener)
        stop(talker.proc)


def paper_experiment(net: Network, counts: list[int], reps: int, workdir: Path,
                     progress: Callable[[str], None]) -> list[dict]:
    """Every (N, with/without, repetition) at once on its own topic, largest N first,
    each launched once the previous listener got its first message (start-ups do not
    overlap; the 10 Hz traffic that runs meanwhile is negligible)."""
    runs = []
    slot = 0
    for n in sorted(counts, reverse=True):
        for rep in range(reps):
            for variant in (("without", "with") if rep % 2 == 0 else ("with", "without")):
                runs.append(PaperRun(n=n, variant=variant, slot=slot))
                slot += 1
    if slot > PAPER_SLOTS:
        raise click.UsageError(f"at most {PAPER_SLOTS} paper runs (counts x repetitions x 2)")
    threads = []
    for run in runs:
        thread = threading.Thread(target=_paper_one, args=(net, run, workdir), daemon=True)
        thread.start()
        threads.append(thread)
        run.started.wait(30)
        progress(f"paper N={run.n} {run.variant:7s} launched (first message after "
                 f"{run.to_first if run.to_first is not None else float('nan'):.3f} s)")
    for thread in threads:
        thread.join(max(counts) * 0.1 + 120)
    rows = []
    for n in sorted(counts):
        row: dict = {"messages": n}
        for variant in ("without", "with"):
            mine = [r for r in runs if r.n == n and r.variant == variant]
            ok = [r for r in mine if r.elapsed is not None and r.received == n]
            row[variant] = {
                "elapsed_s": [r.elapsed for r in mine],
                "to_first_s": [r.to_first for r in mine],
                "mean_s": statistics.fmean(r.elapsed for r in ok) if ok else None,
                "mean_to_first_s": statistics.fmean(r.to_first for r in ok if r.to_first is not None) if ok else None,
                "errors": [r.error or f"received {r.received}/{n}" for r in mine if r not in ok],
            }
        a, b = row["without"]["mean_s"], row["with"]["mean_s"]
        row["overhead_pct"] = (b - a) / a * 100 if a and b else None
        if n in PAPER:
            pa, pb = PAPER[n]
            row["paper"] = {"without_s": pa, "with_s": pb, "overhead_pct": (pb - pa) / pa * 100}
        rows.append(row)
        progress(f"paper N={n}: without {a or float('nan'):.3f} s, with {b or float('nan'):.3f} s, "
                 f"overhead {row['overhead_pct'] if row['overhead_pct'] is not None else float('nan'):+.2f} %")
    return rows


# ============================================================ report


def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a and b else None


def build_report(results: dict) -> dict:
    """Targets and ratios from the raw results (also what --json writes)."""
    tp = results.get("throughput", {})
    targets = []
    for impl in IMPLS:
        if impl not in tp:  # --no-throughput, --only
            continue
        by = {t: tp.get(impl, {}).get(t, {}) for t in TRANSPORTS}
        for key, metric, label in (("small", "msg_per_s", "small messages"), ("image80k", "mb_per_s", "80 KB images"),
                                   ("image1m", "mb_per_s", "1 MB images")):
            icpt = by["interceptor"].get(key, {}).get(metric)
            stun = by["stunnel"].get(key, {}).get(metric)
            r = _ratio(icpt, stun)
            targets.append({"target": f"{label} throughput >= 1.3x stunnel ({impl})", "measured": r,
                            "unit": "x", "met": r is not None and r >= 1.3})
        p = {t: by[t].get("latency", {}).get("p50_us") for t in TRANSPORTS}
        if None not in p.values():
            added_i, added_s = p["interceptor"] - p["plain"], p["stunnel"] - p["plain"]
            targets.append({"target": f"added p50 latency at 1 kHz <= stunnel's ({impl})",
                            "measured": added_i, "limit": added_s, "unit": "us", "met": added_i <= added_s})
    setup = results.get("setup")
    if setup:
        plain_b = setup["plain"]["bytes"].get("tcpros", {}).get("frame_bytes")
        icpt_b = setup["interceptor"]["bytes"].get("tcpros", {}).get("frame_bytes")
        limit = (PAPER_SETUP_BYTES[1] - PAPER_SETUP_BYTES[0]) / 2
        if plain_b is not None and icpt_b is not None:
            targets.append({"target": "set-up bytes added per TCPROS connection <= half the paper's (6,000 B)",
                            "measured": icpt_b - plain_b, "limit": limit, "unit": "B", "met": icpt_b - plain_b <= limit})
        for what, label in (("tcpros_connect", "TCPROS connection set-up median <= stunnel's"),
                            ("service_call", "service call (connect + request + reply) median <= stunnel's")):
            icpt = setup["interceptor"].get(what, {}).get("median_ms")
            stun = setup["stunnel"].get(what, {}).get("median_ms")
            if icpt is not None and stun is not None:
                targets.append({"target": label, "measured": icpt, "limit": stun, "unit": "ms", "met": icpt <= stun})
        plain_t = setup["plain"]["bytes"]["total"]["frame_bytes"]
        icpt_t = setup["interceptor"]["bytes"]["total"]["frame_bytes"]
        targets.append({"target": "set-up bytes added per subscription (requestTopic + TCPROS) <= 6,000 B",
                        "measured": icpt_t - plain_t, "limit": limit, "unit": "B", "met": icpt_t - plain_t <= limit})
    for key, label in (("bringup", "subscribers at once"), ("launch", "nodes in a launch file")):
        rows = results.get(key)
        if rows:
            icpt, stun = rows["interceptor"]["median_ms"], rows["stunnel"]["median_ms"]
            r = _ratio(icpt, stun)
            count = rows.get("subscribers", rows.get("nodes"))
            targets.append({"target": f"bring-up of {count} {label} <= 1.5x stunnel's", "measured": r,
                            "limit": 1.5, "unit": "x", "met": r is not None and r <= 1.5})
    for row in results.get("paper", []):
        o = row.get("overhead_pct")
        targets.append({"target": f"paper experiment N={row['messages']}: overhead <= 0.2 %", "measured": o,
                        "limit": 0.2, "unit": "%", "met": o is not None and o <= 0.2})
    return {**results, "targets": targets}


def _fmt(v: float | None, fmt: str) -> str:
    return "-" if v is None else fmt.format(v)


def table_rows(report: dict) -> list[list[str]]:
    """measure | impl | plain | interceptor | stunnel | interceptor/stunnel | interceptor/plain"""
    rows = []
    tp = report.get("throughput", {})
    spec = [
        ("latency", "p50_us", "one-way latency 1 kHz p50", "{:,.0f} us", False),
        ("latency", "p99_us", "one-way latency 1 kHz p99", "{:,.0f} us", False),
        ("small", "msg_per_s", "std_msgs/String throughput", "{:,.0f} msg/s", True),
        ("image80k", "mb_per_s", "sensor_msgs/Image 80 KB", "{:,.0f} MB/s", True),
        ("image1m", "mb_per_s", "sensor_msgs/Image 1 MB", "{:,.0f} MB/s", True),
    ]
    for key, metric, label, fmt, _higher in spec:
        for impl in IMPLS:
            if impl not in tp:
                continue
            vals = {t: tp[impl].get(t, {}).get(key, {}) for t in TRANSPORTS}
            cells = []
            for t in TRANSPORTS:
                v = vals[t].get(metric)
                lost = "" if vals[t].get("received") == vals[t].get("sent") else f" ({vals[t].get('received')}/{vals[t].get('sent')})"
                cells.append(_fmt(v, fmt) + (lost if vals[t] else ""))
            i, s, p = (vals[t].get(metric) for t in ("interceptor", "stunnel", "plain"))
            rows.append([label, impl, *cells, _fmt(_ratio(i, s), "{:.2f}x"), _fmt(_ratio(i, p), "{:.2f}x")])
    setup = report.get("setup")
    if setup:
        for what, label in (("tcpros_connect", "TCPROS connection set-up (median)"),
                            ("service_call", "service call: connect + request + reply (median)"),
                            ("request_topic", "requestTopic call (median)")):
            v = {t: setup.get(t, {}).get(what, {}).get("median_ms") for t in TRANSPORTS}
            rows.append([label, "probe", *(_fmt(v[t], "{:.2f} ms") for t in TRANSPORTS),
                         _fmt(_ratio(v["interceptor"], v["stunnel"]), "{:.2f}x"),
                         _fmt(_ratio(v["interceptor"], v["plain"]), "{:.2f}x")])
        for what, label in (("tcpros", "bytes per TCPROS connection set-up"),
                            ("total", "bytes per subscription set-up")):
            v = {t: setup.get(t, {}).get("bytes", {}).get(what, {}).get("frame_bytes") for t in TRANSPORTS}
            pay = {t: setup.get(t, {}).get("bytes", {}).get(what, {}).get("payload_bytes") for t in TRANSPORTS}
            cells = [(_fmt(v[t], "{:,} B") + (f" ({pay[t]:,} payload)" if pay[t] is not None else "")) for t in TRANSPORTS]
            rows.append([label, "probe", *cells, _fmt(_ratio(v["interceptor"], v["stunnel"]), "{:.2f}x"),
                         _fmt(_ratio(v["interceptor"], v["plain"]), "{:.2f}x")])
        bringup = report.get("bringup")
        if bringup:
            v = {t: bringup.get(t, {}).get("median_ms") for t in TRANSPORTS}
            n, runs = bringup["subscribers"], bringup["runs"]

            def cell(t: str) -> str:
                got = bringup.get(t, {}).get("received", [])
                short = [g for g in got if g != n]
                return _fmt(v[t], "{:,.0f} ms") + (f" ({min(short)}/{n} received)" if short else "")

            rows.append([f"{n} subscribers at once: until all receive (median of {runs})", "ours",
                         *(cell(t) for t in TRANSPORTS), _fmt(_ratio(v["interceptor"], v["stunnel"]), "{:.2f}x"),
                         _fmt(_ratio(v["interceptor"], v["plain"]), "{:.2f}x")])
            cpu = {t: bringup.get(t, {}).get("relay_cpu_median_s") for t in TRANSPORTS}
            if cpu["interceptor"] is not None and cpu["stunnel"] is not None:
                rows.append(["  relays' CPU per bring-up (3 interceptors / 2 stunnel4)", "ours", "-",
                             _fmt(cpu["interceptor"] * 1e3, "{:,.0f} ms"), _fmt(cpu["stunnel"] * 1e3, "{:,.0f} ms"),
                             _fmt(_ratio(cpu["interceptor"], cpu["stunnel"]), "{:.2f}x"), "-"])
        rows += _launch_rows(report.get("launch"))
        tok = setup.get("token_bytes")
        if tok:
            rows.append(["access token per preamble (A / B)", "probe", "-",
                         " / ".join(f"{v:,} B" for v in tok.values()), "-", "-", "-"])
        rows.append(["paper: bytes per set-up", "CryptoROS", f"{PAPER_SETUP_BYTES[0]:,} B", f"{PAPER_SETUP_BYTES[1]:,} B",
                     "-", "-", f"{PAPER_SETUP_BYTES[1] / PAPER_SETUP_BYTES[0]:.2f}x"])
    for row in report.get("paper", []):
        w, wi = row["without"]["mean_s"], row["with"]["mean_s"]
        o = row.get("overhead_pct")
        paper = row.get("paper")
        note = f" (paper {paper['without_s']:.3f} / {paper['with_s']:.3f} s, {paper['overhead_pct']:+.1f} %)" if paper else ""
        rows.append([f"paper experiment N={row['messages']} at 10 Hz{note}", "rospy", _fmt(w, "{:.3f} s"),
                     _fmt(wi, "{:.3f} s"), "-", "-", _fmt(o, "{:+.2f} %")])
        fw, fwi = row["without"]["mean_to_first_s"], row["with"]["mean_to_first_s"]
        rows.append([f"  of which launch to first message (N={row['messages']})", "rospy", _fmt(fw, "{:.3f} s"),
                     _fmt(fwi, "{:.3f} s"), "-", "-",
                     _fmt((fwi - fw) * 1e3 if fw is not None and fwi is not None else None, "{:+.0f} ms")])
    return rows


def _launch_rows(launch: dict | None) -> list[list[str]]:
    if not launch:
        return []
    v = {t: launch.get(t, {}).get("median_ms") for t in TRANSPORTS}
    n, runs = launch["nodes"], launch["runs"]

    def cell(t: str) -> str:
        short = [g for g in launch.get(t, {}).get("received", []) if g != n]
        return _fmt(v[t], "{:,.0f} ms") + (f" ({min(short)}/{n} finished)" if short else "")

    rows = [[f"launch file of {n} rostopic echo nodes: roslaunch to exit (median of {runs})", "rospy",
             *(cell(t) for t in TRANSPORTS), _fmt(_ratio(v["interceptor"], v["stunnel"]), "{:.2f}x"),
             _fmt(_ratio(v["interceptor"], v["plain"]), "{:.2f}x")]]
    cpu = {t: launch.get(t, {}).get("relay_cpu_median_s") for t in TRANSPORTS}
    if cpu["interceptor"] is not None and cpu["stunnel"] is not None:
        rows.append(["  relays' CPU per launch (3 interceptors / 2 stunnel4)", "rospy", "-",
                     _fmt(cpu["interceptor"] * 1e3, "{:,.0f} ms"), _fmt(cpu["stunnel"] * 1e3, "{:,.0f} ms"),
                     _fmt(_ratio(cpu["interceptor"], cpu["stunnel"]), "{:.2f}x"), "-"])
    return rows


HEADERS = ["measure", "nodes", "plain", "interceptor", "stunnel", "interceptor/stunnel", "interceptor/plain"]


def checks_lines(report: dict) -> list[str]:
    """Which checks ran on the interceptor rows (from the interceptors' own counters)."""
    config = report.get("config", {})
    lines = [f"interceptors: TLS session lifetime {config.get('tls_session_lifetime', 'default')}, "
             f"spare connections {'on' if config.get('spare_connections') else 'off'}"]
    for key, label in (("setup", "set-up probes"), ("bringup", "bring-up")):
        checks = (report.get(key) or {}).get("interceptor", {}).get("checks")
        if checks:
            lines.append(f"checks, {label}: {describe_checks(checks)}")
    return lines


def render(report: dict, markdown: bool) -> None:
    rows = table_rows(report)
    for line in checks_lines(report):
        click.echo(line)
    if markdown:
        click.echo("| " + " | ".join(HEADERS) + " |")
        click.echo("|---|---|" + "---:|" * (len(HEADERS) - 2))
        for row in rows:
            click.echo("| " + " | ".join(row) + " |")
        click.echo(f"\n{targets_title(report)}\n")
        if report.get("quick"):
            click.echo("| target | measured |\n|---|---:|")
            for t in report["targets"]:
                click.echo(f"| {t['target']} | {_target_value(t)} |")
        else:
            click.echo("| target | measured | met |\n|---|---:|---|")
            for t in report["targets"]:
                click.echo(f"| {t['target']} | {_target_value(t)} | {'yes' if t['met'] else 'NO'} |")
        return
    from rich.console import Console
    from rich.table import Table

    console = for_logs(Console())
    table = Table(title="ROS 1 through cryptoros interceptors vs stunnel4 vs plain (loopback, one run)")
    for i, h in enumerate(HEADERS):
        table.add_column(h, justify="left" if i < 2 else "right")
    for row in rows:
        table.add_row(*row)
    console.print(table)
    console.print(targets_table(report))


def targets_table(report: dict):
    """The Targets table; after ``--quick`` without its verdict column (a verdict on a
    run this short would be noise)."""
    from rich.table import Table

    quick = report.get("quick")
    title = targets_title(report)
    targets = Table(title=title, min_width=len(title))  # the heading stays one line
    targets.add_column("target")
    targets.add_column("measured", justify="right")
    if not quick:
        targets.add_column("met")
    for t in report["targets"]:
        verdict = [] if quick else ["[green]yes[/]" if t["met"] else "[red]NO[/]"]
        targets.add_row(t["target"], _target_value(t), *verdict)
    return targets


def targets_title(report: dict) -> str:
    """The Targets table's heading: where the targets come from and, after ``--quick``,
    that the run was too short to judge them."""
    source = "Targets (issues 16 and 35, docs/performance.md)"
    if report.get("quick"):
        return f"{source}: indicative only, a --quick run is too short to judge them"
    return source


def _target_value(t: dict) -> str:
    m = t.get("measured")
    if m is None:
        return "-"
    text = {"x": f"{m:.2f}x", "us": f"{m:+,.0f} us", "B": f"{m:+,.0f} B", "%": f"{m:+.2f} %",
            "ms": f"{m:.2f} ms"}[t["unit"]]
    if "limit" in t and t["unit"] == "us":
        text += f" (stunnel {t['limit']:+,.0f} us)"
    if "limit" in t and t["unit"] == "ms":
        text += f" (stunnel {t['limit']:.2f} ms)"
    return text


# ============================================================ command


@click.command()
@click.option("--quick", is_flag=True, help="Fewer messages, 5 set-up probes, the paper's experiment for N=100 only.")
@click.option("--messages", type=int, default=None,
              help="Messages per throughput/latency row (default: 2,000 latency, 50,000 small, 3,000 x 80 KB, 400 x 1 MB).")
@click.option("--paper", "paper_counts", default=None,
              help="Comma-separated N for the paper's experiment (default 100,250,500; --quick: 100; 0: skip).")
@click.option("--paper-repeat", type=int, default=None, help="Repetitions per N and variant (default 4; --quick: 1).")
@click.option("--setup-probes", type=int, default=None, help="Connection set-ups timed per transport (default 20).")
@click.option("--bringup-subscribers", type=click.IntRange(1, 500), default=50, show_default=True,
              help="Subscribers connecting at once in the bring-up row.")
@click.option("--bringup-runs", type=click.IntRange(0, 50), default=None,
              help="Bring-ups per transport, median reported (default 3; --quick: 1; 0: skip).")
@click.option("--launch-nodes", type=click.IntRange(0, 200), default=None,
              help="Stock rostopic nodes in the launch-file bring-up row (default 30; --quick: 4; 0: skip).")
@click.option("--only", type=click.Choice(IMPLS), default=None, help="Run one node client only.")
@click.option("--no-throughput", is_flag=True, help="Skip the latency and throughput rows.")
@click.option("--spares/--no-spares", default=None,
              help="The interceptors keep spare connections per peer or not ([limits] spare_connections; "
                   "default: the interceptor's, on).")
@click.option("--tls-session-lifetime", type=click.FloatRange(0, 7200), default=None,
              help="The interceptors' [limits] tls_session_lifetime (0: a full TLS handshake on every stream; "
                   "default: the interceptor's, 300 s).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), default=None, help="Also write the results here.")
@click.option("--markdown", is_flag=True, help="Print the tables as Markdown (for the README).")
@click.option("--plots", "plots_dir", type=click.Path(file_okay=False), default=None,
              help="Also draw latency.png (one-way latency at 1 kHz, per node client) and setup.png (TCPROS set-up "
                   "and service call) here: each sample's distribution for plain, interceptor and stunnel.")
@click.option("--keep", is_flag=True, help="Keep the work directory (logs, pcaps, configs) and print its path.")
def interceptor(quick: bool, messages: int | None, paper_counts: str | None, paper_repeat: int | None,
                setup_probes: int | None, bringup_subscribers: int, bringup_runs: int | None,
                launch_nodes: int | None, only: str | None,
                no_throughput: bool, spares: bool | None, tls_session_lifetime: float | None, json_path: str | None, markdown: bool,
                plots_dir: str | None, keep: bool) -> None:
    """Plain ROS 1, our interceptors and stunnel4 side by side, rospy and our node client."""
    if not Path(SYS_PY).exists() or subprocess.run([SYS_PY, "-c", "import rospy"], capture_output=True).returncode:
        raise click.ClickException("rospy is not installed for /usr/bin/python3 (scripts/install-system-parts)")
    for binary in ("rosmaster", "tcpdump"):
        if shutil.which(binary) is None:
            raise click.ClickException(f"{binary} is not installed (scripts/install-system-parts)")
    if not (shutil.which("stunnel4") or shutil.which("stunnel")):
        raise click.ClickException("stunnel4 is not installed (scripts/install-system-parts)")
    if paper_counts is None:
        counts = [100] if quick else [100, 250, 500]
    else:
        counts = [int(x) for x in paper_counts.split(",") if int(x) > 0]
    reps = paper_repeat or (1 if quick else 4)
    probes = setup_probes or (5 if quick else 20)
    bringups = bringup_runs if bringup_runs is not None else (1 if quick else 3)
    launch_count = launch_nodes if launch_nodes is not None else (4 if quick else 30)
    scale = 0.2 if quick else 1.0

    def n(default: int) -> int:
        return messages if messages else max(10, int(default * scale))

    modes = [
        Mode("latency", "one-way latency at 1 kHz", "latency", n(2000)),
        Mode("small", "std_msgs/String throughput", "small", n(50_000)),
        Mode("image80k", "sensor_msgs/Image 80 KB", "image", n(3000), 80_000),
        Mode("image1m", "sensor_msgs/Image 1 MB", "image", n(400), 1_000_000),
    ]
    impls = [i for i in IMPLS if only in (None, i)]
    started = time.monotonic()

    def progress(message: str) -> None:
        click.echo(f"[{time.monotonic() - started:6.1f} s] {message}", err=True)

    workdir = Path(tempfile.mkdtemp(prefix="cryptoros-bench-icpt-"))
    results: dict = {"config": {"messages": {m.key: m.n for m in modes}, "paper_counts": counts, "paper_repeat": reps,
                                "setup_probes": probes, "bringup": {"subscribers": bringup_subscribers,
                                                                    "runs": bringups, "launch_nodes": launch_count},
                                "cpus": os.cpu_count(),
                                "tls_session_lifetime": ("300 s (default)" if tls_session_lifetime is None else
                                                         f"{tls_session_lifetime:g} s" if tls_session_lifetime else
                                                         "0 (off: a full handshake on every stream)"),
                                "spare_connections": "on (default)" if spares is None else spares,
                                "max_messages_per_second": "0 (unthrottled)"}}
    try:
        limits: dict[str, float | bool] = dict(UNTHROTTLED)  # throughput rows: no per-peer rate
        if tls_session_lifetime is not None:
            limits["tls_session_lifetime"] = tls_session_lifetime
        if spares is not None:
            limits["spare_connections"] = spares
        with lab_network(workdir, _policy(), hosts=BENCH_HOSTS, extra_certs=[("stunnel_a", HOSTS["robot_a"]),
                                                            ("stunnel_b", "127.0.0.1")], progress=progress,
                         metrics=True, limits=limits) as net:
            progress("network up")
            results["setup"] = measure_setup(net, probes, workdir, progress)
            if bringups:
                from cryptoros.bench.bringup import measure_bringup, measure_launch

                results["bringup"] = measure_bringup(net, bringup_subscribers, bringups, workdir, progress)
                if launch_count:
                    results["launch"] = measure_launch(net, launch_count, bringups, workdir, progress)
            tp: dict = {}
            for impl in impls if not no_throughput else ():
                for transport in TRANSPORTS:
                    tp.setdefault(impl, {})[transport] = run_pair(net, impl, transport, modes, workdir, progress)
            results["throughput"] = tp
            if counts:
                results["paper"] = paper_experiment(net, counts, reps, workdir, progress)
    except (NetworkError, CaptureError) as exc:
        raise click.ClickException(f"{exc} (work directory {workdir})") from None
    finally:
        if keep:
            click.echo(f"work directory kept: {workdir}", err=True)
        else:
            shutil.rmtree(workdir, ignore_errors=True)
    report = build_report(results)
    report["elapsed_s"] = time.monotonic() - started
    report["quick"] = quick
    if json_path:
        write_output(json_path, json.dumps(report, indent=2))
    render(report, markdown)
    click.echo(_legend(), err=False)
    if plots_dir:
        for path in write_plots(results, Path(plots_dir)):
            click.echo(f"plot: {path}", err=True)


TRANSPORT_STYLE = {"plain": ("plain ROS 1", "-"), "interceptor": ("cryptoros interceptors", "-"),
                   "stunnel": ("stunnel4", "--")}


def write_plots(results: dict, out: Path) -> list[Path]:
    """Empirical distributions (the share of samples at or below x) of what the run
    timed: latency.png, the one-way latency at 1 kHz per node client (when the
    throughput rows ran); setup.png, the TCPROS set-up and the service call."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []

    def ecdf(ax, samples: list[float], transport: str) -> None:
        label, style = TRANSPORT_STYLE[transport]
        xs = sorted(samples)
        if not xs:
            return
        ys = [(i + 1) / len(xs) for i in range(len(xs))]
        ax.step(xs, ys, where="post", linestyle=style, label=f"{label} (median {statistics.median(xs):,.3g})")

    def log_x(ax, label: str) -> None:
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
        plain_numbers = matplotlib.ticker.FuncFormatter(lambda v, _pos: f"{v:g}")
        ax.xaxis.set_major_formatter(plain_numbers)
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel(label)

    def panel(ax, samples_by_transport: dict[str, list[float]], xlabel: str, ylabel: str, title: str) -> None:
        for transport in TRANSPORTS:
            ecdf(ax, samples_by_transport.get(transport, []), transport)
        log_x(ax, xlabel)
        ax.set_ylabel(ylabel)
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3, which="both")
        ax.legend(loc="lower right", fontsize=8)

    def save(fig, name: str) -> None:
        fig.tight_layout()
        written.append(out / name)
        fig.savefig(written[-1], dpi=120)
        plt.close(fig)

    tp = results.get("throughput") or {}
    impls = [impl for impl in IMPLS if any(tp.get(impl, {}).get(t, {}).get("latency", {}).get("samples_us")
                                           for t in TRANSPORTS)]
    if impls:
        fig, axes = plt.subplots(1, len(impls), figsize=(5.5 * len(impls), 4), squeeze=False)
        for ax, impl in zip(axes[0], impls):
            panel(ax, {t: tp[impl].get(t, {}).get("latency", {}).get("samples_us", []) for t in TRANSPORTS},
                  "one-way latency (us), log scale", "share of messages at or below",
                  f"1 kHz, {'rospy' if impl == 'rospy' else 'our node client'}")
        save(fig, "latency.png")
    setup = results.get("setup") or {}
    if setup:
        fig, axes = plt.subplots(1, 2, figsize=(11, 4), squeeze=False)
        for ax, (key, title) in zip(axes[0], (("tcpros_connect", "TCPROS set-up: connect to the publisher's header"),
                                             ("service_call", "service call: connect + request + reply"))):
            panel(ax, {t: setup.get(t, {}).get(key, {}).get("samples_ms", []) for t in TRANSPORTS},
                  "ms, log scale", "share of probes at or below", title)
        save(fig, "setup.png")
    return written


def _legend() -> str:
    return (
        "\nplain: straight to rosmaster and the talker. interceptor: talker on A, listener on B, everything through\n"
        "A's and B's interceptors (mutual TLS + token; header checked, then bytes pumped). stunnel: a fixed chain,\n"
        "talker's TCPROS port <- stunnel4 server <- stunnel4 client <- listener (XML-RPC plain). 'probe' rows: an\n"
        "in-process subscriber against an idle publisher of our node client; bytes counted by tcpdump on lo between\n"
        "the two hosts (frames as Wireshark counts them, TCP payload in brackets); the TCPROS row is from connect\n"
        "to the publisher's header reply (no message yet); a subscription adds the requestTopic call. stunnel's\n"
        "client caches TLS sessions, so its set-ups after the first are resumed handshakes (no certificates); so\n"
        "do the interceptors (unless --tls-session-lifetime 0), which also keep spare connections per peer\n"
        "(unless --no-spares): the lines above the table say which handshakes and checks ran.\n"
        "The interceptors run with [limits] max_messages_per_second = 0 (no per-peer rate; the default would\n"
        "throttle the unthrottled sender of the throughput rows).\n"
        "bring-up: N subscriber nodes of our node client start at once in one process (register, requestTopic,\n"
        "TCPROS) against a latched publisher; time from the start until the last one received its message.\n"
        "launch file: roslaunch of N stock `rostopic echo -n 1` nodes on host B against the latched publisher,\n"
        "timed from its start until it exits (every node received the message and finished).\n"
        "paper experiment: the listener timed from launch to exit (as with `time`), mean of the repetitions."
    )


__all__ = ["interceptor", "build_report", "flows"]
