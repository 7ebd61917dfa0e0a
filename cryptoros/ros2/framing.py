"""Length-prefixed frames, sans-IO, standard library only.

Used on both links of the ROS 2 role: the local socket between the interceptor and
its DDS bridge child, and the mutual-TLS streams between two interceptors (after the
preamble). One frame::

    u32 LE length (of what follows) + u8 kind + u32 LE channel + payload

``channel`` names a topic or service endpoint on the local link and a request id on a
service stream. The declared length is checked against ``max_size`` before a byte of
the body is buffered (h2's ``frame_buffer``); a violation raises :class:`FrameError`.
This module must stay importable by the bridge's python, which has no cryptoros
dependencies installed: no imports beyond the standard library.
"""

from __future__ import annotations

import json
import struct
from typing import Any, Final

HEAD: Final = struct.Struct("<IBI")
ID: Final = struct.Struct("<I")
_LENGTH: Final = struct.Struct("<I")
#: length counts kind + channel + payload
_MIN_LENGTH: Final = HEAD.size - 4
DEFAULT_MAX_SIZE: Final = 16 * 1024 * 1024
#: bytes a frame of the local link between an interceptor and its bridge may carry beyond
#: ``max_message_size``: the call or request id before a service body (4) and a status
#: byte, with room to spare. Both ends allow it: a peer's service frame of exactly
#: max_message_size, given its id here, was 4 bytes over the bridge's limit, and the
#: bridge took that for a broken link and exited (a ROS 2 audit: every flow of the robot
#: down 2 s, again each time the peer sent one)
LINK_SLACK: Final = 64

# ---- kinds, local link (interceptor <-> bridge)
CONTROL: Final = 1  # JSON object, either direction
PUBLISH: Final = 2  # interceptor -> bridge: CDR to publish on channel
MESSAGE: Final = 3  # bridge -> interceptor: CDR received on channel
CALL: Final = 4  # interceptor -> bridge: u32 id + CDR request for the local server behind channel
RESULT: Final = 5  # bridge -> interceptor: u32 id + u8 ok + CDR response of a CALL
REQUEST: Final = 6  # bridge -> interceptor: u32 id + CDR request a local client sent to proxy channel
REPLY: Final = 7  # interceptor -> bridge: u32 id + u8 ok + CDR response for a REQUEST

# ---- kinds, between interceptors (after the preamble)
DATA: Final = 16  # topic stream: one serialized message (channel unused, 0)
SRV_REQUEST: Final = 17  # service stream, caller -> server side: channel = request id
SRV_RESPONSE: Final = 18  # service stream, server side -> caller: channel = request id, payload u8 ok + CDR

KINDS: Final = frozenset({CONTROL, PUBLISH, MESSAGE, CALL, RESULT, REQUEST, REPLY, DATA, SRV_REQUEST, SRV_RESPONSE})


class FrameError(ValueError):
    """The other side sent something that is not a valid frame."""


def encode(kind: int, channel: int, payload: bytes | bytearray | memoryview = b"") -> bytes:
    return HEAD.pack(_MIN_LENGTH + len(payload), kind, channel) + payload


def encode_control(obj: dict[str, Any]) -> bytes:
    return encode(CONTROL, 0, json.dumps(obj, separators=(",", ":")).encode("utf-8"))


