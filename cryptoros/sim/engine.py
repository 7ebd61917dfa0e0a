"""Discrete-event engine: one driver of the transport-independent robots.

A heap of ``(time, order, callback)`` drives everything; ``order`` is a counter so
equal times run in scheduling order and a run is a pure function of its seed. Each
robot (and attacker) gets a :class:`SimHost` implementing
:class:`cryptoros.sim.robot.Host` on top of the engine, the channel and the world.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from cryptoros.sim.channel import Channel, Reception
from cryptoros.sim.packets import Frame
from cryptoros.sim.world import Lidar, World


class Engine:
    def __init__(self) -> None:
        self.now = 0.0
        self._heap: list[tuple[float, int, Callable[[], None]]] = []
        self._order = 0
        self.events = 0

    def at(self, t: float, fn: Callable[[], None]) -> None:
        self._order += 1
        heapq.heappush(self._heap, (t, self._order, fn))

    def after(self, delay: float, fn: Callable[[], None]) -> None:
        self.at(self.now + max(0.0, delay), fn)

    def run_until(self, t_end: float, stop: Callable[[], bool] | None = None) -> None:
        heap = self._heap
        while heap and heap[0][0] <= t_end:
            t, _, fn = heapq.heappop(heap)
            self.now = t
            self.events += 1
            fn()
            if stop is not None and stop():
                return
        self.now = max(self.now, t_end) if not heap or heap[0][0] > t_end else self.now


@dataclass
class SimHost:
    """Host of one robot in the simulator."""

    name: str
    engine: Engine
    channel: Channel
    world: World
    lidar: Lidar
    observed: np.ndarray  # team ground-truth coverage (metrics only, robots never read it)
    cell: tuple[int, int]
    robot: Any = None
    honest: bool = True
    range_m: float = 8.0

    def now(self) -> float:
        return self.engine.now

    def call_later(self, delay: float, fn: Callable[[], None]) -> None:
        self.engine.after(delay, fn)

    def broadcast(self, typename: str, data: bytes) -> None:
        self.channel.transmit(self.engine.now, Frame(self.name, typename, data), self._deliver_at)

    def _deliver_at(self, t: float, rec: Reception) -> None:
        self.engine.at(t, lambda: self._deliver(rec))

    def _deliver(self, rec: Reception) -> None:
        hosts = self.channel.hosts
        if self.channel.finish(rec):
            target = hosts[rec.receiver].robot
            if target is not None:
                target.on_frame(rec.frame)

    def scan(self) -> tuple[np.ndarray, np.ndarray]:
        r, c = self.robot.cell
        flat, occ = self.lidar.scan(self.world.occupied, r, c)
        if self.honest:
            self.observed.flat[flat] = True
        return flat, occ

    def move(self, cell: tuple[int, int]) -> bool:
        if self.world.occupied[cell]:
            return False
        self.cell = cell
        return True

    def position(self) -> tuple[float, float]:
        r, c = self.robot.cell
        res = self.world.resolution
        return (c * res, r * res)

    def up(self) -> bool:
        return self.robot is not None and self.robot.alive()
