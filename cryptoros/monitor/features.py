"""Features of one publisher's messages on one topic, message by message (sans-IO).

:class:`StreamFeatures` is fed a message body (ROS 1 serialization, as the TCPROS
frame carries it) and its arrival time, and returns the message's features as a
tuple in the order :data:`FEATURES` gives for its kind. Everything is "higher is more
suspicious", so a model is one upper limit per feature (:mod:`cryptoros.monitor.model`).

Kinds and what they show (seed 001's attacks and the demo's insiders):

* every type (``any``): ``rate_hz`` (messages in the last second: a flood),
  ``burst_hz`` (the rate over the last :data:`BURST_INTERVALS` arrivals: a flood seen
  within milliseconds of its start, where the second's count needs many messages to
  rise over a clean stream's own), ``size_change`` (relative change of the body size
  from the previous message). An arrival is a read: messages read together (within
  :data:`BURST_MERGE_S`) are one, so a stream the proxy could not read for a while,
  then read at once, is not a burst; a flood so fast that it arrives in chunks is
  caught by ``rate_hz`` in as little time;
* ``pose`` (``geometry_msgs/PoseStamped``): ``speed_mps``, the speed the step from the
  previous position implies (a spoofed position jumps); ``stamp_back_s``, how far
  the header stamp went back (a replay); ``stamp_lag_s``, how far the stamp is from
  the arrival time (a replay of old messages, or a stamp made up ahead of the clock);
* ``scan`` (``sensor_msgs/LaserScan``): ``roughness``, the mean step between
  neighbouring beams relative to the mean range (noise), ``scan_change``, the mean
  change from the previous scan relative to the mean range, ``geometry_change`` (1
  when the scan's angles or range limits differ from the previous scan's: a driver
  never changes them), and the two stamp features. A scan whose limits make no sense
  (not finite, ``range_min >= range_max``, a zero angle step) is malformed: limits
  that leave no beam valid must not hide the ranges from scoring;
* ``twist`` (``geometry_msgs/Twist``): ``linear`` and ``angular``, ``|linear.x|`` and
  ``|angular.z|`` (a command no controller would send);
* ``beacon`` (the demo team's ``cryptoros_sim/Hello``, a robot's position beacon to its
  team, 8 a second): the common features; each beacon is also the reference the robot's
  pose stream is checked against (below);
* ``team_map`` (the demo team's ``cryptoros_sim/MapUpdate``, a robot's own observations
  shared with its team): ``unseen_claim``, the share of the cells the update claims known
  that lie out of sensor reach of every position this stream has reported (what the
  sender cannot have seen: a false "explored" claim), and ``walls_erased``, the share of
  the walls this stream claimed before that the update calls free (a robot's own
  observations only grow: a wall it saw stays a wall; an arena small enough for the liar
  to have seen it all still has walls), both held at their highest for
  :data:`CLAIM_HOLD_S` (one false claim between honest updates keeps the stream flagged).

**Across streams** (:class:`Crosscheck`, one per interceptor or per recording): a pose on
``/<robot>/...`` gets ``beacon_gap_m``, the distance between where the robot's own beacons
(``source == <robot>``) put it and where the pose stream put it when the beacon arrived
(the nearer of its poses just before and just after), the latest gap held for
:data:`GAP_HOLD_S`. A beacon is the robot's own word only when the manager it comes from
is that robot (``beacon_from``: in the interceptor the peer's manager, or this host's own
for the beacons its own nodes send out): another robot cannot frame it. A pose drifting slowly away from the truth looks like motion on its
own (0.1 m/s is a twentieth of a demo robot's speed); against the beacons the robot's
explorer sends its team, it grows without bound. Which of the two is lying the gap cannot
tell: the pose stream is the one scored, so a robot whose beacons lie has its pose stream
flagged (the disagreement is alerted either way).

A body that does not decode as its type scores as its own feature, ``malformed`` (1.0);
a feature that comes out NaN or infinite (a pose at NaN) scores as infinitely over its
limit (:mod:`cryptoros.monitor.model`).
"""

from __future__ import annotations

import functools
import importlib
import math
import struct
from collections import OrderedDict, deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np

from cryptoros.errors import CryptorosError, RemoteProtocolError
from cryptoros.lru import remember
from cryptoros.ros1 import msgs

KIND_OF_TYPE = {
    "geometry_msgs/PoseStamped": "pose",
    "sensor_msgs/LaserScan": "scan",
    "geometry_msgs/Twist": "twist",
    "cryptoros_sim/Hello": "beacon",
    "cryptoros_sim/MapUpdate": "team_map",
}
#: kinds whose types exist only in ROS 1 (the demo team's own messages)
_ROS1_ONLY = frozenset({"beacon", "team_map"})
_COMMON = ("rate_hz", "burst_hz", "size_change", "malformed")
FEATURES: dict[str, tuple[str, ...]] = {
    "any": _COMMON,
    "pose": (*_COMMON, "speed_mps", "stamp_back_s", "stamp_lag_s"),
    "scan": (*_COMMON, "roughness", "scan_change", "stamp_back_s", "stamp_lag_s", "geometry_change"),
    "twist": (*_COMMON, "linear", "angular"),
    "beacon": _COMMON,
    "team_map": (*_COMMON, "unseen_claim", "walls_erased"),
}
# appended last, so a model fitted before it was added still lines up (and ignores it)
FEATURES["pose"] = (*FEATURES["pose"], "beacon_gap_m")
RATE_WINDOW_S = 1.0
#: ``burst_hz`` is the rate over this many intervals between arrivals
BURST_INTERVALS = 3
#: messages read within this of the previous one count as one arrival for ``burst_hz``
BURST_MERGE_S = 0.002
#: arrival times kept for the rate (a flood faster than this per second reads as this)
MAX_RATE_SAMPLES = 4096