def decode_control(payload: bytes) -> dict[str, Any]:
    try:
        obj = json.loads(bytes(payload).decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise FrameError(f"control frame is not UTF-8 JSON: {exc}") from exc
    if not isinstance(obj, dict) or not isinstance(obj.get("op"), str):
        raise FrameError("control frame is not a JSON object with an op")
    return obj


def split_status(payload: bytes) -> tuple[bool, bytes]:
    """``u8 ok + CDR`` -> (ok, CDR)."""
    if len(payload) < 1 or payload[0] not in (0, 1):
        raise FrameError("response without a status byte")
    return payload[0] == 1, payload[1:]


class FrameDecoder:
    """``feed(bytes)`` then iterate ``frames()`` for ``(kind, channel, payload)``, or
    ``runs()`` for runs of consecutive frames of one kind and channel kept whole.

    A fed chunk is parsed where it is (no copy) unless an incomplete frame is waiting;
    only the incomplete rest is kept for the next feed. Every header is checked
    (length against ``max_size``, kind) as soon as its 9 bytes are there, before
    the body is waited for.
    """

    __slots__ = ("_buffer", "_chunk", "_max_size", "_kinds")

    def __init__(self, *, max_size: int = DEFAULT_MAX_SIZE, kinds: frozenset[int] = KINDS) -> None:
        self._buffer = bytearray()  # the incomplete rest of earlier feeds
        self._chunk: bytes | bytearray | memoryview = b""  # a fed chunk not parsed yet (when nothing waited)
        self._max_size = max_size
        self._kinds = kinds

    def feed(self, data: bytes | bytearray | memoryview) -> None:
        if self._chunk:
            self._buffer += self._chunk
            self._chunk = b""
        if self._buffer:
            self._buffer += data
        else:
            self._chunk = data

    @property
    def buffered(self) -> int:
        return len(self._buffer) + len(self._chunk)

    def _source(self) -> memoryview:
        if self._chunk:
            src, self._chunk = self._chunk, b""
            return memoryview(src)
        return memoryview(self._buffer)

    def _keep(self, src: memoryview, pos: int) -> None:
        """Keep ``src[pos:]`` (an incomplete frame) for the next feed."""
        if src.obj is self._buffer:
            src.release()
            if pos:
                del self._buffer[:pos]
        else:
            self._buffer = bytearray(src[pos:]) if pos < len(src) else bytearray()
            src.release()

    def _head(self, src: memoryview, pos: int) -> tuple[int, int, int]:
        length, kind, channel = HEAD.unpack_from(src, pos)
        if length < _MIN_LENGTH or length - _MIN_LENGTH > self._max_size:
            raise FrameError(f"frame of {length} bytes outside 0..{self._max_size}")
        if kind not in self._kinds:
            raise FrameError(f"unexpected frame kind {kind}")
        return length, kind, channel

    def frames(self) -> list[tuple[int, int, bytes]]:
        """Every complete frame buffered now; the rest stays for the next feed."""
        out = []
        src = self._source()
        pos, end = 0, len(src)
        head = HEAD.size
        try:
            while end - pos >= head:
                length, kind, channel = self._head(src, pos)
                stop = pos + 4 + length
                if stop > end:
                    break
                out.append((kind, channel, bytes(src[pos + head : stop])))
                pos = stop
        finally:
            self._keep(src, pos)
        return out

    def runs(self) -> list[tuple[int, int, int, bytearray]]:
        """Every complete frame buffered now as ``(kind, channel, count, frames)``: each run
        of consecutive frames of one kind and channel, headers included, in one copy (to
        pass on with :func:`retag`, without splitting the messages apart)."""
        out: list[tuple[int, int, int, bytearray]] = []
        src = self._source()
        pos, end = 0, len(src)
        head = HEAD.size
        start, run_kind, run_chan, count = 0, -1, -1, 0
        try:
            while end - pos >= head:
                length, kind, channel = self._head(src, pos)
                stop = pos + 4 + length
                if stop > end:
                    break
                if (kind, channel) != (run_kind, run_chan):
                    if count:
                        out.append((run_kind, run_chan, count, bytearray(src[start:pos])))
                    start, run_kind, run_chan, count = pos, kind, channel, 0
                count += 1
                pos = stop
            if count:
                out.append((run_kind, run_chan, count, bytearray(src[start:pos])))
        finally:
            self._keep(src, pos)
        return out


def retag(frames: bytearray, kind: int, channel: int) -> bytearray:
    """Rewrite the kind and channel of every frame in ``frames`` (complete, checked frames,
    as :meth:`FrameDecoder.runs` gives them) in place; returns ``frames``."""
    unpack, pack = _LENGTH.unpack_from, HEAD.pack_into
    pos, end = 0, len(frames)
    while pos < end:
        (length,) = unpack(frames, pos)
        pack(frames, pos, length, kind, channel)
        pos += 4 + length
    return frames


def pieces(frames: bytearray, count: int, most: int) -> list[tuple[int, bytearray]]:
    """``count`` complete frames as pieces of at most ``most`` frames each, as
    ``(frames in it, bytes)``; one piece (``frames`` itself) when they fit."""
    if count <= most:
        return [(count, frames)]
    out, view = [], memoryview(frames)
    pos, end, start, n = 0, len(frames), 0, 0
    while pos < end:
        (length,) = _LENGTH.unpack_from(view, pos)
        pos += 4 + length
        n += 1
        if n == most or pos >= end:
            out.append((n, bytearray(view[start:pos])))
            start, n = pos, 0
    view.release()
    return out


def payloads(frames: bytes | bytearray) -> list[bytes]:
    """The payloads of the complete frames in ``frames``."""
    out, view = [], memoryview(frames)
    pos, end, head = 0, len(frames), HEAD.size
    while pos < end:
        (length,) = _LENGTH.unpack_from(view, pos)
        out.append(bytes(view[pos + head : pos + 4 + length]))
        pos += 4 + length
    return out


__all__ = [
    "CALL", "CONTROL", "DATA", "DEFAULT_MAX_SIZE", "LINK_SLACK", "FrameDecoder", "FrameError", "HEAD", "ID", "KINDS", "MESSAGE",
    "PUBLISH", "REPLY", "REQUEST", "RESULT", "SRV_REQUEST", "SRV_RESPONSE", "decode_control", "encode",
    "encode_control", "payloads", "pieces", "retag", "split_status",
]
