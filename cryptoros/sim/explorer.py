"""Explorer: the robot's belief map and frontier-based exploration on it.

:class:`Belief` keeps what this robot observed itself (``own``) apart from what its
neighbours told it (the latest shared map of each peer); ``known`` is the union, own
observations first, then occupied over free over unknown. A peer's newer map replaces
its older one, so a peer can also *remove* knowledge (which is what an attacker who
erases map data exploits).

:class:`Explorer` plans on ``known`` with a numpy wavefront (breadth-first levels,
4-connected) in a window around the robot that grows only when needed: it picks the
frontier (a known free cell next to an unknown one) with the lowest cost, where cost
is path length plus a penalty for being close to where other robots are or are
heading, so a team spreads out instead of exploring the same room.
"""

from __future__ import annotations

import numpy as np

from cryptoros.sim.world import FREE, OCC, UNKNOWN

Cell = tuple[int, int]


class Belief:
    def __init__(self, shape: tuple[int, int]) -> None:
        self.shape = shape
        self.own = np.full(shape, UNKNOWN, dtype=np.int8)
        self.known = np.full(shape, UNKNOWN, dtype=np.int8)
        self.peers: dict[str, tuple[int, int, np.ndarray, int]] = {}  # id -> r0, c0, data, n_known
        self.bbox: list[int] | None = None  # own observations: rmin, rmax, cmin, cmax
        self.version = 0  # bumped whenever known changes

    def observe(self, flat: np.ndarray, occupied: np.ndarray) -> None:
        if flat.size == 0:
            return
        vals = np.where(occupied, OCC, FREE).astype(np.int8)
        self.own.flat[flat] = vals
        self.known.flat[flat] = vals
        w = self.shape[1]
        rows, cols = flat // w, flat % w
        rmin, rmax, cmin, cmax = int(rows.min()), int(rows.max()), int(cols.min()), int(cols.max())
        if self.bbox is None:
            self.bbox = [rmin, rmax, cmin, cmax]
        else:
            b = self.bbox
            b[0], b[1], b[2], b[3] = min(b[0], rmin), max(b[1], rmax), min(b[2], cmin), max(b[3], cmax)
        self.version += 1

    def mark(self, cell: Cell, value: int) -> None:
        self.own[cell] = value
        self.known[cell] = value
        self.version += 1

    def own_patch(self) -> tuple[int, int, np.ndarray]:
        """Bounding box of own observations: (row0, col0, int8 array copy)."""
        if self.bbox is None:
            return 0, 0, np.zeros((0, 0), dtype=np.int8)
        r0, r1, c0, c1 = self.bbox
        return r0, c0, self.own[r0 : r1 + 1, c0 : c1 + 1].copy()

    def merge_peer(self, peer: str, r0: int, c0: int, data: np.ndarray) -> int:
        """Replace ``peer``'s shared map; return how many cells became newly known."""
        h, w = data.shape
        H, W = self.shape
        if r0 < 0 or c0 < 0 or r0 + h > H or c0 + w > W:
            return 0
        n_known = int(np.count_nonzero(data != UNKNOWN))
        prev = self.peers.get(peer)
        self.peers[peer] = (r0, c0, data, n_known)
        before = int(np.count_nonzero(self.known != UNKNOWN)) if prev is not None and n_known < prev[3] else -1
        if before >= 0:  # the peer's map shrank: rebuild the union without its old map
            self._rebuild()
            self.version += 1
            return int(np.count_nonzero(self.known != UNKNOWN)) - before
        region = self.known[r0 : r0 + h, c0 : c0 + w]
        own = self.own[r0 : r0 + h, c0 : c0 + w]
        merged = np.where(own != UNKNOWN, own, np.maximum(region, data))
        gained = int(np.count_nonzero((region == UNKNOWN) & (merged != UNKNOWN)))
        if gained or not np.array_equal(region, merged):
            region[...] = merged
            self.version += 1
        return gained

    def _rebuild(self) -> None:
        known = np.full(self.shape, UNKNOWN, dtype=np.int8)
        for r0, c0, data, _ in self.peers.values():
            h, w = data.shape
            np.maximum(known[r0 : r0 + h, c0 : c0 + w], data, out=known[r0 : r0 + h, c0 : c0 + w])
        self.known = np.where(self.own != UNKNOWN, self.own, known).astype(np.int8)


def _grow(front: np.ndarray) -> np.ndarray:
    g = front.copy()
    g[1:, :] |= front[:-1, :]
    g[:-1, :] |= front[1:, :]
    g[:, 1:] |= front[:, :-1]
    g[:, :-1] |= front[:, 1:]
    return g


def frontier_mask(known: np.ndarray) -> np.ndarray:
    """Known free cells with an unknown 4-neighbour."""
    unk = known == UNKNOWN
    adj = np.zeros_like(unk)
    adj[1:, :] |= unk[:-1, :]
    adj[:-1, :] |= unk[1:, :]
    adj[:, 1:] |= unk[:, :-1]
    adj[:, :-1] |= unk[:, 1:]
    return (known == FREE) & adj


