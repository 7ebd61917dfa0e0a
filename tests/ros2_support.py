"""Robots on ROS 2 domains behind interceptors, for the ROS 2 tests (no tests here).

Each robot is one localhost-only DDS domain (fresh ids per test session, derived from
the pid) plus one ``cryptoros-interceptor`` with the ``ros2`` role on its own loopback
address; a real ``cryptoros-authz`` daemon holds the registry. The ROS 2 nodes are
unmodified rclpy scripts (tests/ros2_nodes) run by the ROS 2 venv's python, which
``scripts/ros2-venv`` creates (skipped locally, failed under CI=true, if it cannot).
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import os
import queue
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from cryptoros.lab.policy import policy_yaml
from tests.pki_fixtures import TestPKIFactory
from tests.support import REPO, free_port, missing, script, stop, wait_for_port
from tests.authz_support import AuthzDaemon, authz_here, ok

NODES = Path(__file__).parent / "ros2_nodes"
HOSTS = {"robot_a": "127.0.0.2", "robot_b": "127.0.0.3", "robot_c": "127.0.0.5"}
PEERS = {"robot_a": ("robot_b", "robot_c"), "robot_b": ("robot_a",), "robot_c": ("robot_a",)}

STRING2, TWIST, SCAN, IMAGE = "std_msgs/msg/String", "geometry_msgs/msg/Twist", "sensor_msgs/msg/LaserScan", "sensor_msgs/msg/Image"
SET_BOOL = "std_srvs/srv/SetBool"
GRANTS = {
    "robot_a": {"publish": [("/talker", "/chatter", STRING2), ("/talker", "/latched", STRING2), ("/talker", "/twist", TWIST),
                            ("/talker", "/scan", SCAN), ("/talker", "/image", IMAGE), ("/talker", "/both", STRING2),
                            ("/talker", "/stuck", STRING2)],
                "subscribe": [("*", "/back", STRING2), ("*", "/both", STRING2)],
                "serve": [("/flag_server", "/set_flag", SET_BOOL)]},
    "robot_b": {"subscribe": [("*", "/chatter", STRING2), ("*", "/latched", STRING2), ("*", "/secret", STRING2),
                              ("*", "/twist", TWIST), ("*", "/scan", SCAN), ("*", "/image", IMAGE),
                              ("*", "/both", STRING2), ("*", "/stuck", STRING2)],
                "publish": [("/talker", "/back", STRING2), ("/talker_b", "/both", STRING2)],
                "call": [("*", "/set_flag", SET_BOOL)]},
    "robot_c": {},
}
POLICY = policy_yaml(GRANTS)


@functools.cache
def ros2_python() -> Path:
    """The ROS 2 venv's python, created by scripts/ros2-venv on first use."""
    venv = Path(os.environ.get("CRYPTOROS_ROS2_VENV", REPO / ".ros2-venv"))
    lock = Path(f"{venv}.lock")
    try:
        with lock.open("w") as held:  # one worker creates it; the other waits, then finds it made
            fcntl.flock(held, fcntl.LOCK_EX)
            result = subprocess.run([str(REPO / "scripts" / "ros2-venv"), str(venv)], capture_output=True, text=True,
                                    timeout=600)
    except subprocess.TimeoutExpired:
        result = None
    if result is None or result.returncode != 0:
        missing(f"cannot create the ROS 2 venv with scripts/ros2-venv: {result.stderr[-500:] if result else 'timeout'}")
    return venv / "bin" / "python"


def fresh_domains(count: int) -> list[int]:
    """Domain ids below the ephemeral ports (0..100 on Linux's defaults: the interceptor
    refuses a domain over them) no other session on this host is using now; each xdist
    worker (``gwN``) draws from its own part of the range, so two workers never share one."""
    from cryptoros.ros2.exposure import highest_private_domain

    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    workers = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
    index = int(worker[2:]) if worker[2:].isdigit() else 0
    span = (highest_private_domain() + 1) // workers
    low = (index % workers) * span
    # ids whose ports no process on this host has bound: another session's endpoints on a
    # shared domain would match this test's own (cryptoros.ros2.exposure.free_domains)
    from cryptoros.ros2.exposure import free_domains

    return free_domains(count, low + (os.getpid() * 7) % max(1, span - count), low=low, top=low + span - 1)