def kind_of(typename: str, codec: str = "ros1") -> str:
    """The kind of a ROS 1 (``pkg/Name``) or ROS 2 (``pkg/msg/Name``) type name."""
    kind = KIND_OF_TYPE.get(typename.replace("/msg/", "/"), "any")
    return "any" if codec == "cdr" and kind in _ROS1_ONLY else kind


#: how far a demo robot's lidar reaches, plus what it can travel between two map updates
#: and the coarse grid's rounding (the team map has no resolution field: the simulator's)
SENSOR_REACH_M = 3.5 + 2.5
TEAM_MAP_RESOLUTION_M = 0.2
#: the coarse grid of reachable places (metres per cell) and its bound per stream
REACH_CELL_M = 1.0
MAX_REACH_CELLS = 1 << 16
#: reported places remembered per team-map stream
MAX_VISITED = 1 << 14
#: cells of the grid of walls kept per team-map stream (a 100 m x 100 m area at 0.2 m;
#: the demo's arena is 60 x 60 cells)
MAX_WALL_CELLS = 1 << 18
#: team-map origins beyond this many cells from 0 are malformed
_MAX_ORIGIN = 1 << 20
#: a team map bigger than this is not checked: malformed (the demo's is 10,000 cells)
MAX_TEAM_MAP_CELLS = 1 << 22
#: a team map of more cells than this is checked with numpy arrays, not integers: numpy's
#: cost per call (10-20 us on the interceptor's cold path) is paid back on a big patch,
#: where the integers' cost per cell (about 7 ns, against numpy's 1) is not
NUMPY_FROM_CELLS = 1 << 16
CLAIM_HOLD_S = 5.0
BEACON_MATCH_S = 0.4
GAP_HOLD_S = 1.0
#: robots one cross-check follows, and pose streams per robot (least recently heard of dropped first)
MAX_CROSSCHECK_ROBOTS = 1024
MAX_POSE_STREAMS = 16
_REACH_RADIUS = math.ceil(SENSOR_REACH_M / REACH_CELL_M)


#: per byte of an int8 team-map cell: 1 where the cell is a wall (> 0), free (0), known (not -1)
_WALL = bytes(1 if 0 < b < 128 else 0 for b in range(256))
_FREE = bytes(1 if b == 0 else 0 for b in range(256))
_KNOWN = bytes(0 if b == 0xFF else 1 for b in range(256))


def _ones(a: bytes, b: bytes) -> int:
    """How many places are 1 in both of two equally long 0/1 byte strings (as integers:
    one AND and one popcount, no per-cell work)."""
    return (int.from_bytes(a, "little") & int.from_bytes(b, "little")).bit_count()


