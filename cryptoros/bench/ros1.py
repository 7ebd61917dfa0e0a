"""``cryptoros bench ros1``: our ROS 1 transport against rospy's, side by side.

Each row runs a sender process and a receiver process, twice: rospy to rospy (under
``/usr/bin/python3``, Debian's ROS 1) and cryptoros to cryptoros (this venv, uvloop),
both registered with the same master (Debian's ``rosmaster`` when installed, else
``cryptoros master``). Rows:

* small ``std_msgs/String`` messages: received messages per second, publisher
  unthrottled (rospy ``queue_size=None``; ours waits on socket backpressure);
* one-way latency at 1 kHz (p50/p99, sender stamps ``CLOCK_MONOTONIC`` in the message
  right before publishing; both senders pace the same way: ``time.sleep`` for the rest
  of the period, as rospy does; ours then lets its loop run its callbacks);
* ``sensor_msgs/Image`` of 80 KB and 1 MB: MB/s received.

Both sides serialize every message on send and deserialize it on receipt. Figures
are printed, never asserted.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import click

from cryptoros.lab.processes import free_port, stop

SYS_PY = "/usr/bin/python3"
TOPIC = "/bench"

ROSPY_WORKER = r"""
import json, sys, threading, time
import rospy
from std_msgs.msg import String
from sensor_msgs.msg import Image

role, mode, n, size = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
cls = Image if mode == "image" else String
if role == "recv":
    rospy.init_node("bench_recv_rospy", disable_signals=True)
    st = {"n": 0, "t0": 0.0, "t1": 0.0, "bytes": 0, "lat": []}
    done = threading.Event()
    def cb(m):
        now = time.monotonic_ns()
        if mode == "latency":
            st["lat"].append(now - int(m.data))
        elif mode == "image":
            st["bytes"] += len(m.data)
        if st["n"] == 0:
            st["t0"] = now
        st["t1"] = now
        st["n"] += 1
        if st["n"] >= n:
            done.set()
    rospy.Subscriber("/bench", cls, cb, tcp_nodelay=True, buff_size=1 << 24)
    print("READY", flush=True)
    last, deadline = -1, time.monotonic() + 120
    while not done.wait(3.0) and time.monotonic() < deadline:
        if st["n"] == last and st["n"] > 0:
            break
        last = st["n"]
    print("RESULT " + json.dumps(st), flush=True)
else:
    rospy.init_node("bench_send_rospy", disable_signals=True)
    pub = rospy.Publisher("/bench", cls, queue_size=None, tcp_nodelay=True)
    deadline = time.monotonic() + 20
    while pub.get_num_connections() < 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.3)
    if mode == "latency":
        period = 0.001
        nxt = time.monotonic()
        for i in range(n):
            pub.publish(String(data=str(time.monotonic_ns())))
            nxt += period
            d = nxt - time.monotonic()
            if d > 0:
                time.sleep(d)
    elif mode == "small":
        for i in range(n):
            pub.publish(String(data="hello world %d" % i))
    else:
        payload = bytes(size)
        for i in range(n):
            pub.publish(Image(height=1, width=size, encoding="mono8", step=size, data=payload))
    print("SENT", flush=True)
    time.sleep(2.0)
