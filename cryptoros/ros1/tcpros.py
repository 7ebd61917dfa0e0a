"""TCPROS, sans-IO: connection headers, message frames and service framing.

In the manner of h11: :meth:`TCPROSConnection.receive_data` only buffers (``b""``
means the peer closed), :meth:`TCPROSConnection.next_event` parses and returns an
event or :data:`NEED_DATA`, :meth:`TCPROSConnection.send` turns an event into bytes.
No socket anywhere, so the node, the interceptor, the attack toolkit and the tests
share one parser.

Wire format (ROS 1):

* connection header: ``u32 LE total``, then fields ``u32 LE len`` + ``key=value``;
* topic messages and service requests: ``u32 LE len`` + body;
* service responses: ``u8 ok`` + ``u32 LE len`` + body (on ``ok=0`` the body is the
  error text).

Every declared length is checked against the limits given to the constructor before
a byte of its payload is buffered. Peer garbage raises :class:`RemoteProtocolError`
(and the connection stays errored); misuse of the API raises
:class:`LocalProtocolError`.
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Final

from cryptoros.errors import LocalProtocolError, RemoteProtocolError
from cryptoros.sansio import NEED_DATA, ReceiveBuffer, TrailingData
from cryptoros.sansio import NeedData as _NeedData

__all__ = [
    "NEED_DATA",
    "FrameKind",
    "ConnectionHeader",
    "Message",
    "ServiceResponse",
    "ConnectionClosed",
    "TCPROSConnection",
    "encode_header",
    "decode_header",
    "encode_frame",
    "encode_service_response",
    "check_subscriber_header",
    "check_publisher_header",
    "check_service_client_header",
    "check_service_server_header",
    "DEFAULT_MAX_HEADER_SIZE",
    "DEFAULT_MAX_FRAME_SIZE",
    "DEFAULT_MAX_HEADER_FIELDS",
    "KNOWN_HEADER_FIELDS",
    "canonical_header",
    "FrameWalker",
    "FrameTooLarge",
]

DEFAULT_MAX_HEADER_SIZE: Final = 1 << 20  # 1 MiB: message_definition of big types fits
#: Fields of a connection header: rospy and roscpp send 6 to 9 (a service probe 5).
DEFAULT_MAX_HEADER_FIELDS: Final = 32
#: The fields ROS 1 defines (ros_comm's rospy and roscpp, rosbag, the TCPROS wiki page).
#: An interceptor sends on only these, rebuilt from the parsed values
#: (:func:`canonical_header`); anything else a peer wrote is dropped.
KNOWN_HEADER_FIELDS: Final = (
    "callerid",
    "topic",
    "service",
    "type",
    "md5sum",
    "request_type",
    "response_type",
    "message_definition",
    "tcp_nodelay",
    "latching",
    "persistent",
    "probe",
    "error",
)
DEFAULT_MAX_FRAME_SIZE: Final = 256 << 20  # 256 MiB: large point clouds fit

_U32 = struct.Struct("<I")
_OK_U32 = struct.Struct("<BI")


class FrameKind(enum.Enum):
    """What follows the peer's connection header."""

    MESSAGE = "message"  # u32 len + body (topic data, service requests)
    SERVICE_RESPONSE = "service_response"  # u8 ok + u32 len + body


# ---------------------------------------------------------------- events


@dataclass(frozen=True, kw_only=True, slots=True)
class ConnectionHeader:
    """A TCPROS connection header: ordered ``(key, value)`` fields."""

    fields: tuple[tuple[str, str], ...]

    def __post_init__(self) -> None:
        if isinstance(self.fields, Mapping):
            object.__setattr__(self, "fields", tuple(self.fields.items()))
        else:
            object.__setattr__(self, "fields", tuple((k, v) for k, v in self.fields))
        for key, value in self.fields:
            if not isinstance(key, str) or not isinstance(value, str):
                raise LocalProtocolError("header keys and values must be str")
            if not key or "=" in key:
                raise LocalProtocolError(f"invalid header key {key!r}")

    @classmethod
    def of(cls, mapping: Mapping[str, str] | None = None, /, **kw: str) -> ConnectionHeader:
        items = dict(mapping or {})
        items.update(kw)
        return cls(fields=tuple(items.items()))

    def as_dict(self) -> dict[str, str]:
        """Fields as a dict; a repeated key keeps its last value (as roscpp and rospy do)."""
        return dict(self.fields)

    def get(self, key: str, default: str | None = None) -> str | None:
        for k, v in reversed(self.fields):
            if k == key:
                return v
        return default

    def __getitem__(self, key: str) -> str:
        value = self.get(key)
        if value is None:
            raise KeyError(key)
        return value

    def __contains__(self, key: object) -> bool:
        return any(k == key for k, _ in self.fields)


