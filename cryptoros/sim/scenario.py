"""A mission: world + robots + channel + security + attacks, run to a result dict.

:func:`run` is a pure function of its :class:`SimConfig` (with ``crypto_cost=
"nominal"``): the same config gives the same result, except the ``wall`` section
(wall-clock seconds and event counts), which is kept apart for that reason.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from cryptoros.errors import ConfigError
from cryptoros.sim import attacks as A
from cryptoros.sim.battery import BatterySpec
from cryptoros.sim.channel import Channel, Radio
from cryptoros.sim.engine import Engine, SimHost
from cryptoros.sim.robot import DEAD, DONE, STATE_NAMES, Robot, RobotConfig
from cryptoros.sim.security import SecurityConfig, make_managers
from cryptoros.sim.world import FREE, OCC, UNKNOWN, Lidar, World, generate, load_map_server


@dataclass
class SimConfig:
    robots: int = 4
    seed: int = 1
    width: int = 100  # 20 m x 20 m at 0.2 m
    height: int = 100
    map_yaml: str = ""
    resolution: float = 0.2
    bases: int = 1
    attacks: tuple[str, ...] = ()
    security: SecurityConfig = field(default_factory=SecurityConfig)
    plausibility: bool = False
    coverage_target: float = 0.95
    max_time: float = 1800.0
    range_m: float = 6.0
    attacker_range_m: float = 30.0
    bitrate: float = 1e6
    loss: float = 0.0
    idle: int = 0  # robots that start idle at a base
    battery_j: float = 0.0  # 0: TurtleBot3 Burger capacity
    resume_after: float = 20.0  # a recharged robot waits this long at its base (recruitable), then resumes
    recruit: bool = True
    share_period: float = 5.0
    hello_period: float = 1.0
    lsu_period: float = 10.0
    sample_period: float = 2.0
    trace: bool = False

    def __post_init__(self) -> None:
        if self.robots < 1:
            raise ConfigError("need at least one robot")
        for a in self.attacks:
            if a not in A.ATTACKS:
                raise ConfigError(f"unknown attack {a!r}; one of {', '.join(A.ATTACKS)}")

    def as_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["attacks"] = list(self.attacks)
        d["security"] = {**dataclasses.asdict(self.security), "label": self.security.label}
        return d


def _start_cells(world: World, n: int, base_index: int) -> list[tuple[int, int]]:
    """Distinct free cells around a base, nearest first."""
    br, bc = world.bases[base_index % len(world.bases)]
    free_r, free_c = np.nonzero(world.explorable())
    order = np.lexsort((free_c, free_r, (free_r - br) ** 2 + (free_c - bc) ** 2))
    return [(int(free_r[k]), int(free_c[k])) for k in order[: 2 * n + 1 : 2]][:n]


def _centre_cell(world: World) -> tuple[int, int]:
    H, W = world.shape
    free_r, free_c = np.nonzero(world.explorable())
    k = int(np.argmin((free_r - H // 2) ** 2 + (free_c - W // 2) ** 2))
    return int(free_r[k]), int(free_c[k])


class Mission:
    def __init__(self, cfg: SimConfig, *, world: World | None = None, starts: list[tuple[int, int]] | None = None) -> None:
        """``world`` and ``starts`` (one cell per robot) override the generated ones."""
        self.cfg = cfg
        if world is not None:
            self.world = world
        elif cfg.map_yaml:
            self.world = load_map_server(cfg.map_yaml, n_bases=cfg.bases)
        else:
            self.world = generate(cfg.seed, cfg.width, cfg.height, resolution=cfg.resolution, n_bases=cfg.bases)
        w = self.world
        self.engine = Engine()
        master = np.random.default_rng(cfg.seed)
        self.channel = Channel(np.random.default_rng(master.integers(1 << 62)), bitrate=cfg.bitrate, loss=cfg.loss, trace=cfg.trace)
        self.hosts: dict[str, SimHost] = {}
        self.channel.hosts = self.hosts  # type: ignore[attr-defined]
        self.observed = np.zeros(w.shape, dtype=bool)
        self.lidar = Lidar(3.5 / w.resolution)
        names = [f"r{i}" for i in range(cfg.robots)]
        attackers = [(f"mal{i}", kind) for i, kind in enumerate(cfg.attacks)]
        rngs = {n: np.random.default_rng(master.integers(1 << 62)) for n in names + [a for a, _ in attackers]}
        insiders = [a for a, k in attackers if k in A.INSIDER]
        managers, self.roster, self.costs = make_managers(names + [a for a, _ in attackers], cfg.security, cfg.seed, rngs, insiders=insiders)
        if cfg.security.enabled:  # outsiders are not in the roster
            for a, k in attackers:
                if k not in A.INSIDER:
                    self.roster.ec_private.pop(a, None)
                    self.roster.ec_public.pop(a, None)
                    managers[a]._priv = None
        spec = BatterySpec(capacity_j=cfg.battery_j) if cfg.battery_j > 0 else BatterySpec()
        rcfg = RobotConfig(resolution=w.resolution, hello_period=cfg.hello_period, lsu_period=cfg.lsu_period, share_period=cfg.share_period,
                           recruit=cfg.recruit, plausibility=cfg.plausibility, battery=spec, resume_after=cfg.resume_after)
        per_base: dict[int, int] = {}
        for i, n in enumerate(names):
            b = i % len(w.bases)
            per_base[b] = per_base.get(b, 0) + 1
        fixed = starts
        starts_by_base: dict[int, list] = {b: _start_cells(w, k, b) for b, k in per_base.items()}
        self.robots: dict[str, Robot] = {}
        for i, n in enumerate(names):
            b = i % len(w.bases)
            cell = starts_by_base[b].pop(0) if fixed is None else fixed[i]
            host = SimHost(n, self.engine, self.channel, w, self.lidar, self.observed, cell, range_m=cfg.range_m)
            robot = Robot(n, host, rngs[n], start=cell, shape=w.shape, bases=w.bases, config=rcfg, security=managers[n], idle=i >= cfg.robots - cfg.idle)
            host.robot = robot
            self.hosts[n] = host
            self.robots[n] = robot
            self.channel.add(Radio(n, host.position, cfg.range_m, up=host.up))
        self.attackers: dict[str, A.Attacker] = {}
        centre = _centre_cell(w)
        for a, kind in attackers:
            host = SimHost(a, self.engine, self.channel, w, self.lidar, self.observed, centre, honest=False, range_m=cfg.attacker_range_m)
            att = A.make(kind, a, host, rngs[a], managers[a], centre, w.shape, w.resolution)
            host.robot = att
            self.hosts[a] = host
            self.attackers[a] = att
            self.channel.add(Radio(a, host.position, cfg.attacker_range_m, up=host.up, rx_range_m=cfg.attacker_range_m))
        self.explorable = w.explorable()
        self.n_explorable = int(self.explorable.sum())
        self.timeline: list[tuple[float, float]] = []
        self.task_time: float | None = None
        self.end_reason = ""
        self._quiet_since: float | None = None

    def coverage(self) -> float:
        return float(np.count_nonzero(self.observed & self.explorable)) / max(1, self.n_explorable)

    def _sample(self) -> None:
        now = self.engine.now
        cov = self.coverage()
        self.timeline.append((round(now, 3), round(cov, 5)))
        if self.task_time is None and cov >= self.cfg.coverage_target:
            self.task_time = now
            self.end_reason = "coverage_target"
        active = any(r.active for r in self.robots.values())
        if active:
            self._quiet_since = None
        elif self._quiet_since is None:
            self._quiet_since = now
        if self.task_time is None and self._quiet_since is not None and now - self._quiet_since >= 10.0:
            if any(r.state == DONE for r in self.robots.values()):
                self.end_reason = "robots_believe_done"
            elif any(r.out_of_reach for r in self.robots.values()):
                self.end_reason = "frontier_out_of_reach"  # every frontier is beyond what a full battery can reach
            else:
                self.end_reason = "no_robot_active"
        if all(r.state == DEAD for r in self.robots.values()):
            self.end_reason = "all_batteries_empty"
        if not self.end_reason:
            self.engine.after(self.cfg.sample_period, self._sample)

    def run(self, progress: Callable[[float, float], None] | None = None) -> dict[str, Any]:
        t0 = time.perf_counter()
        for r in self.robots.values():
            r.start()
        for a in self.attackers.values():
            a.start()
        self.engine.after(0.0, self._sample)
        horizon = self.cfg.max_time
        step = max(5.0, horizon / 200)
        t = 0.0
        while t < horizon and not self.end_reason:
            t = min(horizon, t + step)
            self.engine.run_until(t, stop=lambda: bool(self.end_reason))
            if progress is not None:
                progress(self.engine.now, self.coverage())
        if not self.end_reason:
            self.end_reason = "max_time"
            self.timeline.append((round(self.engine.now, 3), round(self.coverage(), 5)))
        wall = time.perf_counter() - t0
        return self.result(wall)

    # -- metrics ---------------------------------------------------------------------------

    def _map_quality(self, known: np.ndarray) -> dict[str, float]:
        truth = self.world.occupied
        k = known != UNKNOWN
        n = int(k.sum())
        correct = int(np.count_nonzero(k & ((known == OCC) == truth)))
        believed_free = int(np.count_nonzero((known == FREE) & self.explorable))
        return {
            "known_cells": n,
            "accuracy": round(correct / n, 5) if n else 1.0,
            "believed_coverage": round(believed_free / max(1, self.n_explorable), 5),
            "false_free": int(np.count_nonzero((known == FREE) & truth)),
        }

    def result(self, wall: float) -> dict[str, Any]:
        st = self.channel.stats
        robots = {}
        rejected: dict[str, int] = {}
        energy_total = 0.0
        cpu_total = 0.0
        ops: dict[str, int] = {}
        for n, r in self.robots.items():
            for k, v in r.rejected.items():
                rejected[k] = rejected.get(k, 0) + v
            used = sum(r.battery.used.values())
            energy_total += used
            cpu_total += r.security.cpu_total
            for k, v in r.security.ops.items():
                ops[k] = ops.get(k, 0) + v
            robots[n] = {
                "state": STATE_NAMES[r.state],
                "travelled_m": round(r.travelled_m, 3),
                "energy_used_j": round(used, 3),
                "energy_by_kind_j": {k: round(v, 3) for k, v in r.battery.used.items()},
                "battery_left": round(r.battery.fraction, 5),
                "frames_unloaded": r.buffer.unloaded,
                "frames_buffered": r.buffer.frames,
                "crypto_cpu_s": round(r.security.cpu_total, 6),
                "counters": dict(r.counters),
                "rejected": dict(sorted(r.rejected.items())),
                "map": {**self._map_quality(r.belief.known),
                        "own_coverage": round(int(np.count_nonzero((r.belief.own == FREE) & self.explorable)) / max(1, self.n_explorable), 5)},
            }
        lost_total = sum(st.lost.values())
        attack: dict[str, Any] = {}
        team_known = int(np.count_nonzero(self.observed & self.explorable))
        for a in self.attackers.values():
            rep = a.report()
            if isinstance(a, A.Eavesdropper):
                ek = (a.belief.known != UNKNOWN) & self.explorable & self.observed
                rep["map_share"] = round(int(ek.sum()) / max(1, team_known), 5)
                position_msgs = sum(st.sent_by_type.get(t, 0) for t in ("Hello", "LinkStateUpdate", "MapUpdate", "RecruitPacket"))
                rep["positions_share"] = round(a.stats["positions_read"] / max(1, a.stats["frames_heard"]), 5)
                rep["position_samples"] = len(a.positions)
                _ = position_msgs
            attack[a.name] = rep
        accs = [v["map"]["accuracy"] for v in robots.values()]
        completed = self.task_time is not None
        return {
            "config": self.cfg.as_dict(),
            "world": {"name": self.world.name, "shape": list(self.world.shape), "resolution": self.world.resolution,
                      "explorable_cells": self.n_explorable, "bases": [list(b) for b in self.world.bases]},
            "outcome": {
                "completed": completed,
                "task_time_s": round(self.task_time, 3) if completed else None,
                "end_time_s": round(self.engine.now, 3),
                "end_reason": self.end_reason,
                "coverage": round(self.coverage(), 5),
                "mean_map_accuracy": round(float(np.mean(accs)), 5),
                "robots_believing_done": sum(1 for r in self.robots.values() if r.state == DONE),
            },
            "coverage_over_time": [list(x) for x in self.timeline],
            "packets": {
                "sent": st.sent,
                "receptions": st.receptions,
                "delivered": st.delivered,
                "lost": lost_total,
                "lost_by_reason": dict(sorted(st.lost.items())),
                "rejected": sum(rejected.values()),
                "rejected_by_reason": dict(sorted(rejected.items())),
                "bytes_sent": st.bytes_sent,
                "bytes_delivered": st.bytes_delivered,
                "sent_by_type": dict(sorted(st.sent_by_type.items())),
                "sent_by_honest": sum(v for k, v in st.sent_by_radio.items() if k in self.robots),
            },
            "energy": {"total_j": round(energy_total, 3), "mean_per_robot_j": round(energy_total / len(self.robots), 3)},
            "crypto": {"label": self.cfg.security.label, "cpu_s_total": round(cpu_total, 6), "ops": dict(sorted(ops.items())), "costs": self.costs.as_dict()},
            "recruit": {
                "requests": sum(r.counters["recruit_requests"] for r in self.robots.values()),
                "recruited": sum(r.counters["recruited"] for r in self.robots.values()),
                "returns_home": sum(r.counters["returns_home"] for r in self.robots.values()),
                "charges": sum(r.counters["charges"] for r in self.robots.values()),
                "resumed": sum(r.counters["resumed"] for r in self.robots.values()),
            },
            "robots": robots,
            "attack": attack,
            "wall": {"seconds": round(wall, 3), "events": self.engine.events},
        }


def run(cfg: SimConfig, progress: Callable[[float, float], None] | None = None) -> dict[str, Any]:
    return Mission(cfg).run(progress)


def deterministic(result: dict[str, Any]) -> dict[str, Any]:
    """The result without wall-clock fields (what must repeat for a seed)."""
    out = dict(result)
    out.pop("wall", None)
    return out
