"""Channel: a broadcast radio with range, delays, collisions and random loss.

A transmission of ``n`` bytes from a sender reaches every radio within the sender's
range. At each receiver it occupies ``[t + d/c, t + d/c + 8n/bitrate]`` (propagation
then transmission delay). Two receptions overlapping in time at one receiver collide
and both are lost there (no capture effect); a receiver that is itself transmitting
during a reception loses it too (half duplex). Independently each reception is lost
with probability ``loss``. Radios are found with a spatial hash of cell size = range.

Every frame is traced: ``sent`` once, then per receiver ``delivered`` or ``lost`` with
the reason (``collision``, ``half_duplex``, ``random``, ``receiver_down``). Counters
are always kept; the full per-reception trace only when ``trace=True``.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from cryptoros.sim.packets import Frame

C_LIGHT = 3.0e8


@dataclass
class Radio:
    name: str
    position: Callable[[], tuple[float, float]]  # metres
    range_m: float
    up: Callable[[], bool] = lambda: True
    rx_range_m: float = 0.0  # a sensitive receiver (attacker's antenna) hears farther
    busy_until: float = 0.0
    # reception intervals still relevant: list of [start, end, reception]
    receiving: list = field(default_factory=list)


@dataclass
class Reception:
    frame: Frame
    receiver: str
    start: float
    end: float
    lost: str = ""


@dataclass
class ChannelStats:
    sent: int = 0
    bytes_sent: int = 0
    deferred: int = 0
    receptions: int = 0
    delivered: int = 0
    bytes_delivered: int = 0
    lost: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    sent_by_type: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    sent_by_radio: dict[str, int] = field(default_factory=lambda: defaultdict(int))


class Channel:
    def __init__(self, rng: np.random.Generator, *, bitrate: float = 1e6, loss: float = 0.0, trace: bool = False) -> None:
        self.rng = rng
        self.bitrate = bitrate
        self.loss = loss
        self.radios: dict[str, Radio] = {}
        self.stats = ChannelStats()
        self.trace_on = trace
        self.trace: list[tuple] = []
        self._max_range = 0.0

    def add(self, radio: Radio) -> None:
        self.radios[radio.name] = radio
        self._max_range = max(self._max_range, radio.range_m, radio.rx_range_m)

    def _grid(self) -> dict[tuple[int, int], list[Radio]]:
        cell = self._max_range
        grid: dict[tuple[int, int], list[Radio]] = defaultdict(list)
        for r in self.radios.values():
            x, y = r.position()
            grid[(int(x // cell), int(y // cell))].append(r)
        return grid

    def transmit(self, now: float, frame: Frame, schedule: Callable[[float, Reception], None]) -> float:
        """Put ``frame`` on the air at ``now``; ``schedule(t, reception)`` is called for
        each receiver at its end-of-reception time. Returns the transmission time."""
        sender = self.radios[frame.sender]
        tx = 8.0 * frame.size / self.bitrate
        st = self.stats
        st.sent += 1
        st.bytes_sent += frame.size
        st.sent_by_type[frame.typename.split("/")[-1]] += 1
        st.sent_by_radio[frame.sender] += 1
        if self.trace_on:
            self.trace.append((now, "sent", frame.sender, "", frame.typename, frame.size, ""))
        # carrier sense: a radio sends one frame at a time and waits for what it is
        # hearing to end (plus a random backoff); hidden terminals still collide
        start_tx = max(now, sender.busy_until)
        heard = [r.end for r in sender.receiving if r.start <= start_tx < r.end]
        if heard:
            start_tx = max(heard) + float(self.rng.random()) * 2e-3
            st.deferred += 1
        sender.busy_until = start_tx + tx
        for other in sender.receiving:  # half duplex: what it was hearing is lost
            if other.start < start_tx + tx and start_tx < other.end and not other.lost:
                other.lost = "half_duplex"
        sx, sy = sender.position()
        cell = self._max_range
        gx, gy = int(sx // cell), int(sy // cell)
        grid = self._grid_cache(now)
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for r in grid.get((gx + dx, gy + dy), ()):
                    if r is sender:
                        continue
                    rx, ry = r.position()
                    d = math.hypot(rx - sx, ry - sy)
                    if d > sender.range_m and d > r.rx_range_m:
                        continue
                    start = start_tx + d / C_LIGHT
                    rec = Reception(frame, r.name, start, start + tx)
                    self._check_collision(r, rec)
                    if r.busy_until > start and not rec.lost:
                        rec.lost = "half_duplex"
                    st.receptions += 1
                    schedule(rec.end, rec)
        return start_tx + tx - now

    def _grid_cache(self, now: float) -> dict[tuple[int, int], list[Radio]]:
        # robots move at ~0.2 m/s: a grid refreshed every 0.5 s misplaces nobody by
        # more than a few centimetres compared with a range of metres; the exact
        # distance is always checked against the current position.
        key = math.floor(now * 2)
        if getattr(self, "_gkey", None) != key:
            self._gkey = key
            self._g = self._grid()
        return self._g

    def _check_collision(self, r: Radio, rec: Reception) -> None:
        keep = []
        for other in r.receiving:
            if other.end <= rec.start:
                continue  # finished before this one starts: cannot overlap any more
            keep.append(other)
            if other.start < rec.end and rec.start < other.end:
                if not other.lost:
                    other.lost = "collision"
                rec.lost = "collision"
        keep.append(rec)
        r.receiving = keep

    def finish(self, rec: Reception) -> bool:
        """At end of reception: True when delivered. Records the outcome."""
        r = self.radios[rec.receiver]
        if not rec.lost and not r.up():
            rec.lost = "receiver_down"
        if not rec.lost and self.loss > 0 and self.rng.random() < self.loss:
            rec.lost = "random"
        st = self.stats
        if rec.lost:
            st.lost[rec.lost] += 1
        else:
            st.delivered += 1
            st.bytes_delivered += rec.frame.size
        if self.trace_on:
            self.trace.append((rec.end, "lost" if rec.lost else "delivered", rec.frame.sender, rec.receiver, rec.frame.typename, rec.frame.size, rec.lost))
        return not rec.lost