class _Grid:
    """A 0/1 grid over integer (row, column) places that grows to cover what is marked,
    up to ``limit`` places (a mark that would pass it is dropped: bounded). Kept as one
    integer, a byte a place (row-major, ``width`` places a row), so that a patch laid out
    with the grid's row length (:meth:`laid_out`, one slice per row) is read, counted and
    marked with a handful of whole-integer operations (shift, ``&``, ``|``,
    ``int.bit_count``): no per-cell Python work and no numpy call (each costs 10-20 us
    on the interceptor's cold path)."""

    __slots__ = ("bits", "row0", "col0", "height", "width", "limit", "made")

    def __init__(self, limit: int) -> None:
        self.bits = 0
        self.row0 = self.col0 = self.height = self.width = 0
        self.limit = limit
        self.made = False  # grown at least once (a grid of no place is still made)

    @property
    def size(self) -> int:
        """Places the grid holds."""
        return self.height * self.width

    def covers(self, row0: int, col0: int, h: int, w: int) -> bool:
        return (self.made and self.row0 <= row0 and self.col0 <= col0 and row0 + h <= self.row0 + self.height
                and col0 + w <= self.col0 + self.width)

    def take(self, row0: int, col0: int, h: int, w: int) -> bool:
        """Whether the grid covers the (h, w) window at (row0, col0), growing it if not (by
        a quarter more than needed, so not on every step); False when that would pass
        the limit (what is there is then neither remembered nor read as a whole)."""
        return self.covers(row0, col0, h, w) or self._grow(row0, col0, h, w)

    def shift(self, row0: int, col0: int) -> int:
        """The bit where place (row0, col0) of a covered window starts."""
        return ((row0 - self.row0) * self.width + col0 - self.col0) * 8

    def laid_out(self, cells: bytes, h: int, w: int) -> bytes:
        """A patch's (h, w) row-major team-map cells with the grid's row length (unknown
        cells, -1, between the rows: neither free nor a wall)."""
        width = self.width
        if w == width or not h * w:
            return cells
        return (b"\xff" * (width - w)).join([cells[i:i + w] for i in range(0, h * w, w)])

    def footprint(self, h: int, w: int) -> int:
        """A covered (h, w) window's places, set, at shift 0 (kept for the next patch of
        that shape while small: the cache's memory stays bounded)."""
        if h * self.width <= _CACHED_MASK_BYTES:
            return _footprint(h, w, self.width)
        return _footprint.__wrapped__(h, w, self.width)

    def window(self, row0: int, col0: int, h: int, w: int) -> bytes:
        """The (h, w) window at (row0, col0) as row-major 0/1 bytes (its own row length);
        0 where the grid does not reach."""
        width = self.width
        cells = self.bits.to_bytes(self.height * width, "little")
        out = bytearray(h * w)
        r0, c0 = max(row0, self.row0), max(col0, self.col0)
        r1, c1 = min(row0 + h, self.row0 + self.height), min(col0 + w, self.col0 + width)
        if self.made and r0 < r1 and c0 < c1:
            n = c1 - c0
            for r in range(r0, r1):
                src = (r - self.row0) * width + c0 - self.col0
                dst = (r - row0) * w + c0 - col0
                out[dst:dst + n] = cells[src:src + n]
        return bytes(out)

    def array(self, row0: int, col0: int, h: int, w: int) -> np.ndarray:
        """The (h, w) window at (row0, col0) as a boolean array; False where the grid
        does not reach (a big patch's numpy check)."""
        import numpy as np

        out = np.zeros((h, w), dtype=bool)
        r0, c0 = max(row0, self.row0), max(col0, self.col0)
        r1, c1 = min(row0 + h, self.row0 + self.height), min(col0 + w, self.col0 + self.width)
        if self.made and r0 < r1 and c0 < c1:
            cells = np.frombuffer(self.bits.to_bytes(self.height * self.width, "little"), dtype=bool)
            cells = cells.reshape(self.height, self.width)
            out[r0 - row0:r1 - row0, c0 - col0:c1 - col0] = \
                cells[r0 - self.row0:r1 - self.row0, c0 - self.col0:c1 - self.col0]
        return out

    def mark_array(self, row0: int, col0: int, mask: np.ndarray) -> None:
        """OR a boolean (h, w) ``mask`` into the grid at (row0, col0) (a big patch's
        walls), growing the grid as :meth:`take` does; dropped past the limit."""
        import numpy as np

        h, w = mask.shape
        if not self.take(row0, col0, h, w):
            return
        grid = np.zeros((self.height, self.width), dtype=np.uint8)
        r, c = row0 - self.row0, col0 - self.col0
        grid[r:r + h, c:c + w] = mask
        self.bits |= int.from_bytes(grid.tobytes(), "little")

    def _grow(self, row0: int, col0: int, h: int, w: int) -> bool:
        r0, c0, r1, c1 = row0, col0, row0 + h, col0 + w
        if self.made:
            r0, c0 = min(r0, self.row0), min(c0, self.col0)
            r1, c1 = max(r1, self.row0 + self.height), max(c1, self.col0 + self.width)
        pad_r, pad_c = (r1 - r0) // 4, (c1 - c0) // 4
        if (r1 - r0 + 2 * pad_r) * (c1 - c0 + 2 * pad_c) <= self.limit:
            r0, r1, c0, c1 = r0 - pad_r, r1 + pad_r, c0 - pad_c, c1 + pad_c
        elif (r1 - r0) * (c1 - c0) > self.limit:
            return False
        height, width = r1 - r0, c1 - c0
        if self.made and self.bits:
            old, ow = self.bits.to_bytes(self.height * self.width, "little"), self.width
            grown = bytearray(height * width)
            for r in range(self.height):
                dst = (self.row0 - r0 + r) * width + self.col0 - c0
                grown[dst:dst + ow] = old[r * ow:(r + 1) * ow]
            self.bits = int.from_bytes(grown, "little")
        self.row0, self.col0, self.height, self.width = r0, c0, height, width
        self.made = True
        return True


#: laid-out masks up to this many bytes are cached (64 of them at most: 1 MiB)
_CACHED_MASK_BYTES = 1 << 14


@functools.lru_cache(maxsize=64)
def _footprint(h: int, w: int, width: int) -> int:
    """(h, w) places set, laid out in rows of ``width`` places (a byte each)."""
    return int.from_bytes(bytes(width - w).join([b"\x01" * w] * h), "little")


#: the coarse places within sensor reach of a place, as a square 0/1 mask around it
_REACH_DISK = bytes(int(dr * dr + dc * dc <= _REACH_RADIUS ** 2)
                    for dr in range(-_REACH_RADIUS, _REACH_RADIUS + 1)
                    for dc in range(-_REACH_RADIUS, _REACH_RADIUS + 1))


def _reach_disk_bits(width: int) -> int:
    """:data:`_REACH_DISK` laid out in rows of ``width`` places, at shift 0 (cached
    while small, as :meth:`_Grid.footprint`)."""
    if (2 * _REACH_RADIUS + 1) * width <= _CACHED_MASK_BYTES:
        return _laid_disk(width)
    return _laid_disk.__wrapped__(width)


@functools.lru_cache(maxsize=16)
def _laid_disk(width: int) -> int:
    side = 2 * _REACH_RADIUS + 1
    return int.from_bytes(bytes(width - side).join([_REACH_DISK[i:i + side] for i in range(0, side * side, side)]),
                          "little")