@dataclass(frozen=True, kw_only=True, slots=True)
class Message:
    """One frame: a serialized message or service request (no length prefix)."""

    data: bytes

    def __post_init__(self) -> None:
        if not isinstance(self.data, (bytes, bytearray, memoryview)):
            raise LocalProtocolError("Message.data must be bytes")


@dataclass(frozen=True, kw_only=True, slots=True)
class ServiceResponse:
    """A service response: ``ok`` and the serialized response (or error text)."""

    ok: bool
    data: bytes

    def __post_init__(self) -> None:
        if not isinstance(self.ok, bool):
            raise LocalProtocolError("ServiceResponse.ok must be bool")
        if not isinstance(self.data, (bytes, bytearray, memoryview)):
            raise LocalProtocolError("ServiceResponse.data must be bytes")

    @property
    def error(self) -> str:
        return "" if self.ok else bytes(self.data).decode("utf-8", "replace")


@dataclass(frozen=True, kw_only=True, slots=True)
class ConnectionClosed:
    """The peer closed the connection cleanly (between frames)."""


Event = ConnectionHeader | Message | ServiceResponse | ConnectionClosed


# ---------------------------------------------------------------- pure helpers


def encode_header(fields: ConnectionHeader | Mapping[str, str] | Iterable[tuple[str, str]]) -> bytes:
    """Encode a connection header (with its u32 total length)."""
    if not isinstance(fields, ConnectionHeader):
        fields = ConnectionHeader(fields=fields)  # type: ignore[arg-type]
    parts = []
    for key, value in fields.fields:
        item = f"{key}={value}".encode()
        parts.append(_U32.pack(len(item)))
        parts.append(item)
    body = b"".join(parts)
    return _U32.pack(len(body)) + body


def decode_header(
    body: bytes | bytearray | memoryview, *, max_fields: int = DEFAULT_MAX_HEADER_FIELDS
) -> ConnectionHeader:
    """Decode a header body (without its u32 total length). Strict: every field must
    fit, hold ``=`` with a non-empty key, and be UTF-8; at most ``max_fields`` fields
    (checked as it goes, so a header of 100,000 tiny fields costs no more than
    ``max_fields`` of them); no key twice."""
    view = memoryview(body)
    n = len(view)
    pos = 0
    fields: list[tuple[str, str]] = []
    seen: set[str] = set()
    while pos < n:
        if len(fields) >= max_fields:
            raise RemoteProtocolError(f"connection header has more than {max_fields} fields")
        if n - pos < 4:
            raise RemoteProtocolError("truncated header field length")
        (size,) = _U32.unpack_from(view, pos)
        pos += 4
        if size > n - pos:
            raise RemoteProtocolError(f"header field length {size} exceeds the header ({n - pos} left)")
        raw = bytes(view[pos : pos + size])
        pos += size
        eq = raw.find(b"=")
        if eq < 0:
            raise RemoteProtocolError(f"header field without '=': {raw[:40]!r}")
        if eq == 0:
            raise RemoteProtocolError("header field with an empty key")
        try:
            key = raw[:eq].decode("utf-8")
            value = raw[eq + 1 :].decode("utf-8")
        except UnicodeDecodeError as err:
            raise RemoteProtocolError(f"header field is not UTF-8: {raw[:40]!r}") from err
        if key in seen:
            raise RemoteProtocolError(f"header field {key[:40]!r} given twice")
        seen.add(key)
        fields.append((key, value))
    return ConnectionHeader(fields=tuple(fields))


def canonical_header(header: ConnectionHeader) -> ConnectionHeader:
    """The header an interceptor sends on in place of ``header``: only the
    :data:`KNOWN_HEADER_FIELDS`, in that order, with the parsed values."""
    d = header.as_dict()
    return ConnectionHeader(fields=tuple((k, d[k]) for k in KNOWN_HEADER_FIELDS if k in d))


