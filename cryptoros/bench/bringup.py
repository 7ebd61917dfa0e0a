"""The bring-up rows of ``cryptoros bench interceptor``: a robot starting its nodes,
through the interceptors against plain ROS 1 and the stunnel4 chain.

Two rows, each timed from the start until every subscriber received a latched message:

``subscribers``  N subscriber nodes of our node client start at once in one process
                 (registerSubscriber, requestTopic, TCPROS connection, the message): the
                 relays' own cost, since the nodes themselves are cheap.
``launch``       a launch file of N stock ``rostopic echo -n 1`` nodes started by Debian's
                 ``roslaunch`` (a process per node, the way a robot starts), timed from
                 the start of ``roslaunch`` until it exits because every node has
                 received its message and finished.

Plain and stunnel run against rosmaster with XML-RPC plain (stunnel cannot follow ROS's
dynamic ports): in the subscriber row the subscribers' TCPROS connect is redirected to
the stunnel client; in the launch row the publisher names the stunnel client in its
requestTopic answer (:attr:`cryptoros.ros1.node.Node.tcpros_endpoint`), so stock
subscribers follow it unmodified. Interceptor: the publisher on host A, the subscribers
(and ``roslaunch``) on host B, every call and stream through the interceptors. Both rows
also report the relays' CPU seconds: the three interceptors' (master, A, B) against the
two stunnel4 processes'.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import statistics
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from cryptoros.bench.chain import (TRANSPORTS, Proc, checks_delta, describe_checks, interceptor_checks,
                                   settled_checks, stunnel_chain, worker_cmd)
from cryptoros.lab.network import Network, cpu_seconds, free_port

#: roslaunch and the stock nodes it starts run on Debian's Python (rospy), whatever
#: interpreter runs the bench
SYSTEM_PATH = "/usr/bin:/bin"


def _via_node(via: tuple[str, int]):
    """Our node client whose TCPROS connections go to ``via`` (the stunnel client's
    accept port) whatever requestTopic answers: the stunnel chain, as BENCH_VIA does
    for the worker processes, but for these nodes only."""
    from cryptoros.ros1.node import Node

    class ViaNode(Node):
        async def call_api(self, uri, method, *params):
            reply = await super().call_api(uri, method, *params)
            if method == "requestTopic" and isinstance(reply, list) and len(reply) == 3:
                reply = [reply[0], via[0], via[1]]
            return reply

    return ViaNode


async def _subscribers_once(master_uri: str, count: int, tag: str, via: tuple[str, int] | None = None,
                            timeout: float = 60.0) -> dict:
    """``count`` subscriber nodes of our node client start at once in this process, each
    registering with ``master_uri`` and subscribing to the latched /bench_str: seconds
    from the start until each received the latched message."""
    from cryptoros.ros1.node import Node

    cls = Node if via is None else _via_node(via)
    nodes: list = []
    received: list[float | None] = [None] * count
    t0 = time.perf_counter()

    async def one(i: int) -> None:
        got = asyncio.Event()

        def on_msg(_msg, i=i) -> None:
            if received[i] is None:
                received[i] = time.perf_counter() - t0
            got.set()

        node = cls(f"/bench_bringup_{tag}_{i}", master_uri)
        nodes.append(node)
        await node.start()
        await node.subscribe("/bench_str", "std_msgs/String", on_msg)
        await got.wait()

    outcomes = await asyncio.gather(*(asyncio.wait_for(one(i), timeout) for i in range(count)), return_exceptions=True)
    await asyncio.gather(*(node.close() for node in nodes), return_exceptions=True)
    times = [t for t in received if t is not None]
    errors = sorted({f"{type(o).__name__}: {o}"[:200] for o in outcomes if isinstance(o, BaseException)})
    return {"all_s": max(times) if len(times) == count else None, "first_s": min(times) if times else None,
            "received": len(times), "errors": errors}


def launch_file(path: Path, count: int) -> Path:
    """A launch file of ``count`` stock ``rostopic echo -n 1 /bench_str`` nodes."""
    nodes = [f'  <node pkg="rostopic" type="rostopic" name="bench_echo_{i}" args="echo -n 1 /bench_str"/>'
             for i in range(count)]
    path.write_text("\n".join(["<launch>", *nodes, "</launch>"]) + "\n")
    return path


def _launch_once(file: Path, count: int, env: dict[str, str], log: Path, timeout: float = 120.0) -> dict:
    """Run ``roslaunch file`` (its master must be up: roslaunch would otherwise start its
    own) until it exits: seconds from the start, and how many nodes finished cleanly
    (``rostopic echo -n 1`` exits 0 once it printed the message)."""
    t0 = time.perf_counter()
    with log.open("a") as out:
        proc = subprocess.Popen(["roslaunch", str(file)], env={**env, "PATH": SYSTEM_PATH},
                                stdout=subprocess.PIPE, stderr=out, text=True)
        try:
            stdout, _ = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.terminate()
            try:
                stdout, _ = proc.communicate(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                stdout, _ = proc.communicate()
            out.write(stdout)
            return {"all_s": None, "first_s": None, "received": stdout.count("process has finished cleanly"),
                    "errors": [f"roslaunch still running after {timeout:.0f} s"]}
        out.write(stdout)
    elapsed = time.perf_counter() - t0
    finished = stdout.count("process has finished cleanly")
    errors = [] if finished == count else [f"{count - finished} of {count} nodes did not finish cleanly "
                                           f"(roslaunch exit {proc.returncode}; log {log})"]
    return {"all_s": elapsed if finished == count else None, "first_s": None, "received": finished,
            "errors": errors}


@contextlib.contextmanager
def _latched(net: Network, host: str | None, workdir: Path, tag: str, **extra: str) -> Iterator[Proc]:
    """The latched /bench_str publisher (our node client) on ``host`` (None: plain,
    straight to rosmaster), up until the block ends."""
    pub = Proc(f"latched talker ({tag})", worker_cmd("ours", "latched"), net.ros_env(host, **extra),
               workdir / f"latched-{tag}.log")
    try:
        pub.expect("URI ", 30)
        yield pub
    finally:
        pub.close()


def _cpu(pids: list[int]) -> float:
    """CPU seconds (user + system) the processes ``pids`` have used so far."""
    return sum(cpu_seconds(pid) or 0.0 for pid in pids)


def _short(r: dict, count: int, what: str) -> str:
    if r["all_s"] is not None:
        first = f" (first {r['first_s'] * 1e3:,.0f} ms)" if r["first_s"] is not None else ""
        return f"all {count} {what} after {r['all_s'] * 1e3:,.0f} ms{first}"
    return f"{r['received']}/{count} {what}; {'; '.join(r['errors'][:2])}"


def _summary(raw: dict[str, list[dict]], relay_cpu: dict[str, list[float]]) -> dict:
    result: dict = {}
    for transport, rows in raw.items():
        complete = [r["all_s"] * 1e3 for r in rows if r["all_s"] is not None]
        result[transport] = {
            "all_ms": [None if r["all_s"] is None else r["all_s"] * 1e3 for r in rows],
            "first_ms": [None if r["first_s"] is None else r["first_s"] * 1e3 for r in rows],
            "received": [r["received"] for r in rows],
            "median_ms": statistics.median(complete) if complete else None,
            "errors": sorted({e for r in rows for e in r["errors"]}),
        }
        if transport in relay_cpu:  # the relays' CPU seconds per bring-up (from start to close)
            result[transport]["relay_cpu_s"] = relay_cpu[transport]
            result[transport]["relay_cpu_median_s"] = (statistics.median(relay_cpu[transport])
                                                       if relay_cpu[transport] else None)
    return result


def measure_bringup(net: Network, count: int, runs: int, workdir: Path, progress: Callable[[str], None]) -> dict:
    """The subscriber row: ``count`` subscribers of our node client at once, ``runs``
    times per transport (median reported), plain and stunnel taking turns on one talker."""
    raw: dict[str, list[dict]] = {t: [] for t in TRANSPORTS}
    relay_cpu: dict[str, list[float]] = {"stunnel": [], "interceptor": []}
    talker_port = free_port()
    stunnel_pids: list[int] = []
    interceptor_pids = [net.hosts[h].proc.pid for h in ("master", "robot_a", "robot_b") if net.hosts[h].proc]
    with _latched(net, None, workdir, "plain", BENCH_TCPROS_PORT=str(talker_port)), \
            stunnel_chain(net, talker_port, workdir, "bringup", stunnel_pids) as (client_port, _server_port):
        for run in range(runs):
            for transport in (("plain", "stunnel") if run % 2 == 0 else ("stunnel", "plain")):
                via = ("127.0.0.1", client_port) if transport == "stunnel" else None
                before = _cpu(stunnel_pids)
                raw[transport].append(asyncio.run(_subscribers_once(net.rosmaster_uri, count, f"{transport}{run}", via)))
                if transport == "stunnel":
                    relay_cpu["stunnel"].append(_cpu(stunnel_pids) - before)
                cpu = (f", stunnel4's CPU {relay_cpu['stunnel'][-1] * 1e3:,.0f} ms"
                       if transport == "stunnel" else "")
                progress(f"bring-up {transport:11s} run {run + 1}: {_short(raw[transport][-1], count, 'received')}{cpu}")
    checks_before = interceptor_checks(net)
    with _latched(net, "robot_a", workdir, "a"):
        for run in range(runs):
            before = _cpu(interceptor_pids)
            raw["interceptor"].append(asyncio.run(_subscribers_once(net.hosts["robot_b"].master_uri, count, f"icpt{run}")))
            relay_cpu["interceptor"].append(_cpu(interceptor_pids) - before)
            progress(f"bring-up interceptor run {run + 1}: {_short(raw['interceptor'][-1], count, 'received')}, "
                     f"the interceptors' CPU {relay_cpu['interceptor'][-1] * 1e3:,.0f} ms")
            time.sleep(2.0)  # the new-stream budget per peer (50/s, burst 100) refills between runs
    result = {"subscribers": count, "runs": runs, **_summary(raw, relay_cpu)}
    result["interceptor"]["checks"] = checks_delta(checks_before, settled_checks(net))
    progress(f"bring-up interceptor checks: {describe_checks(result['interceptor']['checks'])}")
    return result


def measure_launch(net: Network, count: int, runs: int, workdir: Path, progress: Callable[[str], None]) -> dict:
    """The launch row: ``roslaunch`` of ``count`` stock ``rostopic echo -n 1`` nodes,
    ``runs`` times per transport (median reported). One publisher at a time (they share
    the topic): plain, stunnel (naming the stunnel client) and the interceptor's on A,
    in turn within each run."""
    file = launch_file(workdir / f"bringup-{count}.launch", count)
    raw: dict[str, list[dict]] = {t: [] for t in TRANSPORTS}
    relay_cpu: dict[str, list[float]] = {"stunnel": [], "interceptor": []}
    talker_port = free_port()
    stunnel_pids: list[int] = []
    interceptor_pids = [net.hosts[h].proc.pid for h in ("master", "robot_a", "robot_b") if net.hosts[h].proc]
    log = workdir / "roslaunch.log"
    with stunnel_chain(net, talker_port, workdir, "launch", stunnel_pids) as (client_port, _server_port):
        publishers = {
            "plain": (None, {"BENCH_TCPROS_PORT": str(talker_port)}, net.ros_env(None)),
            "stunnel": (None, {"BENCH_TCPROS_PORT": str(talker_port), "BENCH_ADVERTISE": f"127.0.0.1:{client_port}"},
                        net.ros_env(None)),
            "interceptor": ("robot_a", {}, net.ros_env("robot_b")),
        }
        for run in range(runs):
            order = TRANSPORTS if run % 2 == 0 else tuple(reversed(TRANSPORTS))
            for transport in order:
                host, extra, env = publishers[transport]
                pids = {"stunnel": stunnel_pids, "interceptor": interceptor_pids}.get(transport, [])
                with _latched(net, host, workdir, f"launch-{transport}", **extra):
                    before = _cpu(pids)
                    raw[transport].append(_launch_once(file, count, env, log))
                    if transport in relay_cpu:
                        relay_cpu[transport].append(_cpu(pids) - before)
                cpu = f", the relays' CPU {relay_cpu[transport][-1] * 1e3:,.0f} ms" if transport in relay_cpu else ""
                progress(f"launch {count} nodes, {transport:11s} run {run + 1}: "
                         f"{_short(raw[transport][-1], count, 'finished')}{cpu}")
    return {"nodes": count, "runs": runs, **_summary(raw, relay_cpu)}


def worker_endpoint() -> tuple[str, int] | None:
    """``BENCH_ADVERTISE`` (host:port) of a publisher worker: what its requestTopic
    answers name instead of its own TCPROS port (the stunnel client's accept)."""
    value = os.environ.get("BENCH_ADVERTISE")
    if not value:
        return None
    host, port = value.rsplit(":", 1)
    return host, int(port)
