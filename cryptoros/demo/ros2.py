"""``cryptoros demo --ros 2``: the same mission with the robots as rclpy nodes (ROS 2 Jazzy).

The robots (:mod:`cryptoros.demo.ros2_robot`) and attackers
(:mod:`cryptoros.demo.ros2_attackers`) run under the ROS 2 venv's python
(``scripts/ros2-venv``; ``$CRYPTOROS_ROS2_PYTHON`` to point elsewhere) with this
package on their ``PYTHONPATH``. Every DDS participant is localhost-only
(``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``); domains stand for machines:

==============  ===========================  ======================================
mode            where the robots are         what connects them
==============  ===========================  ======================================
plain           one shared domain ``D``      DDS itself: every participant on ``D``
                                             (an attacker too) reaches every robot
protected       robot N on domain ``D+1+N``  only the robots' interceptors (``ros2``
                                             role, mutual TLS, tokens, grants);
                                             domain ``D`` (the network) is empty
==============  ===========================  ======================================

Interceptor N listens on 127.0.0.(11+N) like the ROS 1 demo's hosts and has every
other robot's interceptor as a peer. The mission, its clock, the evidence and the
judging are the ROS 1 demo's (:mod:`cryptoros.demo.run`).
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import subprocess
import time
from pathlib import Path
from typing import Any

from cryptoros.demo.attackers import ATTACKS, ROS2_ATTACKS, insider_host, target_of
from cryptoros.demo.robot import SHORT
from cryptoros.demo.run import DemoError, Graph, Mission, robot_addr
from cryptoros.lab.policy import policy_yaml

WHAT = {"eavesdrop": "every topic read (DDS discovery, raw subscriptions of any type)"}
TEAM_TYPE = "std_msgs/msg/UInt8MultiArray"
PRESENCE = ("/team/presence", "std_msgs/msg/String")
#: how long an attacker waits for DDS to match it with its victims before it reports armed anyway
ARM_TIMEOUT = 60.0
READY_CHECK = "import rclpy, std_msgs.msg, geometry_msgs.msg, sensor_msgs.msg, cryptography, rosbags, defusedxml, numpy"


def policy(n: int) -> str:
    """Each robot's manager may publish and subscribe the team topics, nothing else.
    A robot's own pose, scan and command topics (``/rN/*``) are also ``[ros2] local`` on
    its interceptor: they stay on its domain without a denial for each of them."""
    topics = [(f"/team/{short}", TEAM_TYPE) for short in SHORT.values()] + [PRESENCE]
    return policy_yaml({f"r{i}": {action: [(f"/r{i}", topic, ty) for topic, ty in topics]
                                  for action in ("publish", "subscribe")} for i in range(n)})


@functools.cache
def ros2_python() -> Path:
    """The ROS 2 venv's python, checked once to import what the robots need (one clear error)."""
    from cryptoros.ros2 import default_ros2_python

    python = default_ros2_python()
    if not python.exists():
        raise DemoError(f"{python} does not exist: create the ROS 2 venv with scripts/ros2-venv "
                        "(or set CRYPTOROS_ROS2_PYTHON)")
    try:
        check = subprocess.run([str(python), "-c", READY_CHECK], capture_output=True, text=True, timeout=120,
                               env=ros2_env(0, None))
    except subprocess.TimeoutExpired:
        raise DemoError(f"{python} did not import rclpy within 120 s") from None
    if check.returncode != 0:
        last = (check.stderr.strip().splitlines() or ["?"])[-1]
        raise DemoError(f"{python} cannot run the ROS 2 robots ({last}); refresh the venv with scripts/ros2-venv")
    return python


def ros2_env(domain: int, pythonpath: Path | None) -> dict[str, str]:
    from cryptoros.lab.network import clean_env

    env = {k: v for k, v in clean_env().items() if not k.startswith(("_ROS_WHEELS", "RMW_"))}
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    from cryptoros.ros2.profile import localhost_env

    env = localhost_env(env)  # a robot's domain stays on its host
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    return env


def base_domain(robots: int = 8) -> int:
    """``D``: the shared (network) domain; robots use D+1 .. D+robots (all within 0..98, below the ephemeral ports),
    where no process on this host has a port bound now: another session's participants on
    one of these domains (a test, a second demo) would match the robots' own."""
    from cryptoros.ros2.exposure import free_domains

    return free_domains(robots + 1, 10 + (os.getpid() * 7) % 80)[0]


def attacker_role(kind: str, n: int) -> str:
    if ATTACKS[kind]["as"] == "stranger":
        return "stranger on the network (no certificate, no token): the robots' DDS is localhost-only, so only the interceptors' TLS ports are left"
    what = {"spoof-pose": f"/{target_of(kind, n)}/pose"}.get(kind, kind)
    return f"insider node on {insider_host(kind, n)}'s domain (its manager has no grant for {what})"


