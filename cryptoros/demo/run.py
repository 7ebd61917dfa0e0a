"""``cryptoros demo``: a live robot team, attacked, plain ROS then behind cryptoros.

Every part is a separate process in its own process group: the authorization server,
the ROS master (embedded, or the user's with ``--master-uri``), one interceptor per
host, one process per robot (:mod:`cryptoros.demo.robot`) and one per attack
(:mod:`cryptoros.demo.attackers`). Hosts are loopback addresses:

==========  ==============  ===================================================
host        address         what runs there
==========  ==============  ===================================================
master      127.0.0.10      the ROS master (protected: behind its interceptor)
rN          127.0.0.(11+N)  robot N's nodes ``/rN`` and ``/rN_base``
ops         127.0.0.40      the operations host (only with a ``held-*`` attack): its
                            manager may publish r0's pose, scan and cmd_vel
stranger    127.0.0.66      attackers without certificate or token
==========  ==============  ===================================================

Three modes: ``plain`` ROS, ``protected`` (the interceptors) and ``monitored`` (the
interceptors with the runtime monitor, ``[monitor] action = "quarantine"``, its model
trained on a clean calibration mission recorded before: :mod:`cryptoros.demo.session`).

In protected mode an attack runs either as a *stranger* (a machine on the network
without a certificate: it can only reach the interceptors' public TLS ports) or as an
*insider* (a node on another robot's host, behind that robot's interceptor, whose
manager has no grant for what it attacks). Success is judged from what the victims
actually received and executed, recorded by the robots themselves.
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from cryptoros.demo.attackers import ATTACKS, FALSE_MAP_ONSET, HELD_ATTACKS, OPS_HOST, insider_host, target_of
from cryptoros.errors import CryptorosError
from cryptoros.lab.policy import policy_yaml

MASTER_ADDR = "127.0.0.10"
OPS_ADDR = "127.0.0.40"
STRANGER_ADDR = "127.0.0.66"
ALL_ATTACKS = tuple(ATTACKS)
#: seconds after the false map's onset that robots all stopped wait for its first claim
FALSE_MAP_PATIENCE = 8.0
TEAM_TYPES = {"hello": "cryptoros_sim/Hello", "lsu": "cryptoros_sim/LinkStateUpdate", "map": "cryptoros_sim/MapUpdate",
              "recruit": "cryptoros_sim/RecruitPacket", "protocol": "cryptoros_sim/ProtocolPacket"}


class DemoError(CryptorosError, RuntimeError):
    """The demo could not run (a part did not come up, a step failed)."""


@dataclass
class DemoOptions:
    robots: int = 3
    attacks: tuple[str, ...] = ALL_ATTACKS
    seconds: float = 30.0  # wall-clock budget of one mission
    modes: tuple[str, ...] = ("plain", "protected")
    master_uri: str | None = None
    keep: bool = False
    seed: int = 1
    width: int = 60
    height: int = 60
    scale: float = 8.0  # simulated seconds per wall second
    coverage_target: float = 0.9
    attack_delay: float = 1.0  # wall seconds after the start
    workdir: str | None = None
    ros: int = 1  # 1: ROS 1 nodes (this module); 2: rclpy nodes (cryptoros.demo.ros2)
    netns: bool = False  # protected mode: every host in its own network namespace (root)
    #: a compromised robot (monitor datasets): {"robot": "r0", "kind": ..., "onset": wall s after the start}
    compromise: dict[str, Any] | None = None
    #: the runtime monitor's model (mode "monitored"; written by the calibration mission)
    monitor_model: str | None = None
    #: each attack in its own missions (effects do not mix)
    isolate: bool = False
    #: protected modes: every robot's manager in learning mode for the whole mission
    learn: bool = False

    def needs_ops(self) -> bool:
        return any(ATTACKS[k]["as"] == "holder" for k in self.attacks if k in ATTACKS)

    def compromised(self) -> dict[str, dict[str, Any]]:
        """robot -> its compromise: the dataset's, and held-false-map's (robot r1's explorer)."""
        out = {}
        if self.compromise:
            out[self.compromise["robot"]] = self.compromise
        if "held-false-map" in self.attacks:
            robot = target_of("held-false-map", self.robots)
            out[robot] = {"robot": robot, "kind": "false-map", "onset": self.attack_delay + FALSE_MAP_ONSET}
        return out


def robot_addr(i: int) -> str:
    return f"127.0.0.{11 + i}"


def policy(n: int, ops: bool = False) -> str:
    managers: dict = {"master": {}}
    pose, scan, twist = "geometry_msgs/PoseStamped", "sensor_msgs/LaserScan", "geometry_msgs/Twist"
    if ops:  # the operations host: a motion-capture bridge, a scan filter, a teleop console
        managers[OPS_HOST] = {
            "publish": [grant for i in range(n) for grant in (("/mocap_*", f"/r{i}/pose", pose),
                                                              ("/scan_filter", f"/r{i}/scan", scan),
                                                              ("/teleop", f"/r{i}/cmd_vel", twist))],
            "subscribe": [grant for i in range(n) for grant in (("/mocap_*", f"/r{i}/pose", pose),
                                                                ("/scan_filter", f"/r{i}/scan", scan))],
        }
    for i in range(n):
        r = f"r{i}"
        team = [(f"/{r}", f"/team/{short}", ty) for short, ty in TEAM_TYPES.items()]
        managers[r] = {
            "publish": [*team, (f"/{r}", f"/{r}/cmd_vel", twist), (f"/{r}_base", f"/{r}/pose", pose),
                        (f"/{r}_base", f"/{r}/scan", scan)],
            "subscribe": [*team, (f"/{r}", f"/{r}/pose", pose), (f"/{r}", f"/{r}/scan", scan),
                          (f"/{r}_base", f"/{r}/cmd_vel", twist)],
        }
    return policy_yaml(managers)


# ----------------------------------------------------------------------------- processes


class Children:
    """Every child in its own process group; all of them killed on the way out."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []

    def start(self, cmd: list[str], log: Path, env: dict[str, str]) -> subprocess.Popen:
        p = subprocess.Popen(cmd, stdout=log.open("w"), stderr=subprocess.STDOUT, env=env, start_new_session=True)
        self.procs.append(p)
        return p

    def terminate(self, procs: list[subprocess.Popen], timeout: float = 8.0) -> None:
        for p in procs:
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(p.pid, signal.SIGTERM)
        deadline = time.monotonic() + timeout
        for p in procs:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
        for p in procs:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(p.pid, signal.SIGKILL)  # the group: anything a child left behind
            if p.poll() is None:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    p.wait(timeout=5)

    def kill_all(self) -> None:
        self.terminate(self.procs, timeout=5.0)


def _env(**extra: str) -> dict[str, str]:
    from cryptoros.lab.network import clean_env

    return clean_env(PYTHONUNBUFFERED="1", **extra)


def _cpu_seconds(pid: int) -> float:
    from cryptoros.lab.network import cpu_seconds

    return cpu_seconds(pid) or 0.0


def _tail(path: Path, lines: int) -> list[str]:
    try:
        return path.read_text(errors="replace").splitlines()[-lines:]
    except OSError as exc:
        return [f"(no log: {exc})"]


def _rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def scrape(port: int) -> dict[str, Any]:
    """Denials by reason and bytes relayed from one interceptor's ``/metrics``."""
    out: dict[str, Any] = {"denied": {}, "bytes": 0.0, "allowed": 0.0, "monitor_alerts": 0.0, "monitor_quarantines": 0.0,
                           "monitor_dropped": 0.0, "monitor_busy_s": 0.0}
    try:
        text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=3).read().decode()
    except OSError:
        return out
    for line in text.splitlines():
        if line.startswith("cryptoros_interceptor_denied_total{"):
            m = re.search(r'reason="([^"]*)"\}\s+([0-9.e+]+)', line)
            if m:
                out["denied"][m.group(1)] = out["denied"].get(m.group(1), 0) + int(float(m.group(2)))
        elif line.startswith("cryptoros_interceptor_bytes_total{"):
            out["bytes"] += float(line.rsplit(" ", 1)[1])
        elif line.startswith("cryptoros_interceptor_allowed_total{"):
            out["allowed"] += float(line.rsplit(" ", 1)[1])
        elif line.startswith("cryptoros_monitor_alerts_total{"):
            out["monitor_alerts"] += float(line.rsplit(" ", 1)[1])
        elif line.startswith("cryptoros_monitor_quarantines_total"):
            out["monitor_quarantines"] += float(line.rsplit(" ", 1)[1])
        elif line.startswith("cryptoros_monitor_dropped_total{"):
            out["monitor_dropped"] += float(line.rsplit(" ", 1)[1])
        elif line.startswith("cryptoros_monitor_busy_seconds_total "):
            out["monitor_busy_s"] += float(line.rsplit(" ", 1)[1])
    return out