"""


def _our_worker() -> None:
    """Entry point of our sender/receiver processes (argv: role mode n size master)."""
    from cryptoros.memory import tune_malloc
    from cryptoros.ros1.node import Node, install_uvloop

    role, mode, n, size, master = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
    typename = "sensor_msgs/Image" if mode == "image" else "std_msgs/String"
    install_uvloop()
    tune_malloc()

    async def recv() -> None:
        st = {"n": 0, "t0": 0, "t1": 0, "bytes": 0, "lat": []}
        done = asyncio.Event()
        clock = time.monotonic_ns

        def cb(m) -> None:
            if record_message(st, m.data, mode, clock()) >= n:
                done.set()

        async with Node("/bench_recv_ours", master) as node:
            await node.subscribe(TOPIC, typename, cb, tcp_nodelay=True)
            print("READY", flush=True)
            last, deadline = -1, time.monotonic() + 120
            while time.monotonic() < deadline:
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(done.wait(), 3.0)
                if done.is_set() or (st["n"] == last and st["n"] > 0):
                    break
                last = st["n"]
            print("RESULT " + json.dumps(st), flush=True)

    async def send() -> None:
        async with Node("/bench_send_ours", master) as node:
            pub = await node.advertise(TOPIC, typename)
            await pub.wait_for_subscribers(1, 20)
            await asyncio.sleep(0.3)
            await publish_workload(mode, n, size, pub, pub)
            print("SENT", flush=True)
            await asyncio.sleep(2.0)

    asyncio.run(recv() if role == "recv" else send())


def record_message(st: dict, data, mode: str, now: int) -> int:
    """Account one message our receiver got (latency sample, bytes, first and last
    arrival) in ``st``; returns how many it has got. Shared by ``bench ros1`` and
    ``bench interceptor``; the rospy receiver script keeps its own copy (it runs
    under Debian's python, which cannot import cryptoros)."""
    if mode == "latency":
        st["lat"].append(now - int(data))
    elif mode == "image":
        st["bytes"] += len(data)
    if st["n"] == 0:
        st["t0"] = now
    st["t1"] = now
    st["n"] += 1
    return st["n"]


async def publish_workload(mode: str, n: int, size: int, pub_str, pub_img) -> None:
    """What our sender publishes for one benchmark row (shared by ``bench ros1`` and
    ``bench interceptor``): ``latency`` stamps CLOCK_MONOTONIC into a String at 1 kHz,
    ``small`` sends strings unthrottled (with backpressure), ``image`` sends
    ``sensor_msgs/Image`` of ``size`` bytes."""
    from cryptoros.ros1 import msgs

    String = msgs.msg_class("std_msgs/String")
    if mode == "latency":
        nxt = time.monotonic()
        for _ in range(n):
            pub_str.publish(String(data=str(time.monotonic_ns())))
            nxt += 0.001
            d = nxt - time.monotonic()
            if d > 0:
                # the same pacing as the rospy sender: the OS sleeps the rest of the
                # period (time.sleep, a high-resolution timer); asyncio.sleep would
                # round to libuv's 1 ms timer resolution and drift, then send in
                # bursts. The loop runs its callbacks right after.
                time.sleep(d)
            await asyncio.sleep(0)
    elif mode == "small":
        for i in range(n):
            pub_str.publish(String(data="hello world %d" % i))
            if i & 255 == 255:
                await asyncio.sleep(0)
                await pub_str.wait_writable()
    else:
        import numpy as np

        Image = msgs.msg_class("sensor_msgs/Image")
        Header = msgs.msg_class("std_msgs/Header")
        Time = msgs.typestore().types["builtin_interfaces/msg/Time"]
        payload = np.zeros(size, dtype=np.uint8)
        for _ in range(n):
            pub_img.publish(Image(
                header=Header(seq=0, stamp=Time(sec=0, nanosec=0), frame_id=""),
                height=1, width=size, encoding="mono8", is_bigendian=0, step=size, data=payload,
            ))
            await asyncio.sleep(0)
            await pub_img.wait_writable()


def _wait_port(port: int, timeout: float = 15) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.5):
            return
        time.sleep(0.05)
    raise click.ClickException(f"master did not listen on {port}")


