"""One ``cryptoros demo`` run: each mode's mission (ROS 1: :mod:`cryptoros.demo.run`,
ROS 2: :mod:`cryptoros.demo.ros2`), judged, with what it left behind checked.

Kept apart from both missions so neither imports the other's module back.
"""

from __future__ import annotations

import socket
import tempfile
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable

from cryptoros.demo import ros2
from cryptoros.demo.attackers import ATTACKS, target_of
from cryptoros.demo.run import ALL_ATTACKS, Children, DemoError, DemoOptions, Mission, attacker_role, judge


def run_demo(opts: DemoOptions, progress: Callable[[dict[str, Any]], None] = lambda _e: None,
             note: Callable[[str], None] = lambda _m: None) -> dict[str, Any]:
    if opts.robots < 2:
        raise DemoError("the demo needs at least 2 robots")
    mission_class, role, what = Mission, attacker_role, {}
    if opts.ros == 2:
        mission_class, role, what = ros2.Ros2Mission, ros2.attacker_role, ros2.WHAT
        known = ros2.ROS2_ATTACKS
    elif opts.ros == 1:
        known = ALL_ATTACKS
    else:
        raise DemoError(f"ros must be 1 or 2, not {opts.ros}")
    for a in opts.attacks:
        if a not in known:
            raise DemoError(f"unknown attack {a!r} for ROS {opts.ros}; one of {', '.join(known)}")
    workdir = Path(opts.workdir) if opts.workdir else Path(tempfile.mkdtemp(prefix="cryptoros-demo-"))
    workdir.mkdir(parents=True, exist_ok=True)
    children = Children()
    result: dict[str, Any] = {"config": {**asdict(opts), "attacks": list(opts.attacks), "modes": list(opts.modes)},
                              "workdir": str(workdir), "modes": {}, "attacks": {}}
    try:
        for mode in opts.modes:
            note(f"{mode}: starting {'the master' if mode == 'plain' else 'PKI, authorization server, master and interceptors'}"
                 f" and {opts.robots} robots")
            m = mission_class(opts, mode, workdir, children, progress)
            res = m.run()
            res["judged"] = judge(res, opts.attacks, opts.robots)
            result["modes"][mode] = res
        for k in opts.attacks:
            entry = {"seed": ATTACKS[k]["seed"],
                     "what": what.get(k, ATTACKS[k]["what"]).format(t=target_of(k, opts.robots) or ""),
                     "protected_attacker": role(k, opts.robots)}
            for mode, res in result["modes"].items():
                entry[mode] = res["judged"][k]
            result["attacks"][k] = entry
    finally:
        children.kill_all()
    for res in result["modes"].values():
        res.pop("_final", None)
    result["children_started"] = len(children.procs)
    result["leftover_children"] = [p.pid for p in children.procs if p.poll() is None]
    result["ports_still_open"] = [list(p) for res in result["modes"].values() for p in free_after(res.get("ports", []))]
    return result


def free_after(ports: list[tuple[str, int]]) -> list[tuple[str, int]]:
    busy = []
    for host, port in ports:
        with socket.socket() as s:
            s.settimeout(0.3)
            if s.connect_ex((host, port)) == 0:
                busy.append((host, port))
    return busy


__all__ = ["free_after", "run_demo"]