def monitor_section(model: str) -> str:
    """The ``[monitor]`` of every robot's interceptor in the monitored mode: every topic
    watched, the team map gated (a false "explored" claim is believed at its first)."""
    return (f'\n[monitor]\nmodel = "{model}"\naction = "quarantine"\nquarantine_seconds = 600.0\n'
            'gate = ["/team/map"]\n')


# ----------------------------------------------------------------------------- one mission


@dataclass
class Graph:
    """Where robots and attackers of one mode connect."""

    robot_master: dict[str, str]  # robot -> ROS_MASTER_URI
    robot_ip: dict[str, str]
    stranger_master: str
    insider_master: dict[str, str]  # host -> ROS_MASTER_URI of a node there
    insider_ip: dict[str, str]
    interceptors: dict[str, Any] = field(default_factory=dict)  # name -> Host (protected)
    ports: list[tuple[str, int]] = field(default_factory=list)
    stranger_ip: str = STRANGER_ADDR
    #: (host or None for the stranger, argv) -> the command line that runs on that host
    on_host: Callable[[str | None, list[str]], list[str]] = lambda _host, argv: argv


class Mission:
    def __init__(self, opts: DemoOptions, mode: str, workdir: Path, children: Children,
                 progress: Callable[[dict[str, Any]], None]) -> None:
        self.opts = opts
        self.mode = mode
        self.dir = workdir / mode
        self.dir.mkdir(parents=True, exist_ok=True)
        #: the last lines of the log of a robot that exited during the mission
        self.exit_log: dict[str, list[str]] = {}
        self.children = children
        self.progress = progress
        self.team = [f"r{i}" for i in range(opts.robots)]
        from cryptoros.demo.robot import make_world

        self.world = make_world({"seed": opts.seed, "width": opts.width, "height": opts.height})
        self.explorable = self.world.explorable()
        self.t0 = 0.0  # Unix time of the start
        self.n_explorable = int(self.explorable.sum())

    # -- graphs ---------------------------------------------------------------------------------

    @contextlib.contextmanager
    def graph(self):  # type: ignore[no-untyped-def]
        if self.mode == "plain":
            yield from self._plain()
        else:
            yield from self._protected()

    def _plain(self):  # type: ignore[no-untyped-def]
        from cryptoros.lab.network import free_port, tool, wait_port

        if self.opts.master_uri:
            uri = self.opts.master_uri.rstrip("/") + "/"
            ports: list[tuple[str, int]] = []
        else:
            port = free_port(MASTER_ADDR)
            p = self.children.start([tool("cryptoros"), "master", "--host", MASTER_ADDR, "--port", str(port)],
                                    self.dir / "master.log", _env())
            wait_port(MASTER_ADDR, port, 20, p, "cryptoros master")
            uri = f"http://{MASTER_ADDR}:{port}/"
            ports = [(MASTER_ADDR, port)]
        try:
            yield Graph(robot_master={r: uri for r in self.team}, robot_ip={r: robot_addr(i) for i, r in enumerate(self.team)},
                        stranger_master=uri, insider_master={r: uri for r in [*self.team, OPS_HOST]},
                        insider_ip={**{r: robot_addr(i) for i, r in enumerate(self.team)}, OPS_HOST: OPS_ADDR}, ports=ports)
        finally:
            if ports:
                self.children.terminate([p])

    def _protected(self):  # type: ignore[no-untyped-def]
        from cryptoros.lab.network import lab_network

        hosts = {"master": MASTER_ADDR, **{r: robot_addr(i) for i, r in enumerate(self.team)}}
        ops = self.opts.needs_ops()
        if ops:
            hosts[OPS_HOST] = OPS_ADDR
        extra = {}
        if self.mode == "monitored":
            if not self.opts.monitor_model:
                raise DemoError("the monitored mode needs a monitor model (the calibration mission writes one)")
            section = monitor_section(self.opts.monitor_model)
            extra = {r: section for r in self.team}
        with lab_network(self.dir / "net", policy(len(self.team), ops=ops), hosts=hosts,
                           master=self.opts.master_uri or "embedded", metrics=True, new_session=True,
                           netns=self.opts.netns, extra=extra) as net:
            ports = []
            for h in net.hosts.values():
                ports.append((h.address, h.public_port))
                if h.name != "master":
                    ports.append(("127.0.0.1", h.local_master_port))
                if h.metrics_port:
                    ports.append(("127.0.0.1", h.metrics_port))
            stranger = net.lab.add_host("stranger") if net.lab is not None else None
            for r in self.team if self.opts.learn else ():
                net.learn(r, self.opts.seconds + 120)  # the whole mission: a window ends by itself

            def on_host(host: str | None, argv: list[str]) -> list[str]:
                if host is None:
                    return stranger.argv(argv) if stranger is not None else argv
                return net.argv(host, argv)

            master = net.hosts["master"]
            insiders = [*self.team, OPS_HOST] if ops else self.team
            yield Graph(robot_master={r: net.hosts[r].master_uri for r in self.team},
                        robot_ip={r: "127.0.0.1" for r in self.team},
                        stranger_master=f"http://{master.address}:{master.public_port}/",
                        insider_master={r: net.hosts[r].master_uri for r in insiders},
                        insider_ip={r: "127.0.0.1" for r in insiders}, interceptors=net.hosts, ports=ports,
                        on_host=on_host, stranger_ip=stranger.address if stranger is not None else STRANGER_ADDR)

    # -- run ---------------------------------------------------------------------------------

    def run(self) -> dict[str, Any]:
        t_setup = time.monotonic()
        with self.graph() as g:
            setup_s = time.monotonic() - t_setup
            res = self._mission(g, setup_s)
            res["ports"] = [list(p) for p in g.ports]
            res["learning"] = list(self.team) if self.opts.learn and self.mode != "plain" else []
            return res

    def _start_robots(self, g: Graph) -> dict[str, subprocess.Popen]:
        procs = {}
        for r in self.team:
            cfg = {"name": r, "team": self.team, "seed": self.opts.seed, "width": self.opts.width, "height": self.opts.height,
                   "scale": self.opts.scale, "master_uri": g.robot_master[r], "ros_ip": g.robot_ip[r],
                   "status": str(self.dir / f"{r}.status.json"), "go": str(self.dir / "go.json"), "connect_timeout": 20}
            compromise = self.opts.compromised().get(r)
            if compromise:
                cfg["compromise"] = compromise
            path = self.dir / f"{r}.json"
            path.write_text(json.dumps(cfg))
            procs[r] = self.children.start(g.on_host(r, [sys.executable, "-m", "cryptoros.demo.robot", str(path)]),
                                           self.dir / f"{r}.log", _env())
        return procs

    def _start_attack(self, kind: str, g: Graph) -> subprocess.Popen:
        n = len(self.team)
        who = ATTACKS[kind]["as"]
        if who == "stranger":
            master, ip, host = g.stranger_master, g.stranger_ip, None
        else:
            host = h = insider_host(kind, n)
            master, ip = g.insider_master[h], g.insider_ip[h]
        cfg = {"kind": kind, "master_uri": master, "ros_ip": ip, "target": target_of(kind, n), "team": self.team,
               "width": self.opts.width, "height": self.opts.height, "duration": self.opts.seconds,
               "report": str(self.dir / f"attack-{kind}.report.json"), "bag": str(self.dir / "eavesdrop.bag")}
        path = self.dir / f"attack-{kind}.json"
        path.write_text(json.dumps(cfg))
        return self.children.start(g.on_host(host, [sys.executable, "-m", "cryptoros.demo.attackers", str(path)]),
                                   self.dir / f"attack-{kind}.log", _env())

    def _arm_attacks(self, g: Graph) -> dict[str, subprocess.Popen]:
        """Attackers started before the clock, each ready to strike; none here (a ROS 1
        attacker needs no discovery: the master tells it its victims when it registers)."""
        return {}

    def _fire_attacks(self, g: Graph, armed: dict[str, subprocess.Popen]) -> dict[str, subprocess.Popen]:
        """At ``attack_delay``: every attack under way."""
        return armed or {k: self._start_attack(k, g) for k in self.opts.attacks if ATTACKS[k]["as"] != "compromised"}

    def _read_status(self) -> dict[str, dict[str, Any]]:
        out = {}
        for r in self.team:
            with contextlib.suppress(OSError, ValueError):
                out[r] = json.loads((self.dir / f"{r}.status.json").read_text())
        return out

    def coverage(self, statuses: dict[str, dict[str, Any]]) -> tuple[float, np.ndarray]:
        seen = np.zeros(self.world.shape, dtype=bool)
        for s in statuses.values():
            bits = np.unpackbits(np.frombuffer(base64.b64decode(s["observed"]), dtype=np.uint8))[: seen.size]
            seen |= bits.reshape(seen.shape).astype(bool)
        return float(np.count_nonzero(seen & self.explorable)) / max(1, self.n_explorable), seen

    def _mission(self, g: Graph, setup_s: float) -> dict[str, Any]:
        opts = self.opts
        robots = self._start_robots(g)
        attackers: dict[str, subprocess.Popen] = {}
        armed: dict[str, subprocess.Popen] = {}
        fired, fired_at = False, 0.0
        timeline: list[list[float]] = []
        cpu0 = {n: _cpu_seconds(h.proc.pid) for n, h in g.interceptors.items() if h.proc}
        end_reason, mission_time, mission_wall = "", None, None
        try:
            deadline = time.monotonic() + 60
            while True:
                st = self._read_status()
                if len(st) == len(self.team) and all(s.get("ready") for s in st.values()):
                    break
                for r, p in robots.items():
                    if p.poll() is not None:
                        raise DemoError(f"robot {r} exited with {p.returncode} ({self.dir / (r + '.log')})")
                if time.monotonic() > deadline:
                    raise DemoError(f"robots not connected within 60 s ({self.dir})")
                time.sleep(0.1)
            armed = self._arm_attacks(g)
            t0 = time.time() + 0.3
            go = self.dir / "go.json"  # the robots wait for it to exist: it must never be seen half written
            go.with_suffix(".tmp").write_text(json.dumps({"t0": t0}))
            os.replace(go.with_suffix(".tmp"), go)
            self.t0 = t0
            started = time.monotonic() + 0.3
            quiet_since = None
            while True:
                time.sleep(0.25)
                wall = time.monotonic() - started
                if wall >= opts.attack_delay and not fired:
                    attackers, fired, fired_at = self._fire_attacks(g, armed), True, wall
                st = self._read_status()
                cov, _ = self.coverage(st)
                sim_t = max((s.get("t", 0.0) for s in st.values()), default=0.0)
                timeline.append([round(sim_t, 2), round(wall, 2), round(cov, 4)])
                self.progress({"mode": self.mode, "wall": wall, "sim": sim_t, "coverage": cov, "statuses": st,
                               "budget": opts.seconds, "target": opts.coverage_target})
                if cov >= opts.coverage_target:
                    end_reason, mission_time, mission_wall = "coverage_target", sim_t, wall
                    break
                active = any(s.get("state") in ("explore", "home", "recruited") and not s.get("shut_down") for s in st.values())
                if active or wall < 3.0:
                    quiet_since = None
                elif quiet_since is None:
                    quiet_since = wall
                # robots that all stopped (shut down, hijacked, halted, done on an insider's
                # claim) still wait for the stranger's false map, FALSE_MAP_ONSET s after the
                # other attacks: what it did is judged by what the robots received. In plain
                # ROS, where nothing refuses it, until a robot received a claim, up to
                # FALSE_MAP_PATIENCE s more: on a busy machine its first claims had not
                # reached the one robot left 2 s after the onset (a newcomer audit saw "0
                # false map claims"). Behind the interceptors it is refused: no longer wait
                # (waited there, robots done on the held false map ran 6 s more)
                received = any(s.get("stats", {}).get("map_from_non_team") for s in st.values())
                patient = self.mode == "plain" and not received
                map_wait = FALSE_MAP_ONSET + (FALSE_MAP_PATIENCE if patient else 2.0)
                if quiet_since is not None and wall - quiet_since >= 2.0 and \
                        ("false-map" not in attackers or wall - fired_at >= map_wait):
                    end_reason = "robots_stopped"
                    break
                if fired and stalled(timeline, wall - fired_at):
                    end_reason = "stalled"
                    break
                if wall >= opts.seconds:
                    end_reason = "time_limit"
                    break
                for r, p in robots.items():
                    if p.poll() is not None:
                        end_reason = f"robot {r} exited with {p.returncode}"
                        # its last words, kept in the result: the work directory may be gone after
                        self.exit_log[r] = _tail(self.dir / f"{r}.log", 12)
                if end_reason:
                    break
            wall_total = time.monotonic() - started
            cpu = {n: round(_cpu_seconds(h.proc.pid) - cpu0.get(n, 0.0), 3) for n, h in g.interceptors.items() if h.proc}
            rss = {n: round(_rss_mb(h.proc.pid), 1) for n, h in g.interceptors.items() if h.proc}
            metrics = {n: scrape(h.metrics_port) for n, h in g.interceptors.items() if h.metrics_port}
        finally:
            self.children.terminate(list((armed | attackers).values()), timeout=8)
            self.children.terminate(list(robots.values()), timeout=8)
        final = self._read_status()
        cov, seen = self.coverage(final)
        reports = {}
        for k in attackers:
            with contextlib.suppress(OSError, ValueError):
                reports[k] = json.loads((self.dir / f"attack-{k}.report.json").read_text())
        np.save(self.dir / "coverage_map.npy", seen)
        return {
            "mode": self.mode,
            "setup_s": round(setup_s, 2),
            "end_reason": end_reason,
            **({"exit_log": self.exit_log} if self.exit_log else {}),
            "coverage": round(cov, 4),
            "coverage_target": opts.coverage_target,
            "target_reached": mission_time is not None,
            "mission_time_sim_s": round(mission_time, 1) if mission_time is not None else None,
            "mission_time_wall_s": round(mission_wall, 2) if mission_wall is not None else None,
            "wall_s": round(wall_total, 2),
            "t0": self.t0,
            "timeline": timeline,
            "robots": {r: _robot_summary(s) for r, s in final.items()},
            "messages": {"tx": sum(s["stats"]["tx_messages"] for s in final.values()),
                         "rx": sum(s["stats"]["rx_messages"] for s in final.values()),
                         "tx_bytes": sum(s["stats"]["tx_bytes"] for s in final.values()),
                         "rx_bytes": sum(s["stats"]["rx_bytes"] for s in final.values())},
            "denials": _sum_denials(metrics),
            "monitor": {"alerts": int(sum(m["monitor_alerts"] for m in metrics.values())),
                        "quarantines": int(sum(m["monitor_quarantines"] for m in metrics.values())),
                        "dropped": int(sum(m["monitor_dropped"] for m in metrics.values())),
                        # the monitor's time on the interceptors' event loops: its share of their CPU
                        "busy_s": round(sum(m["monitor_busy_s"] for m in metrics.values()), 3)},
            "interceptors": {"cpu_s": cpu, "cpu_s_total": round(sum(cpu.values()), 3),
                             "cpu_share_of_one_core": round(sum(cpu.values()) / max(1e-9, wall_total), 3),
                             "rss_mb": rss, "bytes_relayed": int(sum(m["bytes"] for m in metrics.values())),
                             "metrics": metrics},
            "attack_reports": reports,
            "_final": final,
        }