class _PoseTrack:
    """One pose stream of a robot, as the cross-check follows it."""

    __slots__ = ("at", "x", "y", "gap", "gap_at", "beacon")

    def __init__(self, at: float, x: float, y: float) -> None:
        self.at, self.x, self.y = at, x, y
        self.gap, self.gap_at = 0.0, -math.inf
        #: a beacon waiting for the pose after it: (x, y, arrival, distance to the pose before)
        self.beacon: tuple[float, float, float, float] | None = None


class Crosscheck:
    """What streams tell about each other: per robot, each stream that publishes its pose,
    and the gap the robot's beacons find to it. Bounded: at most
    :data:`MAX_CROSSCHECK_ROBOTS` robots and :data:`MAX_POSE_STREAMS` pose streams each
    (the least recently heard of dropped first).

    A beacon is matched with the poses on either side of it in time (the robot may have
    moved between its pose and its beacon: either may be the one it was at); the gap is
    the nearer of the two."""

    __slots__ = ("_robots",)

    def __init__(self) -> None:
        self._robots: OrderedDict[str, OrderedDict[object, _PoseTrack]] = OrderedDict()

    def pose(self, robot: str, stream: object, now: float, x: float, y: float) -> float:
        """A pose of ``robot`` from ``stream`` arriving at ``now``; returns that stream's
        beacon gap (0 when no beacon of the last :data:`GAP_HOLD_S` found one)."""
        streams = self._robots.get(robot)
        if streams is None:
            streams = OrderedDict()
            remember(self._robots, robot, streams, MAX_CROSSCHECK_ROBOTS)
        else:
            self._robots.move_to_end(robot)
        track = streams.get(stream)
        if track is None:
            track = _PoseTrack(now, x, y)
            remember(streams, stream, track, MAX_POSE_STREAMS)
        else:
            streams.move_to_end(stream)
            track.at, track.x, track.y = now, x, y
            if track.beacon is not None:
                bx, by, b_at, before = track.beacon
                track.beacon = None
                if now - b_at <= BEACON_MATCH_S:
                    track.gap, track.gap_at = min(before, math.hypot(x - bx, y - by)), now
        return track.gap if now - track.gap_at <= GAP_HOLD_S else 0.0

    def follows(self, robot: str) -> bool:
        """Whether a pose stream of ``robot`` is followed (its beacons are worth reading)."""
        return robot in self._robots

    def beacon(self, robot: str, now: float, x: float, y: float) -> None:
        """``robot``'s beacon puts it at (x, y) at ``now``: per pose stream whose latest
        pose arrived in the last :data:`BEACON_MATCH_S`, the gap is known at its next pose."""
        for track in self._robots.get(robot, {}).values():
            if now - BEACON_MATCH_S <= track.at <= now:
                track.beacon = (x, y, now, math.hypot(track.x - x, track.y - y))


#: team-map cells per coarse place along a side
_CELLS_PER_PLACE = round(REACH_CELL_M / TEAM_MAP_RESOLUTION_M)
assert math.isclose(_CELLS_PER_PLACE * TEAM_MAP_RESOLUTION_M, REACH_CELL_M), "a place is a whole number of cells"


def _places(origin: int, n: int) -> tuple[int, list[int]]:
    """The coarse places cells ``origin .. origin + n - 1`` lie in (integers: a place is
    :data:`_CELLS_PER_PLACE` cells): the first place, and how many of the cells each
    place in turn covers."""
    k = _CELLS_PER_PLACE
    first, last = origin // k, (origin + n - 1) // k
    if first == last:
        return first, [n]
    return first, [k * (first + 1) - origin, *([k] * (last - first - 1)), origin + n - k * last]


#: a coarse place's 0/1 byte as the bytes of the cells along a side of it
_ACROSS_PLACE = (bytes(_CELLS_PER_PLACE), b"\x01" * _CELLS_PER_PLACE)


def _spread(places: bytes, row_cells: list[int], col_cells: list[int]) -> bytes:
    """A window of coarse places spread to the cells they cover (row-major 0/1 bytes):
    each place repeated over its cells, each row of places over its rows of cells. (The
    first and last place of a row may cover fewer cells: the patch's cells start
    ``k - col_cells[0]`` cells into its first place.)"""
    ncols, k = len(col_cells), _CELLS_PER_PLACE
    start = k - col_cells[0]
    stop = start + sum(col_cells)
    rows = []
    for i, n in enumerate(row_cells):
        line = b"".join(map(_ACROSS_PLACE.__getitem__, places[i * ncols:(i + 1) * ncols]))
        rows.append(line[start:stop] * n)
    return b"".join(rows)


def warm_up() -> None:
    """Load what scoring needs (numpy, the decoders of the known ROS 1 types) and run
    every kind's features over two made-up messages now: the first message of a kind
    costs ten times the next ones (numpy's first calls, the grids' first allocations),
    and at start-up that is not paid on a peer's first message, on the forwarding path."""
    for typename, kind in KIND_OF_TYPE.items():
        if kind not in _DECODERS:
            msgs.deserializer(typename)
    crosscheck = Crosscheck()
    for typename, sample in _warm_up_samples().items():
        features = StreamFeatures(typename, topic="/r0/warm_up", crosscheck=crosscheck)
        for t in (1.0, 1.1):
            features.observe(sample(t), t, t)