def _run_pair(impl: str, mode: str, n: int, size: int, env: dict[str, str], master: str) -> dict:
    if impl == "rospy":
        cmd = [SYS_PY, "-c", ROSPY_WORKER]
        extra: list[str] = []
    else:
        cmd = [sys.executable, "-c", "from cryptoros.bench.ros1 import _our_worker; _our_worker()"]
        extra = [master]
    recv = subprocess.Popen([*cmd, "recv", mode, str(n), str(size), *extra], env=env, stdout=subprocess.PIPE, text=True)
    send = None
    try:
        line = recv.stdout.readline()
        if not line.startswith("READY"):
            raise click.ClickException(f"{impl} receiver failed to start: {line!r}")
        send = subprocess.Popen(
            [*cmd, "send", mode, str(n), str(size), *extra], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        result = None
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline:
            line = recv.stdout.readline()
            if not line:
                break
            if line.startswith("RESULT "):
                result = json.loads(line[7:])
                break
        if result is None:
            raise click.ClickException(f"{impl} receiver gave no result for {mode}")
        return result
    finally:
        if send is not None:
            stop(send)
        stop(recv)


def _summarize(mode: str, n: int, r: dict) -> dict:
    got = r["n"]
    span = max(r["t1"] - r["t0"], 1) / 1e9
    out: dict = {"received": got, "sent": n}
    if mode == "small":
        out["msg_per_s"] = (got - 1) / span if got > 1 else 0.0
    elif mode == "latency":
        lat = sorted(r["lat"])
        if lat:
            out["p50_us"] = lat[len(lat) // 2] / 1e3
            out["p99_us"] = lat[min(len(lat) - 1, int(len(lat) * 0.99))] / 1e3
    else:
        per = r["bytes"] / got if got else 0
        out["mb_per_s"] = (r["bytes"] - per) / span / 1e6 if got > 1 else 0.0
    return out


@click.command()
@click.option("--small", "n_small", default=50_000, show_default=True, help="Small messages per throughput run.")
@click.option("--latency", "n_latency", default=2_000, show_default=True, help="Messages at 1 kHz for latency.")
@click.option("--image80k", "n_80k", default=3_000, show_default=True, help="80 KB images per run.")
@click.option("--image1m", "n_1m", default=400, show_default=True, help="1 MB images per run.")
@click.option("--only", type=click.Choice(["rospy", "ours"]), default=None, help="Run one side only.")
@click.option("--json", "as_json", is_flag=True, help="Print the results as JSON.")
def ros1(n_small: int, n_latency: int, n_80k: int, n_1m: int, only: str | None, as_json: bool) -> None:
    """Our publisher to our subscriber against rospy to rospy, in one run."""
    have_ros = Path(SYS_PY).exists() and subprocess.run(
        [SYS_PY, "-c", "import rospy"], capture_output=True
    ).returncode == 0
    impls = [i for i in ("rospy", "ours") if (only is None or only == i) and (i != "rospy" or have_ros)]
    if not have_ros and only != "ours":
        click.echo("rospy is not installed: running our side only (scripts/install-system-parts)", err=True)
    port = free_port()
    master = f"http://127.0.0.1:{port}/"
    home = tempfile.mkdtemp(prefix="cryptoros-bench-")
    env = {k: v for k, v in os.environ.items() if not k.startswith("ROS_")}
    env.update(ROS_MASTER_URI=master, ROS_IP="127.0.0.1", ROS_HOME=home, PYTHONUNBUFFERED="1")
    rosmaster = shutil.which("rosmaster")
    if rosmaster:
        master_cmd = [rosmaster, "--core", "-p", str(port)]
        master_name = "rosmaster"
    else:
        master_cmd = [sys.executable, "-m", "cryptoros.cli", "master", "--port", str(port)]
        master_name = "cryptoros master"
    mproc = subprocess.Popen(master_cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    rows = [
        ("small", "std_msgs/String throughput", n_small, 0),
        ("latency", "one-way latency at 1 kHz", n_latency, 0),
        ("image", "sensor_msgs/Image 80 KB", n_80k, 80_000),
        ("image", "sensor_msgs/Image 1 MB", n_1m, 1_000_000),
    ]
    results: dict[str, dict[str, dict]] = {}
    try:
        _wait_port(port)
        for mode, label, n, size in rows:
            for impl in impls:
                raw = _run_pair(impl, mode, n, size, env, master)
                results.setdefault(label, {})[impl] = _summarize(mode, n, raw)
                if not as_json:
                    click.echo(f"  {label:32s} {impl:6s} {results[label][impl]}", err=True)
    finally:
        stop(mproc)
        shutil.rmtree(home, ignore_errors=True)
    if as_json:
        click.echo(json.dumps({"master": master_name, "results": results}, indent=2))
        return
    click.echo(f"\nROS 1 transport, loopback, master: {master_name}\n")
    click.echo("| measure | rospy -> rospy | cryptoros -> cryptoros | ratio |")
    click.echo("|---|---:|---:|---:|")

    def line(label: str, key: str, unit: str, fmt: str, higher_better: bool = True) -> None:
        r = results.get(label, {})
        a = r.get("rospy", {}).get(key)
        b = r.get("ours", {}).get(key)
        ratio = ""
        if a and b:
            ratio = f"{(b / a if higher_better else a / b):.2f}x"
        fa = (fmt.format(a) + unit) if a is not None else "-"
        fb = (fmt.format(b) + unit) if b is not None else "-"
        lost = ""
        for impl in ("rospy", "ours"):
            x = r.get(impl)
            if x and x["received"] != x["sent"]:
                lost += f" ({impl} got {x['received']}/{x['sent']})"
        click.echo(f"| {label} {key.split('_')[0] if key.startswith('p') else ''}{lost} | {fa} | {fb} | {ratio} |")

    line("std_msgs/String throughput", "msg_per_s", " msg/s", "{:,.0f}")
    line("one-way latency at 1 kHz", "p50_us", " us", "{:,.0f}", higher_better=False)
    line("one-way latency at 1 kHz", "p99_us", " us", "{:,.0f}", higher_better=False)
    line("sensor_msgs/Image 80 KB", "mb_per_s", " MB/s", "{:,.0f}")
    line("sensor_msgs/Image 1 MB", "mb_per_s", " MB/s", "{:,.0f}")
    click.echo("\nratio > 1 means cryptoros is better (faster, or lower latency).")