STALL_WINDOW_S = 8.0  # wall seconds without coverage progress that end a mission as "stalled"
STALL_PROGRESS = 0.005  # progress below this share of the explorable cells is no progress
ATTACKS_SETTLED_S = 6.0  # wall seconds after the attacks fire (the last one starts 4 s late)


def stalled(timeline: list[list[float]], since_attacks: float) -> bool:
    """The team has stopped making progress: every attack has been under way for a while
    and coverage (the timeline's last column) grew by less than ``STALL_PROGRESS`` over the
    last ``STALL_WINDOW_S`` wall seconds. Ends a mission the attacks have already decided
    (a halted robot still counts as exploring, so "robots_stopped" never comes)."""
    if since_attacks < ATTACKS_SETTLED_S + STALL_WINDOW_S or not timeline:
        return False
    _, now, cov_now = timeline[-1]
    earlier = [row for row in timeline if row[1] <= now - STALL_WINDOW_S]
    return bool(earlier) and cov_now - earlier[-1][2] < STALL_PROGRESS


def _robot_summary(s: dict[str, Any]) -> dict[str, Any]:
    return {"state": s.get("state"), "shut_down": s.get("shut_down"), "travelled_m": s.get("travelled_m"),
            "halted_s": s.get("halted_s"), "false_obstacles": s.get("false_obstacles"), "stats": s.get("stats"),
            "rejected": s.get("rejected"), "callback_errors": s.get("callback_errors")}