def _warm_up_samples() -> dict[str, Callable[[float], bytes]]:
    """Per known type, a clean message at time t (ROS 1 serialization)."""
    np = importlib.import_module("numpy")

    def header(t: float) -> bytes:
        return _HEADER.pack(1, int(t), int(t % 1 * 1e9)) + _U32.pack(3) + b"map"

    def team_head(t: float) -> bytes:
        return _U32.pack(2) + b"r0" + _BEACON_HEAD.pack(1, t, 1.0, 1.0, 0.0)

    ranges = np.linspace(1.0, 2.0, 360, dtype="<f4").tobytes()
    cells = np.full((10, 10), -1, dtype=np.int8)
    cells[:5] = 0
    cells[5, :] = 100
    samples: dict[str, Callable[[float], bytes]] = {
        "geometry_msgs/PoseStamped": lambda t: header(t) + _POSE.pack(t, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0),
        "sensor_msgs/LaserScan": lambda t: header(t) + _SCAN_FIELDS.pack(0.0, 6.28, 0.0175, 0.0, 0.2, 0.1, 3.5)
        + _U32.pack(360) + ranges + _U32.pack(0),
        "geometry_msgs/Twist": lambda t: _TWIST.pack(0.2, 0.0, 0.0, 0.0, 0.0, 0.1),
        "cryptoros_sim/Hello": team_head,
        "cryptoros_sim/MapUpdate": lambda t: team_head(t) + _MAP_TAIL.pack(0.0, 0.0, 0.0, False, 0, 0, 10, 10, 100)
        + cells.tobytes(),
    }
    assert set(samples) == set(KIND_OF_TYPE)
    return samples


def robot_of(topic: str) -> str:
    """The robot a topic belongs to: its first namespace (``/r0/pose`` -> ``r0``)."""
    parts = topic.strip("/").split("/")
    return parts[0] if len(parts) > 1 else ""


def _cdr_decoder(typename: str, kind: str) -> Callable[[Any], Any]:
    """A decoder of ROS 2 (CDR) samples giving what the kind's features read."""
    from cryptoros.ros2.cdr import deserializer

    decode = deserializer(typename)
    if kind == "pose":
        def pose(body: Any) -> tuple[float, float, float]:
            msg = decode(body)
            return _stamp(msg), float(msg.pose.position.x), float(msg.pose.position.y)
        return pose
    if kind == "twist":
        def twist(body: Any) -> tuple[float, float]:
            msg = decode(body)
            return float(msg.linear.x), float(msg.angular.z)
        return twist
    if kind != "scan":
        return decode

    def scan(body: Any) -> tuple[float, tuple[float, ...], np.ndarray]:
        import numpy as np

        msg = decode(body)
        geometry = _checked_geometry(tuple(float(getattr(msg, f)) for f in _GEOMETRY))
        return _stamp(msg), geometry, np.asarray(msg.ranges, dtype=np.float64)

    return scan


#: the LaserScan fields a driver never changes between scans
_GEOMETRY = ("angle_min", "angle_max", "angle_increment", "range_min", "range_max")


def _checked_geometry(geometry: tuple[float, ...]) -> tuple[float, ...]:
    _amin, _amax, step, range_min, range_max = geometry
    if not all(math.isfinite(v) for v in geometry) or step == 0.0 or not 0.0 <= range_min < range_max:
        raise RemoteProtocolError(f"LaserScan limits make no sense: {dict(zip(_GEOMETRY, geometry))}")
    return geometry


def _stamp(msg: Any) -> float:
    stamp = msg.header.stamp
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


_HEADER = struct.Struct("<III")  # seq, stamp sec, stamp nsec
_POSE = struct.Struct("<7d")  # position x, y, z, orientation x, y, z, w
_TWIST = struct.Struct("<6d")  # linear x, y, z, angular x, y, z
_SCAN_FIELDS = struct.Struct("<7f")  # angle_min .. range_max
_U32 = struct.Struct("<I")


def _decode_scan(body: bytes | memoryview) -> tuple[float, tuple[float, ...], np.ndarray]:
    """What the scan features read of a ``sensor_msgs/LaserScan`` (ROS 1 serialization):
    the stamp, the geometry (angles and range limits, checked) and the ranges; 10x
    quicker than decoding the whole message. Malformed bytes raise
    :class:`RemoteProtocolError`."""
    import numpy as np  # here, not at import: an interceptor without scans to watch never loads it
    try:
        _seq, sec, nsec = _HEADER.unpack_from(body, 0)
        (frame_len,) = _U32.unpack_from(body, 12)
        pos = 16 + frame_len
        fields = _SCAN_FIELDS.unpack_from(body, pos)
        pos += _SCAN_FIELDS.size
        (count,) = _U32.unpack_from(body, pos)
        pos += 4
        if pos + 4 * count > len(body):
            raise RemoteProtocolError("LaserScan ranges run past the message")
        ranges = np.frombuffer(body, dtype="<f4", count=count, offset=pos).astype(np.float64)
    except struct.error as err:
        raise RemoteProtocolError(f"malformed LaserScan: {err}") from err
    geometry = _checked_geometry((fields[0], fields[1], fields[2], fields[5], fields[6]))
    return sec + nsec * 1e-9, geometry, ranges