class Explorer:
    def __init__(self, *, window: int = 24, slack: int = 8, sep_cells: float = 12.0, sep_weight: float = 2.0) -> None:
        self.window = window
        self.slack = slack
        self.sep_cells = sep_cells
        self.sep_weight = sep_weight
        self.blacklist: set[int] = set()

    # -- wavefront in a window -------------------------------------------------------

    @staticmethod
    def _bfs(passable: np.ndarray, start: Cell, stop: np.ndarray | None, slack: int, max_level: int = 1 << 30) -> tuple[np.ndarray, int]:
        """Distances from ``start`` (-1 unreached). Stops ``slack`` levels after the
        first cell of ``stop`` is reached. Returns (dist, level of first stop or -1)."""
        dist = np.full(passable.shape, -1, dtype=np.int32)
        front = np.zeros(passable.shape, dtype=bool)
        front[start] = True
        dist[start] = 0
        visited = front.copy()
        found = -1
        if stop is not None and stop[start]:
            found = 0
        d = 0
        while d < max_level:
            if found >= 0 and d >= found + slack:
                break
            nxt = _grow(front) & passable & ~visited
            if not nxt.any():
                break
            d += 1
            dist[nxt] = d
            visited |= nxt
            front = nxt
            if found < 0 and stop is not None and (nxt & stop).any():
                found = d
        return dist, found

    @staticmethod
    def _backtrace(dist: np.ndarray, goal: Cell) -> list[Cell]:
        path = [goal]
        r, c = goal
        d = int(dist[goal])
        h, w = dist.shape
        while d > 0:
            for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                rr, cc = r + dr, c + dc
                if 0 <= rr < h and 0 <= cc < w and dist[rr, cc] == d - 1:
                    r, c, d = rr, cc, d - 1
                    path.append((r, c))
                    break
            else:  # pragma: no cover - BFS distances always have a predecessor
                break
        path.reverse()
        return path[1:]  # without the start

    def _window(self, shape: tuple[int, int], center: Cell, half: int, also: Cell | None = None) -> tuple[int, int, int, int]:
        H, W = shape
        r0, r1 = center[0] - half, center[0] + half + 1
        c0, c1 = center[1] - half, center[1] + half + 1
        if also is not None:
            r0, r1 = min(r0, also[0] - 2), max(r1, also[0] + 3)
            c0, c1 = min(c0, also[1] - 2), max(c1, also[1] + 3)
        return max(0, r0), min(H, r1), max(0, c0), min(W, c1)

    # -- public planning -------------------------------------------------------------

    def plan_frontier(self, known: np.ndarray, start: Cell, others: list[tuple[float, float]] = ()) -> list[Cell] | None:
        """Path (start excluded) to the best frontier, or None when none is reachable."""
        H, W = known.shape
        half = self.window
        while True:
            r0, r1, c0, c1 = self._window(known.shape, start, half)
            # frontier needs one cell of context outside the window
            R0, R1, C0, C1 = max(0, r0 - 1), min(H, r1 + 1), max(0, c0 - 1), min(W, c1 + 1)
            fr = frontier_mask(known[R0:R1, C0:C1])[r0 - R0 : r0 - R0 + (r1 - r0), c0 - C0 : c0 - C0 + (c1 - c0)]
            win = known[r0:r1, c0:c1]
            passable = win == FREE
            s = (start[0] - r0, start[1] - c0)
            passable[s] = True
            if self.blacklist:
                for f in self.blacklist:
                    rr, cc = divmod(f, W)
                    if r0 <= rr < r1 and c0 <= cc < c1:
                        fr[rr - r0, cc - c0] = False
            dist, found = self._bfs(passable, s, fr, self.slack)
            if found >= 0:
                cand = fr & (dist >= 0)
                cr, cc = np.nonzero(cand)
                cost = dist[cr, cc].astype(float)
                if others:
                    o = np.asarray(others, dtype=float)
                    gr = (cr + r0)[:, None] - o[None, :, 0]
                    gc = (cc + c0)[:, None] - o[None, :, 1]
                    near = np.sqrt(gr * gr + gc * gc).min(axis=1)
                    cost += self.sep_weight * np.maximum(0.0, self.sep_cells - near)
                k = int(np.argmin(cost))
                goal = (int(cr[k]), int(cc[k]))
                path = self._backtrace(dist, goal)
                return [(r + r0, c + c0) for r, c in path]
            whole = r0 == 0 and c0 == 0 and r1 == H and c1 == W
            if whole:
                return None
            reached = dist >= 0
            touches = reached[0, :].any() or reached[-1, :].any() or reached[:, 0].any() or reached[:, -1].any()
            if not touches:
                return None
            half *= 2

    def plan_to(self, known: np.ndarray, start: Cell, goal: Cell) -> list[Cell]:
        """Path through known free cells to ``goal``, or to the reachable cell nearest
        to it when ``goal`` cannot be reached. Empty when already there."""
        H, W = known.shape
        half = max(self.window, abs(goal[0] - start[0]), abs(goal[1] - start[1]))
        while True:
            r0, r1, c0, c1 = self._window(known.shape, start, half, also=goal)
            passable = known[r0:r1, c0:c1] == FREE
            s = (start[0] - r0, start[1] - c0)
            g = (goal[0] - r0, goal[1] - c0)
            passable[s] = True
            passable[g] = known[goal] != OCC
            stop = np.zeros_like(passable)
            stop[g] = True
            dist, found = self._bfs(passable, s, stop, 0)
            if found >= 0:
                return [(r + r0, c + c0) for r, c in self._backtrace(dist, g)]
            whole = r0 == 0 and c0 == 0 and r1 == H and c1 == W
            if whole:
                rr, cc = np.nonzero(dist >= 0)
                k = int(np.argmin((rr - g[0]) ** 2 + (cc - g[1]) ** 2))
                return [(r + r0, c + c0) for r, c in self._backtrace(dist, (int(rr[k]), int(cc[k])))]
            half *= 2

    def is_frontier(self, known: np.ndarray, cell: Cell) -> bool:
        r, c = cell
        if known[r, c] != FREE:
            return False
        H, W = known.shape
        for rr, cc in ((r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1)):
            if 0 <= rr < H and 0 <= cc < W and known[rr, cc] == UNKNOWN:
                return True
        return False