def _sum_denials(metrics: dict[str, dict[str, Any]]) -> dict[str, int]:
    out: dict[str, int] = {}
    for m in metrics.values():
        for k, v in m["denied"].items():
            out[k] = out.get(k, 0) + v
    return dict(sorted(out.items()))


# ----------------------------------------------------------------------------- judging


def judge(mode: dict[str, Any], attacks: tuple[str, ...], n: int) -> dict[str, dict[str, Any]]:
    """Per attack: did it succeed, judged by its effect where the victim shows one (a
    halted base, phantom cells in a map, an executed shutdown), else by what it received."""
    final = mode["_final"]
    stats = {r: s["stats"] for r, s in final.items()}
    published: set[str] = set()
    for s in final.values():
        published.update(s.get("published", []))

    out: dict[str, dict[str, Any]] = {}
    for k in attacks:
        t = target_of(k, n)
        rep = mode["attack_reports"].get(k, {})
        ok, ev = False, ""
        if k == "spoof-pose":
            got = from_publisher(stats[t], "pose", ATTACKS[k]["node"])
            ok, ev = got["n"] > 0, f"{t} received {got['n']} spoofed poses (max error {got['effect']} m)"
        elif k == "scan-noise":
            got = from_publisher(stats[t], "scan", ATTACKS[k]["node"])
            ok, ev = got["effect"] > 0, f"{t} received {got['n']} noise scans ({got['effect']:.0f} phantom cells in its map)"
        elif k == "cmd-flood":
            got, halted = from_publisher(stats[t], "cmd_vel", ATTACKS[k]["node"]), final[t].get("halted_s") or 0.0
            ok = halted > 0 and got["effect"] > 0  # judged by effect: it halted the base
            # the base's halt counted only when this sender's stops reached it (the held
            # flood's halted it too: a newcomer read "0 stop commands, halted 26.7 s")
            ev = f"{t} received {got['n']} foreign stop commands" + (f", halted {halted} s" if got["effect"] else "")
        elif k == "false-map":
            c = sum(s["map_from_non_team"] for s in stats.values())
            # a robot done without any of the stranger's claims (the held false map, its own
            # frontiers gone) is not counted to it
            done = sum(1 for s in final.values() if s.get("state") == "done" and s["stats"]["map_from_non_team"])
            ok, ev = c > 0, f"robots received {c} false map claims; {done} of them believed the map explored"
        elif k == "map-erase":
            # a team member's update erased and sent by the attacker's node (robot.py's
            # "map_relayed" evidence): its own sender, so another robot's late update is not its
            got = [from_publisher(s, "map_relayed", ATTACKS[k]["node"]) for s in stats.values()]
            c = int(sum(g["effect"] for g in got))
            ok, ev = c > 0, f"robots received {c} erased team map updates from {ATTACKS[k]['node']}"
        elif k == "eavesdrop":
            c = int(rep.get("messages", 0))
            read = f"{c} messages ({rep.get('bytes', 0)} B)"
            if "digests" in rep:  # ROS 2: the network may carry other attackers' messages; count the robots'
                c = sum(1 for d in rep["digests"] if d in published)
                read = f"{c} of the robots' messages ({rep.get('bytes', 0)} B read in all)"
            ok = c > 0
            ev = (f"attacker read {read} on {len(rep.get('topics', {}))} topics, "
                  f"positions of {len(rep.get('positions_read', {}))} robots, {rep.get('map_share_read', 0):.0%} of the map cells")
        elif k == "shutdown":
            reasons = [x for x in stats[t]["shutdown_reasons"] if "same name" not in x]
            ok, ev = bool(reasons), (f"{t} executed shutdown ({reasons[0]})" if reasons else f"{t} got no shutdown call")
        elif k == "hijack":
            reasons = [x for x in stats[t]["shutdown_reasons"] if "same name" in x]
            ok, ev = bool(reasons), (f"{t} was shut down by the master: {reasons[0]}" if reasons else f"{t} kept its name")
        elif k in HELD_ATTACKS:
            out[k] = _judge_held(k, t, final, mode)
            continue
        if not ok and rep.get("refused"):
            ev += f"; attacker: {rep['refused']}"
        out[k] = {"succeeded": ok, "evidence": ev}
    return out


