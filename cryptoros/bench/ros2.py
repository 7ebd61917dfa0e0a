"""``cryptoros bench ros2``: rclpy to rclpy on one domain against the same through the
interceptor pair (robot A's domain -> interceptor A ==mTLS==> interceptor B -> robot
B's domain), in one run, printed side by side.

Needs the ROS 2 venv (``scripts/ros2-venv``; ``--python`` or ``CRYPTOROS_ROS2_PYTHON``
to point elsewhere). Builds its own PKI, registry, ``cryptoros-authz serve`` and two
``cryptoros-interceptor`` processes with the ``ros2`` role; every process is stopped
in a ``finally``.

Method (identical for both paths; see ``cryptoros/ros2/bench_node.py``): reliable +
KEEP_ALL on both ends, serialized messages, a warm-up handshake before the count starts,
a subscriber that only records (raw take loop on its own thread), rates over the
subscriber's receive window and counts of what it really received. The interceptors run
with ``[limits] max_messages_per_second = 0`` (no per-peer rate: the default would throttle
the unthrottled sender of the throughput rows).
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import tempfile
import time
from collections.abc import Iterator
from typing import Any
from pathlib import Path

import click

from cryptoros.lab.network import UNTHROTTLED, NetworkError, lab_network, clean_env, cpu_seconds, stop
from cryptoros.lab.policy import policy_yaml
from cryptoros.ros2 import default_ros2_python

NODE = Path(__file__).resolve().parent.parent / "ros2" / "bench_node.py"
HOSTS = {"robot_a": "127.0.0.2", "robot_b": "127.0.0.3"}
POLICY = policy_yaml({
    "robot_a": {"publish": [("/bench_pub", "/bench", "std_msgs/msg/String"),
                            ("/bench_pub", "/bench", "sensor_msgs/msg/Image")]},
    "robot_b": {"subscribe": [("*", "/bench", "std_msgs/msg/String"), ("*", "/bench", "sensor_msgs/msg/Image")]},
})


def _ros_env(domain: int) -> dict[str, str]:
    """A robot's rclpy node: its domain and the localhost-only profile (docs/ros2.md)."""
    from cryptoros.ros2.profile import localhost_env

    env = {k: v for k, v in clean_env().items() if not k.startswith(("_ROS_WHEELS", "RMW_"))}
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    return localhost_env(env)


#: the processes whose CPU is accounted per row (pub and sub report their own)
PROCESSES = ("publisher", "interceptor_a", "bridge_a", "interceptor_b", "bridge_b", "subscriber")


def children(pid: int) -> list[int]:
    """Direct children of ``pid`` (every thread's /proc/<pid>/task/<tid>/children)."""
    found: list[int] = []
    with contextlib.suppress(OSError):
        for task in Path(f"/proc/{pid}/task").iterdir():
            with contextlib.suppress(OSError):
                found += [int(c) for c in (task / "children").read_text().split()]
    return found


def long_lived(pids: dict[str, int]) -> dict[str, int]:
    """The interceptors and their DDS bridge children (looked up again per row: a bridge may restart)."""
    out = dict(pids)
    for side in ("a", "b"):
        kids = children(pids[f"interceptor_{side}"])
        if kids:
            out[f"bridge_{side}"] = kids[0]
    return out


def _snapshot(pids: dict[str, int]) -> dict[str, float | None]:
    return {name: cpu_seconds(pid) for name, pid in pids.items()}


def cpu_per_message(result: dict, before: dict, after: dict, bridged: bool) -> dict[str, Any]:
    """CPU microseconds per received message per process, the total, and the pipeline
    ceiling (the rate if every process had a core of its own: 1e6 / the largest)."""
    n = max(1, result.get("received", 0))
    per: dict[str, float] = {}
    per["publisher"] = result.get("pub_cpu_s", 0.0) * 1e6 / n
    for name in ("interceptor_a", "bridge_a", "interceptor_b", "bridge_b"):
        if before.get(name) is not None and after.get(name) is not None:
            per[name] = (after[name] - before[name]) * 1e6 / n
    per["subscriber"] = result.get("sub_cpu_s", 0.0) * 1e6 / n
    counted = per if bridged else {k: per[k] for k in ("publisher", "subscriber")}
    top = max(counted.values()) if counted else 0.0
    return {"us_per_msg": {k: round(v, 1) for k, v in per.items()},
            "total_us": round(sum(counted.values()), 1),
            "ceiling_msg_s": round(1e6 / top) if top else None,
            "busiest": max(counted, key=counted.get) if counted else None,
            "window_s": round(after.get("_t", 0.0) - before.get("_t", 0.0), 3)}


