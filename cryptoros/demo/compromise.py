"""A compromised robot: its own software misuses the grants it holds.

Authorization lets these through: the messages go out under the robot's own node names,
on its own topics. What changes is their content or rate, from ``onset`` on (Unix
time). The demo robot asks this object what to publish; the monitor's datasets label
every message the robot publishes after ``onset`` on the affected topics as an attack.

* ``spoof-pose``: its base publishes random positions in the arena (seed 001's spoofed
  position);
* ``drift``: its base adds an offset that grows by 0.1 m per second (a slow drift);
* ``replay``: its base republishes its poses of five seconds ago, stamps included;
* ``scan-noise``: its base publishes laser ranges of uniform noise (seed 001's noise);
* ``cmd-flood``: its explorer adds stop commands at 200 Hz on its own ``cmd_vel``
  (seed 001's DoS, with a valid grant);
* ``false-map``: its explorer claims at 2 Hz on ``/team/map``, a topic it may publish,
  that the whole map is free and explored (seed 000's false claim, from a team member).
"""

from __future__ import annotations

import collections
import time

import numpy as np

#: kind -> (topic suffix of the robot's, publisher: "base" or "explorer")
COMPROMISES: dict[str, tuple[str, str]] = {
    "spoof-pose": ("pose", "base"),
    "drift": ("pose", "base"),
    "replay": ("pose", "base"),
    "scan-noise": ("scan", "base"),
    "cmd-flood": ("cmd_vel", "explorer"),
    "false-map": ("/team/map", "explorer"),
}
REPLAY_DELAY_S = 5.0
DRIFT_M_PER_S = 0.1
FLOOD_HZ = 200.0
FALSE_MAP_HZ = 2.0


class Compromise:
    def __init__(self, kind: str, onset: float, seed: int, arena_m: tuple[float, float]) -> None:
        if kind not in COMPROMISES:
            raise ValueError(f"unknown compromise {kind!r}; known: {', '.join(COMPROMISES)}")
        self.kind, self.onset = kind, onset
        self.rng = np.random.default_rng(seed)
        self.arena_m = arena_m
        self._history: collections.deque[tuple[float, float, float]] = collections.deque()

    def active(self, now: float | None = None) -> bool:
        return (time.time() if now is None else now) >= self.onset

    def pose(self, x: float, y: float, stamp: float) -> tuple[float, float, float]:
        """What the base publishes for a true pose (x, y) stamped ``stamp``."""
        self._history.append((x, y, stamp))
        while self._history and self._history[0][2] < stamp - 2 * REPLAY_DELAY_S:
            self._history.popleft()
        if not self.active(stamp):
            return x, y, stamp
        if self.kind == "spoof-pose":
            return float(self.rng.uniform(0, self.arena_m[0])), float(self.rng.uniform(0, self.arena_m[1])), stamp
        if self.kind == "drift":
            return x + DRIFT_M_PER_S * (stamp - self.onset), y, stamp
        if self.kind == "replay":
            old = next((h for h in reversed(self._history) if h[2] <= stamp - REPLAY_DELAY_S), self._history[0])
            return old
        return x, y, stamp

    def ranges(self, ranges: np.ndarray, low: float, high: float) -> np.ndarray:
        if self.kind != "scan-noise" or not self.active():
            return ranges
        return self.rng.uniform(low, high, len(ranges)).astype(np.float32)


__all__ = ["COMPROMISES", "FALSE_MAP_HZ", "FLOOD_HZ", "Compromise"]