#: a held-grant attack "succeeded" when its victim was fed for longer than this (wall s)
HELD_EXPOSURE_S = 1.0
#: ... or, for noise scans, when more than this many were believed (``consecutive`` pass
#: before any alert)
HELD_SCANS_BELIEVED = 5


def _judge_held(k: str, t: str | None, final: dict[str, Any], mode: dict[str, Any]) -> dict[str, Any]:
    """A misuse of a held grant, judged by its effect on the victim: how long it was fed
    false poses or halted, how many noise scans it marked into its map, whether the team
    stopped believing the map explored."""
    if k == "held-false-map":
        liar = t
        # a robot is fooled by the liar's claims it received: one that stopped early without
        # any (its own frontiers gone, under the other attacks) is not the false map's doing
        from_liar = {r: s["stats"].get("map_complete_claims_from", {}).get(liar, 0) for r, s in final.items() if r != liar}
        claims = sum(from_liar.values())
        fooled = {}
        for r, s in final.items():
            if r != liar and from_liar[r] and s.get("done_at") is not None:
                cov = coverage_at(mode["timeline"], s["done_at"] - mode["t0"])
                if cov < mode["coverage_target"]:
                    fooled[r] = cov
        if fooled:
            return {"succeeded": True, "evidence": f"{', '.join(sorted(fooled))} stopped exploring at "
                    f"{min(fooled.values()):.0%} coverage, believing {liar}'s claims ({claims} received)"}
        return {"succeeded": False, "evidence": f"no robot stopped before the target believing {liar}'s claims "
                f"({claims} of them received)"}
    st = final[t]["stats"]
    key = {"held-scan-noise": "scan", "held-cmd-flood": "cmd_vel", "held-replay": "pose_replayed"}.get(k, "pose")
    got = from_publisher(st, key, ATTACKS[k]["node"])
    n, last = got["n"], got["last"]
    window = round(last - got["first"], 2)
    out: dict[str, Any] = {}
    cut = ""
    # n, not the window: on a loaded host the few messages let through before the cut can
    # reach the victim in one burst (a window of 0.0 s, and a cut all the same)
    if n and mode["monitor"]["quarantines"] and last < mode["t0"] + mode["wall_s"] - 2.0:
        cut = f"; cut by the monitor {window} s after its first message"
        out["cut_after_s"] = window
    if k == "held-cmd-flood":  # every stop command holds the base HALT_S: a stream of them, the whole window
        return {**out, "succeeded": got["effect"] > 0 and window > HELD_EXPOSURE_S,
                "evidence": f"{t} obeyed {got['effect']:.0f} stop commands over {window} s{cut}"}
    if k == "held-scan-noise":
        return {**out, "succeeded": n > HELD_SCANS_BELIEVED,
                "evidence": f"{t} believed {n} noise scans over {window} s ({got['effect']:.0f} phantom cells in its map){cut}"}
    what = "replayed" if k == "held-replay" else "false"
    return {**out, "succeeded": window > HELD_EXPOSURE_S,
            "evidence": f"{t} was fed {n} {what} poses over {window} s (up to {got['effect']:.1f} m off){cut}"}