def _decode_pose(body: bytes | memoryview) -> tuple[float, float, float]:
    """What the pose features read of a ``geometry_msgs/PoseStamped`` (ROS 1
    serialization): the stamp and the position's x and y. A body of any other length
    than the type's is malformed (:class:`RemoteProtocolError`)."""
    try:
        _seq, sec, nsec = _HEADER.unpack_from(body, 0)
        (frame_len,) = _U32.unpack_from(body, 12)
        if 16 + frame_len + _POSE.size != len(body):
            raise RemoteProtocolError(f"PoseStamped of {len(body)} bytes with a frame_id of {frame_len}")
        x, y, *_rest = _POSE.unpack_from(body, 16 + frame_len)
    except struct.error as err:
        raise RemoteProtocolError(f"malformed PoseStamped: {err}") from err
    return sec + nsec * 1e-9, x, y


def _decode_twist(body: bytes | memoryview) -> tuple[float, float]:
    """What the twist features read of a ``geometry_msgs/Twist``: linear.x, angular.z."""
    if len(body) != _TWIST.size:
        raise RemoteProtocolError(f"Twist of {len(body)} bytes (it has {_TWIST.size})")
    linear_x, _ly, _lz, _ax, _ay, angular_z = _TWIST.unpack(body)
    return linear_x, angular_z


_BEACON_HEAD = struct.Struct("<Id3d")  # seq, timestamp, position
_MAP_TAIL = struct.Struct("<3d?iiHHI")  # goal, exploration_complete, origin x/y, width, height, len(data)


def _source_and_position(body: bytes | memoryview) -> tuple[str, float, float, int]:
    """(source, position x, y, offset after the position) of a team packet that starts
    ``string source, uint32 seq, float64 timestamp, geometry_msgs/Point position``."""
    try:
        (n,) = _U32.unpack_from(body, 0)
        if n > 256:
            raise RemoteProtocolError(f"team packet source of {n} bytes")
        source = bytes(body[4:4 + n]).decode()
        _seq, _ts, x, y, _z = _BEACON_HEAD.unpack_from(body, 4 + n)
    except (struct.error, UnicodeDecodeError) as err:
        raise RemoteProtocolError(f"malformed team packet: {err}") from err
    if len(source) != n or not (math.isfinite(x) and math.isfinite(y)):
        raise RemoteProtocolError("team packet source or position makes no sense")
    return source, x, y, 4 + n + _BEACON_HEAD.size


def _decode_beacon(body: bytes | memoryview) -> tuple[str, float, float]:
    """What the beacon features read of a ``cryptoros_sim/Hello``: source and position."""
    return _source_and_position(body)[:3]


def _decode_team_map(body: bytes | memoryview) -> tuple[float, float, int, int, int, int, bytes]:
    """What the team-map features read of a ``cryptoros_sim/MapUpdate``: the sender's
    position, the patch's origin (cells), its height and width, and its cells (int8,
    row-major) as bytes."""
    _source, x, y, pos = _source_and_position(body)
    try:
        *_goal, _complete, origin_x, origin_y, width, height, count = _MAP_TAIL.unpack_from(body, pos)
    except struct.error as err:
        raise RemoteProtocolError(f"malformed MapUpdate: {err}") from err
    pos += _MAP_TAIL.size
    if count != width * height or count > MAX_TEAM_MAP_CELLS or pos + count > len(body):
        raise RemoteProtocolError(f"MapUpdate of {width}x{height} cells carries {count} (or too many to check)")
    if not (abs(origin_x) < _MAX_ORIGIN - width and abs(origin_y) < _MAX_ORIGIN - height
            and abs(x) < 1e5 and abs(y) < 1e5):
        raise RemoteProtocolError("MapUpdate origin or position out of range")
    return x, y, origin_x, origin_y, height, width, bytes(body[pos:pos + count])


_DECODERS: dict[str, Callable[[Any], Any]] = {"pose": _decode_pose, "twist": _decode_twist, "scan": _decode_scan,
                                              "beacon": _decode_beacon, "team_map": _decode_team_map}


