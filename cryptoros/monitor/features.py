"""Features of one publisher's messages on one topic, message by message (sans-IO).

:class:`StreamFeatures` is fed a message body (ROS 1 serialization, as the TCPROS
frame carries it) and its arrival time, and returns the message's features as a
tuple in the order :data:`FEATURES` gives for its kind. Everything is "higher is more
suspicious", so a model is one upper limit per feature (:mod:`cryptoros.monitor.model`).

Kinds and what they show (seed 001's attacks and the demo's insiders):

* every type (``any``): ``rate_hz`` (messages in the last second: a flood),
  ``size_change`` (relative change of the body size from the previous message);
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
  ``|angular.z|`` (a command no controller would send).

A body that does not decode as its type scores as its own feature, ``malformed`` (1.0);
a feature that comes out NaN or infinite (a pose at NaN) scores as infinitely over its
limit (:mod:`cryptoros.monitor.model`).
"""

from __future__ import annotations

import math
import struct
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np

from cryptoros.errors import CryptorosError, RemoteProtocolError
from cryptoros.ros1 import msgs

KIND_OF_TYPE = {
    "geometry_msgs/PoseStamped": "pose",
    "sensor_msgs/LaserScan": "scan",
    "geometry_msgs/Twist": "twist",
}
_COMMON = ("rate_hz", "size_change", "malformed")
FEATURES: dict[str, tuple[str, ...]] = {
    "any": _COMMON,
    "pose": (*_COMMON, "speed_mps", "stamp_back_s", "stamp_lag_s"),
    "scan": (*_COMMON, "roughness", "scan_change", "stamp_back_s", "stamp_lag_s", "geometry_change"),
    "twist": (*_COMMON, "linear", "angular"),
}
RATE_WINDOW_S = 1.0
#: arrival times kept for the rate (a flood faster than this per second reads as this)
MAX_RATE_SAMPLES = 4096


def kind_of(typename: str) -> str:
    """The kind of a ROS 1 (``pkg/Name``) or ROS 2 (``pkg/msg/Name``) type name."""
    return KIND_OF_TYPE.get(typename.replace("/msg/", "/"), "any")


def _cdr_decoder(typename: str, kind: str) -> Callable[[Any], Any]:
    """A decoder of ROS 2 (CDR) samples giving what the kind's features read."""
    from cryptoros.ros2.cdr import deserializer

    decode = deserializer(typename)
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


class StreamFeatures:
    """The features of one (publisher, topic) stream; keeps only what the next
    message's features need (the previous message's values and a bounded window of
    arrival times)."""

    __slots__ = ("kind", "names", "_decode", "_arrivals", "_size", "_prev", "_prev_at")

    def __init__(self, typename: str, *, codec: str = "ros1") -> None:
        """``codec``: how bodies are serialized, ``ros1`` (TCPROS) or ``cdr`` (ROS 2)."""
        self.kind = kind_of(typename)
        self.names = FEATURES[self.kind]
        self._decode: Callable[[Any], Any] | None = None
        if self.kind != "any":
            if codec == "cdr":
                self._decode = _cdr_decoder(typename, self.kind)
            else:
                self._decode = _decode_scan if self.kind == "scan" else msgs.deserializer(typename)
        self._arrivals: deque[float] = deque(maxlen=MAX_RATE_SAMPLES)
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
        size = len(body)
        size_change = abs(size - self._size) / max(1, self._size) if self._size is not None else 0.0
        self._size = size
        common = (float(len(arrivals)), size_change)
        if self._decode is None:
            return (*common, 0.0)
        try:
            msg = self._decode(body)
            content = getattr(self, f"_{self.kind}")(msg, now, wall)
        except (CryptorosError, AttributeError, ValueError, TypeError):
            return (*common, 1.0) + (0.0,) * (len(self.names) - 3)
        self._prev_at = now
        return (*common, 0.0, *content)

    # -- per kind: the content features, and what the next message compares with
    def _stamps(self, stamp: float, prev_stamp: float | None, wall: float) -> tuple[float, float]:
        back = max(0.0, prev_stamp - stamp) if prev_stamp is not None else 0.0
        return back, abs(wall - stamp)  # old (a replay) or ahead of the clock (made up)

    def _pose(self, msg: Any, now: float, wall: float) -> tuple[float, ...]:
        p = msg.pose.position
        x, y, stamp = float(p.x), float(p.y), _stamp(msg)
        prev = self._prev
        speed = 0.0
        if prev is not None:
            px, py, pstamp = prev
            dt = stamp - pstamp if stamp > pstamp else now - self._prev_at
            speed = math.hypot(x - px, y - py) / max(dt, 1e-3)
        back, lag = self._stamps(stamp, prev[2] if prev is not None else None, wall)
        self._prev = (x, y, stamp)
        return speed, back, lag

    def _scan(self, msg: Any, now: float, wall: float) -> tuple[float, ...]:
        import numpy as np

        stamp, geometry, ranges = msg
        range_min, range_max = geometry[3], geometry[4]
        valid = (ranges >= range_min) & (ranges <= range_max)  # NaN compares false: invalid
        prev = self._prev
        if valid.all():  # the common case, without NaN bookkeeping
            kept = ranges
            scale = max(float(kept.mean()) if kept.size else 0.0, 1e-3)
            rough = float(np.abs(np.diff(kept)).mean()) / scale if kept.size > 1 else 0.0
            same = prev is not None and prev[0].shape == kept.shape
            change = float(np.nanmean(np.abs(kept - prev[0]))) / scale if same and kept.size else 0.0
        else:
            kept = np.where(valid, ranges, np.nan)
            with np.errstate(invalid="ignore"):
                scale = max(float(np.nanmean(kept)) if valid.any() else 0.0, 1e-3)
                steps = np.abs(np.diff(kept))
                rough = float(np.nanmean(steps)) / scale if np.isfinite(steps).any() else 0.0
                change = 0.0
                if prev is not None and prev[0].shape == kept.shape:
                    delta = np.abs(kept - prev[0])
                    change = float(np.nanmean(delta)) / scale if np.isfinite(delta).any() else 0.0
        if not math.isfinite(change):
            change = 0.0
        back, lag = self._stamps(stamp, prev[1] if prev is not None else None, wall)
        moved = 1.0 if prev is not None and prev[2] != geometry else 0.0
        self._prev = (kept, stamp, geometry)
        return rough, change, back, lag, moved

    def _twist(self, msg: Any, now: float, wall: float) -> tuple[float, ...]:
        return abs(float(msg.linear.x)), abs(float(msg.angular.z))


__all__ = ["FEATURES", "KIND_OF_TYPE", "StreamFeatures", "kind_of"]
