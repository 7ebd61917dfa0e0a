"""What every sans-IO codec of cryptoros shares (h11's ``_util`` and ``_receivebuffer``).

The codecs (:mod:`cryptoros.ros1.tcpros`, :mod:`cryptoros.ros1.xmlrpc`,
:mod:`cryptoros.tunnel`) follow one shape: ``receive_data(bytes)`` only buffers
(``b""`` means the peer closed), ``next_event()`` parses and returns an event or
:data:`NEED_DATA`, and ``trailing_data`` hands the bytes buffered but not parsed to
whoever relays the rest of the stream. This module holds the pieces they share:

* :data:`NEED_DATA`, the one sentinel ("feed me more bytes");
* :class:`ReceiveBuffer`, the bytes received and not yet parsed, with the EOF flag
  and the rules of ``receive_data`` (no data after EOF; an optional bound);
* :class:`TrailingData`, the one form of ``trailing_data``: ``(data, closed)`` as h11.
"""

from __future__ import annotations

from typing import Final, NamedTuple

from cryptoros.errors import LocalProtocolError, RemoteProtocolError

__all__ = ["NEED_DATA", "NeedData", "ReceiveBuffer", "TrailingData"]


class NeedData:
    """Type of :data:`NEED_DATA`; there is exactly one instance."""

    __slots__ = ()
    _instance: NeedData | None = None

    def __new__(cls) -> NeedData:
        if cls._instance is None:
            cls._instance = super().__new__(cls)
        return cls._instance

    def __repr__(self) -> str:
        return "NEED_DATA"

    def __reduce__(self) -> str:
        return "NEED_DATA"


#: Returned by every codec's ``next_event()`` when it needs more bytes.
NEED_DATA: Final = NeedData()


class TrailingData(NamedTuple):
    """Bytes a codec buffered but did not parse, and whether the peer closed.

    Every codec's ``trailing_data`` property returns one (``data, closed =
    conn.trailing_data``). Calling it, ``conn.trailing_data()``, gives ``data``
    alone: the spelling :class:`cryptoros.tunnel.PreambleReader` had before.
    """

    data: bytes
    closed: bool

    def __call__(self) -> bytes:
        return self.data


class ReceiveBuffer:
    """Bytes received and not yet parsed, plus whether the peer closed.

    ``feed(b"")`` marks EOF; bytes fed after EOF are an API misuse
    (:class:`LocalProtocolError`). ``max_size`` (None: no bound) caps what may sit
    unparsed: a feed that would exceed it raises :class:`RemoteProtocolError`
    before the bytes are kept. The parser reads :attr:`data` (a ``bytearray``, for
    ``struct.unpack_from`` and ``find``) and takes what it parsed with
    :meth:`maybe_extract`, :meth:`discard` or :meth:`take_all`.
    """

    __slots__ = ("data", "closed", "max_size")

    def __init__(self, *, max_size: int | None = None) -> None:
        if max_size is not None and max_size < 0:
            raise LocalProtocolError("max_size must be None or >= 0")
        self.data = bytearray()
        self.closed = False
        self.max_size = max_size

    def feed(self, data: bytes | bytearray | memoryview) -> None:
        """Keep ``data``; ``b""`` means the peer closed."""
        if self.closed:
            if data:
                raise LocalProtocolError("receive_data after EOF")
            return
        if not data:
            self.closed = True
            return
        if self.max_size is not None and len(self.data) + len(data) > self.max_size:
            raise RemoteProtocolError(f"more than {self.max_size} bytes buffered unparsed")
        self.data += data

    def __len__(self) -> int:
        return len(self.data)

    def __bool__(self) -> bool:
        return bool(self.data)

    def __bytes__(self) -> bytes:
        return bytes(self.data)

    def maybe_extract(self, count: int) -> bytes | None:
        """The first ``count`` bytes, removed from the buffer, or None if fewer are
        buffered."""
        if count < 0:
            raise LocalProtocolError("count must be >= 0")
        if len(self.data) < count:
            return None
        out = bytes(self.data[:count])
        del self.data[:count]
        return out

    def discard(self, count: int) -> None:
        """Drop the first ``count`` bytes (already parsed in place)."""
        del self.data[:count]

    def take_all(self) -> bytes:
        """Everything buffered, removed from the buffer."""
        out = bytes(self.data)
        self.data.clear()
        return out

    def trailing(self) -> TrailingData:
        """What is buffered (left in place) and whether the peer closed."""
        return TrailingData(bytes(self.data), self.closed)