class StreamFeatures:
    """The features of one (publisher, topic) stream; keeps only what the next
    message's features need (the previous message's values and a bounded window of
    arrival times)."""

    __slots__ = ("kind", "names", "_decode", "_arrivals", "_reads", "_size", "_prev", "_prev_at", "_robot", "_crosscheck",
                 "_beacon_from", "_reach", "_visited", "_claims", "_walls", "_content")

    def __init__(self, typename: str, *, codec: str = "ros1", topic: str = "",
                 crosscheck: Crosscheck | None = None, beacon_from: str | None = None) -> None:
        """``codec``: how bodies are serialized, ``ros1`` (TCPROS) or ``cdr`` (ROS 2).
        ``topic`` and ``crosscheck``: the stream's topic and the :class:`Crosscheck` it
        shares with the other streams (none: no checks across streams).
        ``beacon_from``: the manager the stream comes from; its beacons count only for
        the robot of that name (None: a recording, every beacon counts)."""
        self.kind = kind_of(typename, codec)
        self.names = FEATURES[self.kind]
        self._decode: Callable[[Any], Any] | None = None
        #: the kind's content features (``_pose``, ``_scan``...)
        self._content: Callable[[Any, float, float], tuple[float, ...]] | None = getattr(self, f"_{self.kind}", None)
        if self.kind != "any":
            if codec == "cdr":
                self._decode = _cdr_decoder(typename, self.kind)
            else:
                self._decode = _DECODERS.get(self.kind) or msgs.deserializer(typename)
        self._robot = robot_of(topic)
        self._crosscheck = crosscheck
        self._beacon_from = beacon_from
        self._reach = _Grid(MAX_REACH_CELLS)  # team_map: coarse places in reach of a reported position
        self._visited: set[tuple[int, int]] = set()  # team_map: coarse places of the reported positions
        self._claims: deque[tuple[float, float, float]] = deque(maxlen=64)  # team_map: (arrival, unseen, erased)
        self._walls = _Grid(MAX_WALL_CELLS)  # team_map: cells this stream claimed occupied
        self._arrivals: deque[float] = deque(maxlen=MAX_RATE_SAMPLES)
        self._reads: deque[float] = deque(maxlen=BURST_INTERVALS + 1)  # for burst_hz: the last arrivals (reads)
        self._size: int | None = None
        self._prev: Any = None  # the previous message's content values (per kind)
        self._prev_at = 0.0

    def observe(self, body: bytes | memoryview, now: float, wall: float) -> tuple[float, ...]:
        """Features of one message body arriving at monotonic ``now`` (wall clock
        ``wall``, for the stamp's age)."""
        arrivals = self._arrivals
        arrivals.append(now)
        while arrivals and arrivals[0] <= now - RATE_WINDOW_S:
            arrivals.popleft()
        reads = self._reads
        if not reads or now - reads[-1] > BURST_MERGE_S:
            reads.append(now)
        burst = BURST_INTERVALS / max(reads[-1] - reads[0], 1e-3) if len(reads) > BURST_INTERVALS else 0.0
        size = len(body)
        size_change = abs(size - self._size) / max(1, self._size) if self._size is not None else 0.0
        self._size = size
        common = (float(len(arrivals)), burst, size_change)
        if self._decode is None:
            return (*common, 0.0)
        try:
            msg = self._decode(body)
            content = self._content(msg, now, wall)
        except (CryptorosError, AttributeError, ValueError, TypeError):
            return (*common, 1.0) + (0.0,) * (len(self.names) - len(_COMMON))
        self._prev_at = now
        return (*common, 0.0, *content)

    def reference(self, body: bytes | memoryview, now: float, wall: float) -> None:
        """What one message of a stream that is never scored (this host's own beacons)
        tells the cross-check: its content is read, its features are not computed."""
        if self._decode is None or self._content is None:
            return
        try:
            self._content(self._decode(body), now, wall)
        except (CryptorosError, AttributeError, ValueError, TypeError):
            return

    # -- per kind: the content features, and what the next message compares with
    def _stamps(self, stamp: float, prev_stamp: float | None, wall: float) -> tuple[float, float]:
        back = max(0.0, prev_stamp - stamp) if prev_stamp is not None else 0.0
        return back, abs(wall - stamp)  # old (a replay) or ahead of the clock (made up)

    def _pose(self, msg: Any, now: float, wall: float) -> tuple[float, ...]:
        stamp, x, y = msg
        prev = self._prev
        speed = 0.0
        if prev is not None:
            px, py, pstamp = prev
            dt = stamp - pstamp if stamp > pstamp else now - self._prev_at
            speed = math.hypot(x - px, y - py) / max(dt, 1e-3)
        back, lag = self._stamps(stamp, prev[2] if prev is not None else None, wall)
        self._prev = (x, y, stamp)
        gap = 0.0
        if self._crosscheck is not None and self._robot and math.isfinite(x) and math.isfinite(y):
            gap = self._crosscheck.pose(self._robot, self, now, x, y)
        return speed, back, lag, gap

    def _beacon(self, msg: Any, now: float, wall: float) -> tuple[float, ...]:
        source, x, y = msg
        if self._crosscheck is not None and self._beacon_from in (None, source):
            self._crosscheck.beacon(source, now, x, y)
        return ()

    def _team_map(self, msg: Any, now: float, wall: float) -> tuple[float, ...]:
        x, y, origin_x, origin_y, h, w, cells = msg
        self._note_reach(x, y)
        if h * w > NUMPY_FROM_CELLS:
            unseen, erased = self._big_team_map(origin_x, origin_y, h, w, cells)
        else:
            unseen = self._unseen(origin_x, origin_y, h, w, cells)
            erased = self._walls_erased(origin_x, origin_y, h, w, cells)
        claims = self._claims
        claims.append((now, unseen, erased))
        while claims and claims[0][0] < now - CLAIM_HOLD_S:
            claims.popleft()
        return max(c[1] for c in claims), max(c[2] for c in claims)

    def _unseen(self, origin_x: int, origin_y: int, h: int, w: int, cells: bytes) -> float:
        """The share of the patch's known cells out of reach of every reported position."""
        unseen = 0.0
        # the grid of places in reach over the patch's coarse places (outside it: out of
        # reach); when some are not, spread to the patch's cells (each place repeated over
        # the cells it covers: the patch's places are consecutive), then the known cells
        row0, row_cells = _places(origin_y, h)
        col0, col_cells = _places(origin_x, w)
        reach, rows, cols = self._reach, len(row_cells), len(col_cells)
        if reach.covers(row0, col0, rows, cols):  # the honest robot's case: every place in reach, nothing unseen
            every = reach.footprint(rows, cols)
            in_reach = ((reach.bits >> reach.shift(row0, col0)) & every) == every
        else:
            in_reach = False
        if not in_reach:
            known = int.from_bytes(cells.translate(_KNOWN), "little")
            total = known.bit_count()
            if total:
                places = _spread(reach.window(row0, col0, rows, cols), row_cells, col_cells)
                unseen = (total - (known & int.from_bytes(places, "little")).bit_count()) / total
        return unseen

    def _big_team_map(self, origin_x: int, origin_y: int, h: int, w: int, cells: bytes) -> tuple[float, float]:
        """:meth:`_unseen` and :meth:`_walls_erased` of a big patch, the same shares
        computed with numpy arrays (the places in reach spread to the cells with
        ``np.repeat``)."""
        import numpy as np

        patch = np.frombuffer(cells, dtype=np.int8).reshape(h, w)
        row0, row_cells = _places(origin_y, h)
        col0, col_cells = _places(origin_x, w)
        in_reach = self._reach.array(row0, col0, len(row_cells), len(col_cells))
        unseen = 0.0
        if not in_reach.all():
            known = patch != -1
            total = int(np.count_nonzero(known))
            if total:
                reach_cells = np.repeat(np.repeat(in_reach, row_cells, axis=0), col_cells, axis=1)
                unseen = (total - int(np.count_nonzero(known & reach_cells))) / total
        before = self._walls.array(origin_y, origin_x, h, w)
        n = int(np.count_nonzero(before))
        erased = int(np.count_nonzero(before & (patch == 0))) / n if n else 0.0
        self._walls.mark_array(origin_y, origin_x, patch > 0)
        return unseen, erased

    def _walls_erased(self, origin_x: int, origin_y: int, h: int, w: int, cells: bytes) -> float:
        """The share of the walls this stream claimed before (within this update's patch)
        that this update calls free: a robot's own observations only grow, and a wall it
        saw stays a wall. Remembers this update's walls (a grid of at most
        :data:`MAX_WALL_CELLS`: beyond it, walls are not remembered)."""
        walls = self._walls
        if not walls.take(origin_y, origin_x, h, w):  # past the bound: read what is there, remember nothing
            before = walls.window(origin_y, origin_x, h, w)
            n = before.count(1)
            return _ones(before, cells.translate(_FREE)) / n if n else 0.0
        at = walls.shift(origin_y, origin_x)
        laid = walls.laid_out(cells, h, w)
        before = (walls.bits >> at) & walls.footprint(h, w)
        n = before.bit_count()
        erased = (before & int.from_bytes(laid.translate(_FREE), "little")).bit_count() / n if n else 0.0
        walls.bits |= int.from_bytes(laid.translate(_WALL), "little") << at
        return erased

    def _note_reach(self, x: float, y: float) -> None:
        """Every coarse place within sensor reach of (x, y) is one the sender can have seen."""
        place = (math.floor(y / REACH_CELL_M), math.floor(x / REACH_CELL_M))  # (row, column)
        if place in self._visited or len(self._visited) >= MAX_VISITED:
            return
        self._visited.add(place)
        reach, side = self._reach, 2 * _REACH_RADIUS + 1
        row0, col0 = place[0] - _REACH_RADIUS, place[1] - _REACH_RADIUS
        if reach.take(row0, col0, side, side):
            reach.bits |= _reach_disk_bits(reach.width) << reach.shift(row0, col0)

    def _scan(self, msg: Any, now: float, wall: float) -> tuple[float, ...]:
        """Means over the valid beams only (in range: NaN and inf never are), computed
        with a handful of numpy reductions (no NaN bookkeeping: ``nanmean`` and
        ``errstate`` cost more than the rest of a scan's features together)."""
        import numpy as np

        stamp, geometry, ranges = msg
        range_min, range_max = geometry[3], geometry[4]
        size = ranges.size
        valid = (ranges >= range_min) & (ranges <= range_max)  # NaN compares false: invalid
        n = int(np.count_nonzero(valid))
        every = n == size
        filled = ranges if every else np.where(valid, ranges, 0.0)  # invalid beams add nothing
        scale = max(float(np.add.reduce(filled)) / n if n else 0.0, 1e-3)
        steps = np.abs(filled[1:] - filled[:-1])
        if every:
            rough = float(np.add.reduce(steps)) / (size - 1) / scale if size > 1 else 0.0
        else:  # steps between two valid beams
            pairs = valid[1:] & valid[:-1]
            n_pairs = int(np.count_nonzero(pairs))
            rough = float(np.add.reduce(steps[pairs])) / n_pairs / scale if n_pairs else 0.0
        prev = self._prev
        change = 0.0
        if prev is not None and prev[0].shape == filled.shape:
            prev_filled, prev_valid, prev_every = prev[3], prev[4], prev[5]
            delta = np.abs(filled - prev_filled)
            if every and prev_every:
                change = float(np.add.reduce(delta)) / size / scale if size else 0.0
            else:  # beams valid in both scans
                both = valid & prev_valid
                n_both = int(np.count_nonzero(both))
                change = float(np.add.reduce(delta[both])) / n_both / scale if n_both else 0.0
        if not math.isfinite(change):
            change = 0.0
        back, lag = self._stamps(stamp, prev[1] if prev is not None else None, wall)
        moved = 1.0 if prev is not None and prev[2] != geometry else 0.0
        self._prev = (ranges, stamp, geometry, filled, valid, every)
        return rough, change, back, lag, moved

    def _twist(self, msg: Any, now: float, wall: float) -> tuple[float, ...]:
        linear, angular = msg
        return abs(linear), abs(angular)


__all__ = ["FEATURES", "KIND_OF_TYPE", "Crosscheck", "StreamFeatures", "kind_of", "robot_of", "warm_up"]