def encode_frame(data: bytes | bytearray | memoryview) -> bytes:
    """``u32 len`` + data."""
    return _U32.pack(len(data)) + bytes(data)


def encode_service_response(ok: bool, data: bytes | bytearray | memoryview) -> bytes:
    """``u8 ok`` + ``u32 len`` + data."""
    return _OK_U32.pack(1 if ok else 0, len(data)) + bytes(data)


def _require(header: ConnectionHeader, keys: Iterable[str], what: str) -> dict[str, str]:
    d = header.as_dict()
    missing = [k for k in keys if not d.get(k)]
    if missing:
        raise RemoteProtocolError(f"{what} header lacks {', '.join(missing)}")
    return d


def check_subscriber_header(header: ConnectionHeader) -> dict[str, str]:
    """A subscriber's header, as a publisher receives it: needs ``topic``, ``type``
    (``*`` allowed), ``md5sum`` and ``callerid``."""
    d = _require(header, ("callerid", "topic", "md5sum", "type"), "subscriber")
    if not d["topic"].startswith("/"):
        raise RemoteProtocolError(f"topic is not a global name: {d['topic']!r}")
    return d


def check_publisher_header(header: ConnectionHeader) -> dict[str, str]:
    """A publisher's reply header: ``error`` becomes a RemoteProtocolError; else
    ``type`` and ``md5sum`` are required."""
    d = header.as_dict()
    if "error" in d:
        raise RemoteProtocolError(f"publisher refused the connection: {d['error']}")
    return _require(header, ("md5sum", "type"), "publisher")


def check_service_client_header(header: ConnectionHeader) -> dict[str, str]:
    """A service client's header, as the server receives it."""
    d = _require(header, ("callerid", "service", "md5sum"), "service client")
    if not d["service"].startswith("/"):
        raise RemoteProtocolError(f"service is not a global name: {d['service']!r}")
    return d


def check_service_server_header(header: ConnectionHeader) -> dict[str, str]:
    """A service server's reply header."""
    d = header.as_dict()
    if "error" in d:
        raise RemoteProtocolError(f"service refused the connection: {d['error']}")
    return _require(header, ("md5sum",), "service server")


# ---------------------------------------------------------------- the frame walker


class FrameTooLarge(RemoteProtocolError):
    """A frame declared a length over the limit (checked before a byte of it is kept)."""

    def __init__(self, size: int, limit: int, what: str = "frame") -> None:
        super().__init__(f"declared {what} length {size} exceeds the limit {limit}")
        self.size = size
        self.limit = limit