@contextlib.contextmanager
def interceptor_pair(workdir: Path, python: Path, domains: tuple[int, int], depth: int = 10) -> Iterator[dict[str, int]]:
    """Robot A's and robot B's interceptors (``ros2`` role, peers of each other) with their
    PKI, registry and authorization server; yields the two interceptors' pids."""
    with lab_network(workdir, POLICY, hosts=HOSTS, master="none", ros2=dict(zip(HOSTS, domains, strict=True)),
                       ros2_python=python, ros2_depth=depth, limits=UNTHROTTLED) as net:
        yield {"interceptor_a": net.hosts["robot_a"].proc.pid, "interceptor_b": net.hosts["robot_b"].proc.pid}


def _run_pair(python: Path, kind: str, count: int, hz: float, pub_domain: int, sub_domain: int,
              pids: dict[str, int] | None = None, bridged: bool = False) -> dict:
    """One publisher, one subscriber; warm-up until the subscriber saw a message, then
    ``count`` measured messages. Returns the subscriber's figures plus the publisher's
    ``sent`` and ``send_rate``, and ``cpu``: CPU per message of every process (publisher
    and subscriber over their measured window, the interceptors and bridges of ``pids``
    from GO until the subscriber got its last message; on the direct path they idle)."""
    sub = subprocess.Popen([str(python), str(NODE), "sub", kind, str(count), "3"], env=_ros_env(sub_domain),
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    pub = None
    try:
        if sub.stdout.readline().strip() != "READY":
            raise NetworkError("the benchmark subscriber did not start")
        pub = subprocess.Popen([str(python), str(NODE), "pub", kind, str(count), str(hz)], env=_ros_env(pub_domain),
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        if sub.stdout.readline().strip() != "WARM":
            raise NetworkError("no warm-up message reached the benchmark subscriber within 60 s")
        watched = long_lived(pids or {})
        before = _snapshot(watched)
        before["_t"] = time.monotonic()
        pub.stdin.write("GO\n")
        pub.stdin.flush()
        if sub.stdout.readline().strip() != "DONE":  # the subscriber stops on its own within 180 s
            raise NetworkError("the benchmark subscriber did not finish")
        after = _snapshot(watched)
        after["_t"] = time.monotonic()
        line = sub.stdout.readline()  # the JSON line follows DONE (communicate() would miss what readline buffered)
        sub.wait(timeout=60)
        result = json.loads(line)
        pub_out, _ = pub.communicate(timeout=30)
        result.update(json.loads(pub_out.strip().splitlines()[-1]))
        result["cpu"] = cpu_per_message(result, before, after, bridged)
        return result
    finally:
        stop(sub)
        if pub is not None:
            stop(pub)


def _load() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "?"


@click.command()
@click.option("--small", "n_small", default=20_000, show_default=True, help="Small messages, as fast as the path takes them (reliable, KEEP_ALL).")
@click.option("--at100", "n_100", default=500, show_default=True, help="Messages at 100 Hz for latency.")
@click.option("--at1k", "n_1k", default=3_000, show_default=True, help="Messages at 1 kHz for latency.")
@click.option("--image80k", "n_img", default=1_000, show_default=True, help="80 KB images, as fast as the path takes them (reliable, KEEP_ALL).")
@click.option("--depth", default=10, show_default=True,
              help="[ros2] depth of the interceptors (history of the bridge's DDS endpoints).")
@click.option("--python", "python", default=None, help="The ROS 2 venv's python (default: .ros2-venv).")
@click.option("--json", "as_json", is_flag=True, help="Print the results as JSON.")
@click.option("--keep", "keep", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Work in this directory and keep it (PKI, registry, the interceptors' logs) to look into a run.")
def ros2(n_small: int, n_100: int, n_1k: int, n_img: int, depth: int, python: str | None, as_json: bool,
         keep: Path | None) -> None:
    """rclpy to rclpy direct against rclpy through the interceptor pair, in one run."""
    py = Path(python) if python else default_ros2_python()
    if not py.exists():
        raise click.ClickException(f"{py} does not exist: create the ROS 2 venv with scripts/ros2-venv")
    from cryptoros.ros2.exposure import free_domains

    # direct, robot A, robot B: domains no other session on this host is using now
    domains = tuple(free_domains(3, (os.getpid() * 7) % 99))
    rows = [
        ("std_msgs/String 64 B, max rate", "small", n_small, 0.0),
        ("one-way latency at 100 Hz", "small", n_100, 100.0),
        ("one-way latency at 1 kHz", "small", n_1k, 1000.0),
        ("sensor_msgs/Image 80 KB, max rate", "image", n_img, 0.0),
    ]
    results: dict[str, Any] = {}
    if keep is not None:
        keep.mkdir(parents=True, exist_ok=True)
    with (contextlib.nullcontext(str(keep)) if keep is not None
          else tempfile.TemporaryDirectory(prefix="cryptoros-bench-ros2-")) as tmp:
        # Both paths of a row run back to back (direct first), so a change of load on the
        # shared machine hits both alike; the idle interceptors run during the direct rows too.
        with interceptor_pair(Path(tmp), py, domains[1:], depth) as pids:
            time.sleep(1.0)
            for label, kind, count, hz in rows:
                for path, (pub_domain, sub_domain) in (("direct", (domains[0], domains[0])),
                                                       ("bridged", (domains[1], domains[2]))):
                    results.setdefault(label, {})[path] = _run_pair(py, kind, count, hz, pub_domain, sub_domain,
                                                                    pids, path == "bridged")
                    if not as_json:
                        click.echo(f"  {label:36s} {path:8s} {results[label][path]}", err=True)
    results["load_average"] = _load()
    if as_json:
        click.echo(json.dumps(results, indent=2))
        return
    click.echo("\nInterceptors: [limits] max_messages_per_second = 0 (unthrottled).")
    click.echo("\n| measurement | direct (one domain) | through the interceptor pair | ratio / added |")
    click.echo("|---|---|---|---|")
    for label, kind, count, hz in rows:
        d, b = results[label]["direct"], results[label]["bridged"]
        got = f"received {d['received']}/{count} direct, {b['received']}/{count} through"
        if hz:
            added = (b["p50"] or 0) - (d["p50"] or 0)
            click.echo(f"| {label} (p50 / p99 ms) | {d['p50']:.3f} / {d['p99']:.3f} | {b['p50']:.3f} / {b['p99']:.3f} "
                       f"| +{added:.3f} ms p50 ({got}) |")
        else:
            key = "mbps" if kind == "image" else "rate"
            ratio = b[key] / d[key] * 100 if d[key] else 0.0
            click.echo(f"| {label} (msg/s; MB/s) | {d['rate']:,.0f}; {d['mbps']:,.1f} | {b['rate']:,.0f}; {b['mbps']:,.1f} "
                       f"| {ratio:.0f} % ({got}) |")
    click.echo("\nCPU per message (µs; publisher and subscriber over their measured window, interceptors and bridges"
               " from GO to the last message; on the direct path the pair idles and is not counted in the total):")
    heads = ("pub", "icpt A", "bridge A", "icpt B", "bridge B", "sub")
    click.echo(f"| row | path | {' | '.join(heads)} | total | ceiling msg/s | measured msg/s |")
    click.echo("|---|---|" + "---:|" * (len(heads) + 3))
    for label, kind, count, hz in rows:
        for path in ("direct", "bridged"):
            r = results[label][path]
            c = r["cpu"]
            cells = " | ".join(f"{c['us_per_msg'][p]:.1f}" if p in c["us_per_msg"] else "-" for p in PROCESSES)
            ceiling = f"{c['ceiling_msg_s']:,}" if c["ceiling_msg_s"] else "-"
            click.echo(f"| {label} | {path} | {cells} | {c['total_us']:.1f} | {ceiling} | {r['rate']:,.0f} |")
    click.echo("ceiling = 1e6 / the largest per-process µs per message: the rate if every process had a core of its own"
               " (a paced row's ceiling only says how much headroom is left).")
    click.echo(f"\nload average after the run: {results['load_average']} (2 cores shared); interceptors' [ros2] depth = {depth}")