class Ros2Mission(Mission):
    """One mission of ``cryptoros demo --ros 2``."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.python = ros2_python()
        self.base = base_domain(len(self.team))
        # the robots import this package from a directory holding only it (not the main
        # venv's site-packages: the ROS 2 venv brings its own numpy and cryptography)
        self.pythonpath = self.dir / "pylib"
        self.pythonpath.mkdir(exist_ok=True)
        link = self.pythonpath / "cryptoros"
        if not link.exists():
            import cryptoros

            link.symlink_to(Path(cryptoros.__file__).resolve().parent, target_is_directory=True)

    def robot_domain(self, robot: str) -> int:
        return self.base if self.mode == "plain" else self.base + 1 + self.team.index(robot)

    def _plain(self):  # type: ignore[no-untyped-def]
        yield Graph(robot_master={}, robot_ip={}, stranger_master="", insider_master={}, insider_ip={})

    def _protected(self):  # type: ignore[no-untyped-def]
        from cryptoros.lab.network import lab_network

        hosts = {r: robot_addr(i) for i, r in enumerate(self.team)}
        with lab_network(self.dir / "net", policy(len(self.team)), hosts=hosts, master="none", metrics=True,
                           new_session=True, ros2={r: self.robot_domain(r) for r in self.team},
                           ros2_python=self.python, ros2_local={r: [f"/{r}/*"] for r in self.team}) as net:
            ports = [(h.address, h.public_port) for h in net.hosts.values()]
            ports += [("127.0.0.1", h.metrics_port) for h in net.hosts.values() if h.metrics_port]
            yield Graph(robot_master={}, robot_ip={}, stranger_master="", insider_master={}, insider_ip={},
                        interceptors=net.hosts, ports=ports)

    def _start_robots(self, g: Graph) -> dict[str, subprocess.Popen]:
        procs = {}
        for r in self.team:
            cfg = {"name": r, "team": self.team, "seed": self.opts.seed, "width": self.opts.width,
                   "height": self.opts.height, "scale": self.opts.scale, "status": str(self.dir / f"{r}.status.json"),
                   "go": str(self.dir / "go.json"), "connect_timeout": 40, "domain": self.robot_domain(r)}
            path = self.dir / f"{r}.json"
            path.write_text(json.dumps(cfg))
            procs[r] = self.children.start([str(self.python), "-m", "cryptoros.demo.ros2_robot", str(path)],
                                           self.dir / f"{r}.log", ros2_env(self.robot_domain(r), self.pythonpath))
        return procs

    def _start_attack(self, kind: str, g: Graph) -> subprocess.Popen:
        n = len(self.team)
        stranger = ATTACKS[kind]["as"] == "stranger"
        domain = self.base if self.mode == "plain" or stranger else self.robot_domain(insider_host(kind, n))
        doors = [[h.address, h.public_port] for h in g.interceptors.values()] if stranger and self.mode == "protected" else []
        cfg = {"kind": kind, "domain": domain, "target": target_of(kind, n), "team": self.team, "width": self.opts.width,
               "height": self.opts.height, "duration": self.opts.seconds, "doors": doors,
               "report": str(self.dir / f"attack-{kind}.report.json"),
               # the arm/fire handshake (see _arm_attacks); on the shared domain of plain mode
               # the attacker is armed only once DDS has matched it with its victims
               "armed": str(self.dir / f"attack-{kind}.armed.json"), "fire": str(self.dir / "attacks-fire.json"),
               "expect_victims": self.mode == "plain", "arm_timeout": ARM_TIMEOUT}
        path = self.dir / f"attack-{kind}.json"
        path.write_text(json.dumps(cfg))
        return self.children.start([str(self.python), "-m", "cryptoros.demo.ros2_attackers", str(path)],
                                   self.dir / f"attack-{kind}.log", ros2_env(domain, self.pythonpath))

    def _arm_attacks(self, g: Graph) -> dict[str, subprocess.Popen]:
        """Every attacker started before the clock and waited for until it reports itself
        armed: its DDS endpoints created and, on plain mode's shared domain, matched with
        its victims' (discovery of five new participants takes seconds on a cold machine;
        the attacks must neither depend on that nor on each other's timing)."""
        (self.dir / "attacks-fire.json").unlink(missing_ok=True)
        procs = {k: self._start_attack(k, g) for k in self.opts.attacks}
        deadline = time.monotonic() + ARM_TIMEOUT + 30
        waiting = set(procs)
        while waiting:
            for k in sorted(waiting):
                if (self.dir / f"attack-{k}.armed.json").exists():
                    waiting.discard(k)
                elif procs[k].poll() is not None:
                    raise DemoError(f"attacker {k} exited with {procs[k].returncode} before it was armed "
                                    f"({self.dir / f'attack-{k}.log'})")
            if waiting and time.monotonic() > deadline:
                raise DemoError(f"attackers {sorted(waiting)} not armed within {ARM_TIMEOUT + 30:.0f} s ({self.dir})")
            time.sleep(0.1)
        return procs

    def _fire_attacks(self, g: Graph, armed: dict[str, subprocess.Popen]) -> dict[str, subprocess.Popen]:
        fire = self.dir / "attacks-fire.json"
        tmp = fire.with_suffix(".tmp")
        tmp.write_text(json.dumps({"at": time.time()}))
        tmp.replace(fire)
        return armed

    def _mission(self, g: Graph, setup_s: float) -> dict[str, Any]:
        res = super()._mission(g, setup_s)
        res["domains"] = {r: self.robot_domain(r) for r in self.team} | {"network": self.base}
        res["deny_log"] = deny_lines(g)
        return res


def deny_lines(g: Graph, limit: int = 40) -> dict[str, list[str]]:
    """Each interceptor's distinct ``DENY`` log lines (what was refused, by whom, why)."""
    out: dict[str, list[str]] = {}
    for name, host in g.interceptors.items():
        seen: list[str] = []
        with contextlib.suppress(OSError):
            for line in host.logs().splitlines():
                if " DENY " in line:
                    text = line.split(" DENY ", 1)[1].strip()
                    if text not in seen:
                        seen.append(text)
        if seen:
            out[name] = seen[:limit]
    return out


__all__ = ["ROS2_ATTACKS", "Ros2Mission", "attacker_role", "policy", "ros2_python"]