class FrameWalker:
    """Walks the TCPROS frames after a connection header, sans-IO, without copying
    bodies: only the length prefixes are read. ``u32 LE length`` + body by default;
    with ``service_response=True``, ``u8 ok`` + ``u32 LE length`` + body. A declared
    length over ``max_size`` (None: unbounded) raises :class:`FrameTooLarge` before a
    byte of that frame is buffered or let through; an ``ok`` byte other than 0 or 1
    raises :class:`RemoteProtocolError`.

    Two ways to walk, one prefix check (:meth:`read_prefix`):

    * :meth:`walk` follows a stream fed in arbitrary pieces (the interceptor's pump:
      where may the bytes read so far be cut, how many frames began);
    * :meth:`split` finds the complete frames in a buffer the caller keeps (the node's
      subscriber: bodies are sliced out of its own receive buffer).
    """

    __slots__ = ("_need", "_prefix", "prefix_size", "max_size", "what")

    def __init__(self, *, max_size: int | None = None, service_response: bool = False, what: str = "frame") -> None:
        if max_size is not None and max_size < 0:
            raise LocalProtocolError("max_size must be None or >= 0")
        self._need = 0  # body bytes still to come of the current frame (walk)
        self._prefix = b""  # a length prefix split across reads (walk)
        self.prefix_size = 5 if service_response else 4
        self.max_size = max_size
        self.what = what

    def read_prefix(self, data: bytes | bytearray | memoryview, pos: int = 0) -> int:
        """The body length declared by the whole prefix at ``data[pos:]``, checked."""
        if self.prefix_size == 5:
            ok, size = _OK_U32.unpack_from(data, pos)
            if ok > 1:
                raise RemoteProtocolError(f"service response ok byte is {ok}, not 0 or 1 ({self.what})")
        else:
            (size,) = _U32.unpack_from(data, pos)
        if self.max_size is not None and size > self.max_size:
            raise FrameTooLarge(size, self.max_size, self.what)
        return size

    def walk(self, data: bytes | bytearray | memoryview, allowed: int | None = None) -> tuple[int, int]:
        """Walk the next piece of the stream but start at most ``allowed`` new frames
        (None: any number): returns the offset where the walk stopped (everything
        before may be forwarded) and how many frames were started. A started frame's
        body is always let through."""
        started, pos, n = 0, 0, len(data)
        plen = self.prefix_size
        while pos < n:
            if self._need:
                step = min(self._need, n - pos)
                self._need -= step
                pos += step
                continue
            if not self._prefix:
                if allowed is not None and started >= allowed:
                    break
                if n - pos >= plen:  # the common case: a whole prefix in this piece
                    self._need = self.read_prefix(data, pos)
                    started += 1
                    pos += plen
                    continue
            chunk = bytes(data[pos : pos + plen - len(self._prefix)])
            if not self._prefix:
                started += 1
            pos += len(chunk)
            self._prefix += chunk
            if len(self._prefix) == plen:
                self._need = self.read_prefix(self._prefix)
                self._prefix = b""
        return pos, started

    def split(
        self,
        data: bytes | bytearray | memoryview,
        start: int = 0,
        end: int | None = None,
        *,
        count: int | None = None,
    ) -> tuple[list[tuple[int, int]], int, int | None, RemoteProtocolError | None]:
        """The complete frames in ``data[start:end]``, for a caller that keeps its own
        buffer. Returns ``(spans, stop, pending, error)``: ``(body_start, body_end)``
        of each complete frame, the offset of the first byte not in one, the declared
        body length of the incomplete frame at ``stop`` if its prefix is whole (else
        None), and the error of a bad prefix at ``stop`` (the frames before it are
        still returned, as a subscriber delivers them). At most ``count`` frames
        (None: all)."""
        if end is None:
            end = len(data)
        plen = self.prefix_size
        spans: list[tuple[int, int]] = []
        pos = start
        while end - pos >= plen and (count is None or len(spans) < count):
            try:
                size = self.read_prefix(data, pos)
            except RemoteProtocolError as err:
                return spans, pos, None, err
            stop = pos + plen + size
            if stop > end:
                return spans, pos, size, None
            spans.append((pos + plen, stop))
            pos = stop
        return spans, pos, None, None


# ---------------------------------------------------------------- the connection


class _State(enum.Enum):
    HEADER = "header"
    FRAMES = "frames"
    CLOSED = "closed"
    ERROR = "error"