def from_publisher(stats: dict[str, Any], key: str, node: str) -> dict[str, Any]:
    """What one publisher's foreign messages of ``key`` did to a robot (the robot's
    ``by_publisher`` evidence). Where the transport does not name publishers (ROS 2),
    every foreign message is counted under "" and taken as this publisher's."""
    table = stats.get("by_publisher", {}).get(key, {})
    return table.get(node) or table.get("") or {"n": 0, "first": 0.0, "last": 0.0, "effect": 0.0}


def coverage_at(timeline: list[list[float]], wall: float) -> float:
    """The team's coverage ``wall`` seconds into the mission (the timeline's last row before)."""
    before = [row[2] for row in timeline if row[1] <= wall]
    return before[-1] if before else 0.0


# ----------------------------------------------------------------------------- the whole demo


def attacker_role(kind: str, n: int) -> str:
    if ATTACKS[kind]["as"] == "stranger":
        return "stranger (no certificate, no token)"
    if ATTACKS[kind]["as"] == "holder":
        return f"{ATTACKS[kind]['node']} on the operations host (its manager holds the grant it misuses)"
    if ATTACKS[kind]["as"] == "compromised":
        return f"robot {target_of(kind, n)}'s own explorer (granted /team/map)"
    what = {"spoof-pose": f"/{target_of(kind, n)}/pose", "map-erase": "/team/map as /mitm",
            "shutdown": f"shutdown of /{target_of(kind, n)}", "hijack": f"the name /{target_of(kind, n)}"}.get(kind, kind)
    return f"insider on {insider_host(kind, n)}'s host (manager has no grant for {what})"
