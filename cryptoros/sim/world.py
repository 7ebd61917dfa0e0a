"""The world: a ground-truth occupancy grid, charging stations, and the lidar.

Ground truth (:class:`World`) is kept apart from what robots believe: robots only see
it through :class:`Lidar` scans and bumps. Beliefs are ``int8`` grids with the
``nav_msgs/OccupancyGrid`` convention: ``-1`` unknown, ``0`` free, ``100`` occupied.

Cells are indexed ``(row, col)``; the metric frame has ``x = col * resolution`` and
``y = row * resolution`` (the PGM's top row is row 0, as map_server draws it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from cryptoros.errors import ConfigError

UNKNOWN = -1
FREE = 0
OCC = 100


@dataclass
class World:
    occupied: np.ndarray  # bool (H, W): ground truth
    resolution: float  # metres per cell
    bases: list[tuple[int, int]]  # charging stations (row, col)
    origin: tuple[float, float] = (0.0, 0.0)
    name: str = "generated"
    _explorable: np.ndarray | None = field(default=None, repr=False)

    @property
    def shape(self) -> tuple[int, int]:
        return self.occupied.shape  # type: ignore[return-value]

    def explorable(self) -> np.ndarray:
        """Free cells reachable from a base (the coverage denominator)."""
        if self._explorable is None:
            free = ~self.occupied
            seed = np.zeros_like(free)
            for r, c in self.bases:
                seed[r, c] = True
            self._explorable = flood(seed, free)
        return self._explorable

    def truth_grid(self) -> np.ndarray:
        """Ground truth as an OccupancyGrid-valued int8 array."""
        return np.where(self.occupied, OCC, FREE).astype(np.int8)


def flood(seed: np.ndarray, passable: np.ndarray) -> np.ndarray:
    """Cells of ``passable`` 4-connected to ``seed`` (numpy wavefront, no cell loop)."""
    reached = seed & passable
    while True:
        grown = reached.copy()
        grown[1:, :] |= reached[:-1, :]
        grown[:-1, :] |= reached[1:, :]
        grown[:, 1:] |= reached[:, :-1]
        grown[:, :-1] |= reached[:, 1:]
        grown &= passable
        if np.array_equal(grown, reached):
            return reached
        reached = grown


def generate(
    seed: int,
    width: int = 60,
    height: int = 60,
    *,
    resolution: float = 0.2,
    min_room: int = 14,
    door: int = 5,
    n_bases: int = 1,
    obstacles: int = 0,
) -> World:
    """Rooms by recursive division with doors, from ``seed`` (same seed, same world)."""
    rng = np.random.default_rng(seed)
    occ = np.zeros((height, width), dtype=bool)
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = True
    stack = [(1, 1, height - 1, width - 1)]  # r0, c0, r1, c1 (exclusive interior)
    while stack:
        r0, c0, r1, c1 = stack.pop()
        h, w = r1 - r0, c1 - c0
        if h < 2 * min_room and w < 2 * min_room:
            continue
        horizontal = h >= w if (h >= 2 * min_room and w >= 2 * min_room) else h >= 2 * min_room
        if horizontal:
            r = int(rng.integers(r0 + min_room, r1 - min_room + 1))
            occ[r, c0:c1] = True
            for _ in range(1 + int(w > 3 * min_room)):
                d = int(rng.integers(c0, max(c0 + 1, c1 - door)))
                occ[r, d : d + door] = False
            stack += [(r0, c0, r, c1), (r + 1, c0, r1, c1)]
        else:
            c = int(rng.integers(c0 + min_room, c1 - min_room + 1))
            occ[r0:r1, c] = True
            for _ in range(1 + int(h > 3 * min_room)):
                d = int(rng.integers(r0, max(r0 + 1, r1 - door)))
                occ[d : d + door, c] = False
            stack += [(r0, c0, r1, c), (r0, c + 1, r1, c1)]
    for _ in range(obstacles):
        r, c = int(rng.integers(3, height - 5)), int(rng.integers(3, width - 5))
        occ[r : r + 2, c : c + 2] = True
    bases = _place_bases(occ, n_bases)
    return World(occ, resolution, bases, name=f"generated-{seed}-{width}x{height}")


def _place_bases(occ: np.ndarray, n: int) -> list[tuple[int, int]]:
    """Bases in free cells near the corners (first near the top-left)."""
    h, w = occ.shape
    corners = [(3, 3), (h - 4, w - 4), (3, w - 4), (h - 4, 3)]
    free_r, free_c = np.nonzero(~occ)
    bases = []
    for i in range(n):
        tr, tc = corners[i % 4]
        k = int(np.argmin((free_r - tr) ** 2 + (free_c - tc) ** 2))
        bases.append((int(free_r[k]), int(free_c[k])))
    return bases


# ---------------------------------------------------------------- map_server files


def load_map_server(yaml_path: str | Path, *, n_bases: int = 1, bases: list[tuple[int, int]] | None = None) -> World:
    """Load a ROS ``map_server`` map (YAML + PGM). Unknown pixels count as occupied."""
    yaml_path = Path(yaml_path)
    try:
        meta = yaml.safe_load(yaml_path.read_text())
        image = yaml_path.parent / meta["image"]
        resolution = float(meta["resolution"])
        negate = int(meta.get("negate", 0))
        occ_t = float(meta.get("occupied_thresh", 0.65))
        free_t = float(meta.get("free_thresh", 0.196))
        origin = meta.get("origin", [0.0, 0.0, 0.0])
    except (OSError, KeyError, TypeError, ValueError, yaml.YAMLError) as err:
        raise ConfigError(f"bad map_server yaml {yaml_path}: {err}") from err
    pix = read_pgm(image)
    p = pix.astype(float) / 255.0 if negate else (255.0 - pix.astype(float)) / 255.0
    occupied = p > free_t  # occupied or unknown: not explorable
    _ = occ_t
    w = World(occupied, resolution, [], origin=(float(origin[0]), float(origin[1])), name=yaml_path.stem)
    w.bases = bases if bases is not None else _place_bases(occupied, n_bases)
    return w


def read_pgm(path: str | Path) -> np.ndarray:
    data = Path(path).read_bytes()
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < 4:
        while data[pos : pos + 1].isspace():
            pos += 1
        if data[pos : pos + 1] == b"#":
            pos = data.index(b"\n", pos) + 1
            continue
        end = pos
        while not data[end : end + 1].isspace():
            end += 1
        tokens.append(data[pos:end])
        pos = end
    magic, w, h, maxval = tokens[0], int(tokens[1]), int(tokens[2]), int(tokens[3])
    if magic == b"P5":
        raw = np.frombuffer(data[pos + 1 : pos + 1 + w * h], dtype=np.uint8)
    elif magic == b"P2":
        raw = np.array(data[pos:].split()[: w * h], dtype=np.int64)
    else:
        raise ConfigError(f"{path}: not a PGM (P5/P2) file")
    if raw.size != w * h:
        raise ConfigError(f"{path}: truncated PGM")
    arr = raw.reshape(h, w).astype(np.int64)
    if maxval != 255:
        arr = arr * 255 // maxval
    return arr.astype(np.uint8)


def save_map_server(world: World, yaml_path: str | Path) -> Path:
    """Write ``world`` as map_server YAML + binary PGM (occupied 0, free 254)."""
    yaml_path = Path(yaml_path)
    pgm = yaml_path.with_suffix(".pgm")
    h, w = world.shape
    pix = np.where(world.occupied, 0, 254).astype(np.uint8)
    pgm.write_bytes(b"P5\n%d %d\n255\n" % (w, h) + pix.tobytes())
    meta = {
        "image": pgm.name,
        "resolution": world.resolution,
        "origin": [world.origin[0], world.origin[1], 0.0],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
    }
    yaml_path.write_text(yaml.safe_dump(meta))
    return yaml_path


# ---------------------------------------------------------------- lidar


class Lidar:
    """A 360-degree range sensor on the grid: precomputed ray offsets, numpy casting."""

    def __init__(self, range_cells: float) -> None:
        self.range_cells = range_cells
        n_rays = max(64, int(2 * math.pi * range_cells * 1.3))
        steps = np.arange(0.5, range_cells + 1e-9, 0.5)
        ang = np.linspace(0, 2 * math.pi, n_rays, endpoint=False)
        dr = np.rint(np.outer(np.sin(ang), steps)).astype(np.int32)
        dc = np.rint(np.outer(np.cos(ang), steps)).astype(np.int32)
        self.dr, self.dc = dr, dc
        self.n_steps = steps.size

    def scan(self, occupied: np.ndarray, r: int, c: int) -> tuple[np.ndarray, np.ndarray]:
        """Flat indices of the cells seen from (r, c) and whether each is occupied."""
        h, w = occupied.shape
        rr = self.dr + r
        cc = self.dc + c
        inside = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
        rr = np.clip(rr, 0, h - 1)
        cc = np.clip(cc, 0, w - 1)
        hit = occupied[rr, cc] | ~inside
        first = np.where(hit.any(axis=1), hit.argmax(axis=1), self.n_steps)
        visible = (np.arange(self.n_steps)[None, :] <= first[:, None]) & inside
        flat = (rr * w + cc)[visible]
        return flat, hit[visible]
