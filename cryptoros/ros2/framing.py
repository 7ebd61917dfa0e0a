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
#: length counts kind + channel + payload
_MIN_LENGTH: Final = HEAD.size - 4
DEFAULT_MAX_SIZE: Final = 16 * 1024 * 1024

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
    """``feed(bytes)`` then iterate ``frames()`` for ``(kind, channel, payload)``."""

    __slots__ = ("_buffer", "_max_size", "_kinds")

    def __init__(self, *, max_size: int = DEFAULT_MAX_SIZE, kinds: frozenset[int] = KINDS) -> None:
        self._buffer = bytearray()
        self._max_size = max_size
        self._kinds = kinds

    def feed(self, data: bytes | bytearray | memoryview) -> None:
        self._buffer += data

    @property
    def buffered(self) -> int:
        return len(self._buffer)

    def frames(self) -> list[tuple[int, int, bytes]]:
        """Every complete frame buffered now; the rest stays for the next feed."""
        out = []
        buf = self._buffer
        pos, end = 0, len(buf)
        head = HEAD.size
        while end - pos >= head:
            length, kind, channel = HEAD.unpack_from(buf, pos)
            if length < _MIN_LENGTH or length - _MIN_LENGTH > self._max_size:
                raise FrameError(f"frame of {length} bytes outside 0..{self._max_size}")
            if kind not in self._kinds:
                raise FrameError(f"unexpected frame kind {kind}")
            stop = pos + 4 + length
            if stop > end:
                break
            out.append((kind, channel, bytes(buf[pos + head : stop])))
            pos = stop
        if pos:
            del buf[:pos]
        return out


__all__ = [
    "CALL", "CONTROL", "DATA", "DEFAULT_MAX_SIZE", "FrameDecoder", "FrameError", "HEAD", "ID", "KINDS", "MESSAGE",
    "PUBLISH", "REPLY", "REQUEST", "RESULT", "SRV_REQUEST", "SRV_RESPONSE", "decode_control", "encode",
    "encode_control", "split_status",
]