class TCPROSConnection:
    """One side of a TCPROS connection.

    ``frame_kind`` says how the peer frames what follows its header: plain
    :attr:`FrameKind.MESSAGE` frames (a subscriber receiving topic data, a service
    server receiving requests) or :attr:`FrameKind.SERVICE_RESPONSE` (a service
    client). It can be set after the header arrived (:meth:`set_frame_kind`), for a
    port shared by topics and services demultiplexed on the header.
    """

    __slots__ = (
        "max_header_size",
        "max_header_fields",
        "max_frame_size",
        "frame_kind",
        "_rb",
        "_state",
        "their_header",
        "_walker",
        "_response_walker",
    )

    def __init__(
        self,
        *,
        frame_kind: FrameKind = FrameKind.MESSAGE,
        max_header_size: int = DEFAULT_MAX_HEADER_SIZE,
        max_frame_size: int = DEFAULT_MAX_FRAME_SIZE,
        max_header_fields: int = DEFAULT_MAX_HEADER_FIELDS,
        expect_header: bool = True,
    ) -> None:
        if max_header_size < 4 or max_frame_size < 0 or max_header_fields < 1:
            raise LocalProtocolError("limits must be positive")
        self.max_header_size = max_header_size
        self.max_header_fields = max_header_fields
        self.max_frame_size = max_frame_size
        self.frame_kind = frame_kind
        self._rb = ReceiveBuffer()
        self._state = _State.HEADER if expect_header else _State.FRAMES
        self.their_header: ConnectionHeader | None = None
        self._walker = FrameWalker(max_size=max_frame_size)
        self._response_walker = FrameWalker(max_size=max_frame_size, service_response=True, what="response")

    # -- input
    def receive_data(self, data: bytes | bytearray | memoryview) -> None:
        """Buffer bytes from the peer; ``b""`` means the peer closed."""
        self._rb.feed(data)

    @property
    def trailing_data(self) -> TrailingData:
        """``(data, closed)``: bytes buffered but not parsed yet, and whether EOF was
        seen (for handing the raw stream over to a byte pump after the header check)."""
        return self._rb.trailing()

    def set_frame_kind(self, kind: FrameKind) -> None:
        self.frame_kind = kind

    def next_event(self) -> Event | _NeedData:
        """The next event, or :data:`NEED_DATA`. Raises RemoteProtocolError on garbage."""
        state = self._state
        if state is _State.ERROR:
            raise RemoteProtocolError("connection already failed")
        if state is _State.CLOSED:
            return ConnectionClosed()
        try:
            if state is _State.HEADER:
                event = self._next_header()
            else:
                event = self._next_frame()
        except RemoteProtocolError:
            self._state = _State.ERROR
            raise
        if event is NEED_DATA and self._rb.closed:
            if self._rb or self._state is _State.HEADER:
                where = "header" if self._state is _State.HEADER else "frame"
                self._state = _State.ERROR
                raise RemoteProtocolError(f"connection closed in the middle of a {where}")
            self._state = _State.CLOSED
            return ConnectionClosed()
        return event

    def _next_header(self) -> Event | _NeedData:
        buf = self._rb.data
        if len(buf) < 4:
            return NEED_DATA
        (size,) = _U32.unpack_from(buf, 0)
        if size > self.max_header_size:
            raise RemoteProtocolError(f"declared header length {size} exceeds the limit {self.max_header_size}")
        if len(buf) < 4 + size:
            return NEED_DATA
        header = decode_header(memoryview(buf)[4 : 4 + size], max_fields=self.max_header_fields)
        del buf[: 4 + size]
        self.their_header = header
        self._state = _State.FRAMES
        return header

    def _next_frame(self) -> Event | _NeedData:
        buf = self._rb.data
        if self.frame_kind is FrameKind.MESSAGE:
            if len(buf) < 4:
                return NEED_DATA
            size = self._walker.read_prefix(buf, 0)
            end = 4 + size
            if len(buf) < end:
                return NEED_DATA
            data = bytes(buf[4:end])
            del buf[:end]
            return Message(data=data)
        if len(buf) < 5:
            return NEED_DATA
        size = self._response_walker.read_prefix(buf, 0)
        ok = buf[0]
        end = 5 + size
        if len(buf) < end:
            return NEED_DATA
        data = bytes(buf[5:end])
        del buf[:end]
        return ServiceResponse(ok=bool(ok), data=data)

    def messages(self) -> list[bytes]:
        """Fast path for a data stream after the header: every complete message
        frame buffered now, as bytes (``[]`` if none). Raises like :meth:`next_event`;
        EOF is reported by :meth:`next_event`, not here."""
        if self._state is not _State.FRAMES or self.frame_kind is not FrameKind.MESSAGE:
            if self._state is _State.ERROR:
                raise RemoteProtocolError("connection already failed")
            return []
        buf = self._rb.data
        spans, pos, _pending, error = self._walker.split(buf)
        if error is not None:
            self._state = _State.ERROR
            raise error
        with memoryview(buf) as view:
            out = [bytes(view[a:b]) for a, b in spans]
        if pos:
            del buf[:pos]
        return out

    def pending_frame_size(self) -> int | None:
        """Declared size of the partial message frame at the head of the buffer
        (lets an I/O layer size its receive buffer), or None."""
        if self._state is _State.FRAMES and self.frame_kind is FrameKind.MESSAGE and len(self._rb) >= 4:
            return _U32.unpack_from(self._rb.data, 0)[0]
        return None

    # -- output
    def send(self, event: Event) -> bytes:
        """Bytes for an event of ours (our header, a frame, a service response)."""
        if isinstance(event, Message):
            return encode_frame(event.data)
        if isinstance(event, ConnectionHeader):
            return encode_header(event)
        if isinstance(event, ServiceResponse):
            return encode_service_response(event.ok, event.data)
        if isinstance(event, ConnectionClosed):
            return b""
        raise LocalProtocolError(f"cannot send {event!r}")