def ros2_env(domain: int, *, localhost_profile: bool = True) -> dict[str, str]:
    """The environment of an unmodified rclpy node on a robot: its domain, and (as
    docs/ros2.md asks of operators) cryptoros's localhost-only Fast DDS profile."""
    from cryptoros.ros2.profile import PROFILE_ENV, localhost_env

    env = {k: v for k, v in os.environ.items() if not k.startswith(("ROS_", "_ROS_WHEELS", "RMW_", PROFILE_ENV))}
    env.pop("PYTHONPATH", None)
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    return localhost_env(env) if localhost_profile else env


class Line(str):
    """One line of a node's output, with ``at``: when (monotonic) it was read from the pipe."""

    at: float

    def __new__(cls, text: str) -> "Line":
        line = super().__new__(cls, text)
        line.at = time.monotonic()
        return line


class Lines:
    """A process's stdout lines (:class:`Line`), read by a thread so every wait can be
    bounded, and timed as they come even while the test is busy elsewhere."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.proc = proc
        self.queue: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        for line in self.proc.stdout:
            self.queue.put(Line(line.rstrip("\n")))
        self.queue.put(None)

    def until(self, wanted: str | None, timeout: float) -> list[str]:
        """Lines read until one equals ``wanted`` (None: for ``timeout`` seconds)."""
        lines, deadline = [], time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                if wanted is None:
                    return lines
                raise AssertionError(f"no {wanted!r} within {timeout}s; got {lines[-5:]}")
            try:
                line = self.queue.get(timeout=left)
            except queue.Empty:
                continue
            if line is None:
                if wanted is None:
                    return lines
                raise AssertionError(f"process ended before {wanted!r}; got {lines[-10:]}")
            lines.append(line)
            if line == wanted:
                return lines


def collect(lines: Lines, count: int, timeout: float) -> list[str]:
    """Lines until ``count`` GOT lines arrived (AssertionError after ``timeout``)."""
    out, n, deadline = [], 0, time.monotonic() + timeout
    while n < count:
        left = deadline - time.monotonic()
        if left <= 0:
            raise AssertionError(f"only {n} of {count} messages within {timeout}s; last {out[-5:]}")
        try:
            line = lines.queue.get(timeout=left)
        except queue.Empty:
            continue
        if line is None:
            raise AssertionError(f"process ended after {n} of {count} messages; last {out[-5:]}")
        out.append(line)
        n += line.startswith("GOT ")
    return out


def collect_through(lines: Lines, seq: int, quiet: float) -> list[str]:
    """Lines until the GOT line of message ``seq`` or a later one; AssertionError once no
    message arrived for ``quiet`` seconds. (Counted as they arrive: a burst of 12,000
    messages re-parsed per line took 26 s of the test's CPU.)"""
    out: list[str] = []
    while True:
        more = collect(lines, 1, quiet)
        out += more
        if got(more)[-1] >= seq:
            return out


def got(lines: list[str]) -> list[int]:
    return [int(line.split()[1]) for line in lines if line.startswith("GOT ")]


#: sequence numbers of an attacker's messages start here (robot A's talker counts from 0)
INSIDER = 500_000
#: every legitimate flow is back within this long after an attack ends
BACK_WITHIN = 5.0


class Arrivals:
    """A listener's GOT lines, timed as they left its pipe (:class:`Line`), split by sender."""

    def __init__(self, lines: Lines) -> None:
        self.lines = lines
        self.a: list[tuple[float, int]] = []  # (arrival, seq) of robot A's messages
        self.insider: list[tuple[float, int]] = []
        self.bad: list[str] = []
        self.other: list[str] = []  # the last lines that were neither (errors, READY, END)

    def _read(self, timeout: float) -> bool:
        try:
            line = self.lines.queue.get(timeout=timeout)
        except Exception:  # queue.Empty
            return False
        if line is None:
            raise AssertionError(f"robot B's listener ended; its last other lines: {self.other[-5:]}")
        if line.startswith("GOT "):
            seq = int(line.split()[1])
            (self.insider if seq >= INSIDER else self.a).append((getattr(line, "at", time.monotonic()), seq))
        elif line.startswith("BAD"):
            self.bad.append(line)
        else:
            self.other = [*self.other[-9:], line]
        return True

    def until(self, done, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not done():
            left = deadline - time.monotonic()
            assert left > 0, f"{what} within {timeout} s (robot A: {len(self.a)}, insider: {len(self.insider)})"
            self._read(min(left, 0.2))

    def more_from_a(self, count: int, timeout: float, what: str, *, since: float | None = None) -> None:
        """Until ``count`` more of robot A's messages (``since``: printed after that time)."""
        if since is None:
            target = len(self.a) + count
            self.until(lambda: len(self.a) >= target, timeout, what)
        else:
            self.until(lambda: sum(t > since for t, _ in self.a[-count:]) >= count, timeout, what)

    def a_silence(self, start: float, stop: float | None = None) -> float:
        """The longest silence of robot A's flow from ``start`` to ``stop`` (None: to its
        last message), both ends counted."""
        times = [start] + [t for t, _ in self.a if t > start and (stop is None or t < stop)]
        times += [stop] if stop is not None else []
        return max((b - a for a, b in zip(times, times[1:])), default=float("inf"))


def assert_flow_held(seen: Arrivals, start: float, end: float, *, during_bound: float = BACK_WITHIN) -> None:
    """Robot A's flow during an attack (``start`` to ``end``): never silent ``during_bound``
    seconds; after it: back within BACK_WITHIN and never silent that long again."""
    assert not seen.bad, seen.bad[:3]
    during, after = seen.a_silence(start, end), seen.a_silence(end)
    print(f"robot A's longest silence: {during:.2f} s during the attack, {after:.2f} s after it")
    assert during < during_bound, f"robot A's flow was silent for {during:.1f} s during the attack"
    assert after < BACK_WITHIN, f"robot A's flow was silent for {after:.1f} s after the attack"


def flow_around(network, attack, *, during_bound: float = BACK_WITHIN) -> None:
    """Robot A's talker (20 Hz) to robot B's listener on ``/chatter``, before, during
    ``attack(seen)`` (it returns once the attack ended) and after it: never silent
    BACK_WITHIN seconds (:func:`assert_flow_held`)."""
    with network.node("robot_b", "listener.py", "string", "/chatter", "300") as sub:
        sub.until("READY", 20)
        seen = Arrivals(sub)
        with network.node("robot_a", "talker.py", "string", "/chatter", "1000000", "20"):
            seen.more_from_a(10, 40, "robot A's /chatter did not reach robot B before the attack")
            start = time.monotonic()
            attack(seen)
            end = time.monotonic()
            seen.more_from_a(60, 40, "robot A's flow did not come back after the attack", since=end)
    assert_flow_held(seen, start, end, during_bound=during_bound)


@dataclass
class Robot:
    name: str
    address: str
    domain: int
    public_port: int
    metrics_port: int
    config: Path
    proc: subprocess.Popen | None = None
    log: Path | None = None

    def logs(self) -> str:
        return self.log.read_text() if self.log and self.log.exists() else ""

    def denials(self) -> str:
        return "\n".join(line for line in self.logs().splitlines() if "DENY" in line)


@dataclass
class Ros2Network:
    workdir: Path
    pki: TestPKIFactory
    daemon: AuthzDaemon
    python: Path
    robots: dict[str, Robot] = field(default_factory=dict)

    @contextlib.contextmanager
    def node(self, robot: str, script_name: str, *args: str, domain: int | None = None,
             localhost_profile: bool = True) -> Iterator[Lines]:
        """An unmodified rclpy node on ``robot``'s domain; stopped on exit. Without
        ``localhost_profile`` it is started as a careless operator would, DDS on every interface."""
        env = ros2_env(self.robots[robot].domain if domain is None else domain, localhost_profile=localhost_profile)
        proc = subprocess.Popen([str(self.python), str(NODES / script_name), *args], env=env, cwd=str(NODES),
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            yield Lines(proc)
        finally:
            stop(proc, timeout=5)

    def start(self, name: str, *options: str) -> Robot:
        robot = self.robots[name]
        robot.log = self.workdir / f"interceptor-{name}.log"
        robot.proc = subprocess.Popen(
            [script("cryptoros-interceptor"), "--config", str(robot.config), "--log-level", "debug", *options],
            stdout=robot.log.open("a"), stderr=subprocess.STDOUT,
        )
        wait_for_port(robot.address, robot.public_port, timeout=40, proc=robot.proc)
        return robot

    def stop(self, name: str) -> None:
        robot = self.robots[name]
        if robot.proc is not None:
            stop(robot.proc, timeout=10)
            robot.proc = None

    def cli(self, *args: str):
        return authz_here(*args, db=self.daemon.db)

    def metrics(self, name: str) -> str:
        import urllib.request

        with urllib.request.urlopen(f"http://127.0.0.1:{self.robots[name].metrics_port}/metrics", timeout=5) as r:
            return r.read().decode()


def robot_config(pki: TestPKIFactory, name: str, address: str, *, public: int, metrics: int, domain: int,
                 peers: list[str], authz_url: str, python: Path, extra: str = "") -> str:
    cert, key = pki.pki.cert_path_for(name), pki.pki.key_path_for(name)
    peer_list = ", ".join(f'"{p}"' for p in peers)
    return "\n".join([
        f'manager = "{name}"',
        'roles = ["ros2"]',
        "[tls]", f'ca = "{pki.ca_cert}"', f'cert = "{cert}"', f'key = "{key}"', f'crl = "{pki.crl}"',
        "[authz]", f'url = "{authz_url}"', "revocation_poll_interval = 0.5",
        "[listen]", f'public = "{address}:{public}"', f'metrics = "127.0.0.1:{metrics}"',
        "[ros2]", f"domain_id = {domain}", f"peers = [{peer_list}]", f'python = "{python}"', "graph_interval = 0.25",
        'transient_local = ["/latched"]',
        extra,
    ]) + "\n"


@contextlib.contextmanager
def ros2_network(workdir: Path, *, start: tuple[str, ...] = ("robot_a", "robot_b", "robot_c"),
                 policy: str = POLICY, extra: dict[str, str] | None = None,
                 peers: dict[str, tuple[str, ...]] | None = None) -> Iterator[Ros2Network]:
    python = ros2_python()
    pki = TestPKIFactory(workdir / "pki")
    fingerprints = {}
    for name, address in HOSTS.items():
        fingerprints[name] = pki.issue(name, kind="interceptor", sans=(f"IP:{address}",)).fingerprint_sha256
    db = f"sqlite:///{workdir / 'registry.db'}"
    (workdir / "policy.yaml").write_text(policy.format(**fingerprints))
    ok(authz_here("import", str(workdir / "policy.yaml"), db=db))
    daemon = AuthzDaemon(pki=pki, db=db, workdir=workdir)
    net = None
    try:
        daemon.start()
        net = Ros2Network(workdir=workdir, pki=pki, daemon=daemon, python=python)
        taken: set[int] = set()  # every robot's ports distinct (metrics all on 127.0.0.1)
        ports = {name: free_port(address, taken) for name, address in HOSTS.items()}
        for (name, address), domain in zip(HOSTS.items(), fresh_domains(len(HOSTS)), strict=True):
            config = workdir / f"{name}.toml"
            metrics = free_port("127.0.0.1", taken)
            config.write_text(robot_config(
                pki, name, address, public=ports[name], metrics=metrics, domain=domain,
                peers=[f"{HOSTS[p]}:{ports[p]}" for p in {**PEERS, **(peers or {})}[name]], authz_url=daemon.base, python=python,
                extra=(extra or {}).get(name, ""),
            ))
            net.robots[name] = Robot(name, address, domain, ports[name], metrics, config)
        for name in start:
            net.start(name)
        yield net
    finally:
        if net is not None:
            for name in net.robots:
                net.stop(name)
        daemon.stop()
