"""The preamble that opens every stream between two interceptors, sans-IO.

After the mutual-TLS handshake, the connecting interceptor sends one
:class:`Preamble` (its access token and what the stream is for) and the accepting
interceptor answers one :class:`PreambleReply`. From then on the stream carries the
relayed bytes untouched. The token therefore travels once per stream, never per
message.

Wire format, both directions::

    b"CRT" + u8 version (1) + u8 kind (1 = preamble, 2 = reply) + u32 LE length + JSON

The JSON body is an object with exactly the fields of the dataclass. The declared
length is checked against ``max_size`` before a byte of the body is buffered; any
deviation raises :class:`~cryptoros.errors.RemoteProtocolError`. A refusal is opaque
on the wire (``{"ok": false, "error": "denied"}``); the reason stays in the log of the
side that refused.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from typing import Final

from cryptoros.errors import LocalProtocolError, RemoteProtocolError
from cryptoros.sansio import NEED_DATA, ReceiveBuffer, TrailingData
from cryptoros.sansio import NeedData as _NeedData

MAGIC: Final = b"CRT"
VERSION: Final = 1
KIND_PREAMBLE: Final = 1
KIND_REPLY: Final = 2
DEFAULT_MAX_SIZE: Final = 64 * 1024
_HEAD = struct.Struct("<3sBBI")

#: What a stream between interceptors may be for.
#: ``refresh`` carries nothing: it shows the peer our current token and takes its own.
PURPOSES: Final = frozenset({"master", "node", "topic", "service", "ros2", "refresh"})
MAX_TARGET_LENGTH: Final = 512


@dataclass(frozen=True, kw_only=True, slots=True)
class Preamble:
    """Sent by the connecting interceptor right after the TLS handshake."""

    token: str
    purpose: str
    target: str

    def __post_init__(self) -> None:
        if not isinstance(self.token, str) or not self.token:
            raise LocalProtocolError("preamble token must be a non-empty string")
        if self.purpose not in PURPOSES:
            raise LocalProtocolError(f"unknown stream purpose {self.purpose!r}")
        if not isinstance(self.target, str) or len(self.target) > MAX_TARGET_LENGTH:
            raise LocalProtocolError("preamble target must be a string of at most 512 characters")


@dataclass(frozen=True, kw_only=True, slots=True)
class PreambleReply:
    """The accepting interceptor's answer. ``error`` is opaque by design.

    On success the accepting side sends its own access token too, so each end checks
    the other's grants against the ROS connection headers (mutual, as in CryptoROS).
    """

    ok: bool
    error: str = ""
    token: str = ""


_KINDS: Final = {KIND_PREAMBLE: Preamble, KIND_REPLY: PreambleReply}


def encode(event: Preamble | PreambleReply) -> bytes:
    """Bytes for one preamble or reply."""
    if isinstance(event, Preamble):
        kind, body = KIND_PREAMBLE, {"token": event.token, "purpose": event.purpose, "target": event.target}
    elif isinstance(event, PreambleReply):
        kind, body = KIND_REPLY, {"ok": event.ok, "error": event.error, "token": event.token}
    else:
        raise LocalProtocolError(f"cannot encode {type(event).__name__}")
    data = json.dumps(body, separators=(",", ":")).encode("utf-8")
    return _HEAD.pack(MAGIC, VERSION, kind, len(data)) + data


class PreambleReader:
    """Reads exactly one preamble (or one reply) from the start of a stream.

    ``expect`` is :class:`Preamble` on the accepting side, :class:`PreambleReply` on
    the connecting side. After the event, :attr:`trailing_data` is ``(data, closed)``:
    whatever bytes of the relayed stream arrived in the same read, and whether the
    peer closed (``reader.trailing_data()`` gives ``data`` alone).
    """

    def __init__(self, expect: type[Preamble] | type[PreambleReply], *, max_size: int = DEFAULT_MAX_SIZE) -> None:
        if expect not in (Preamble, PreambleReply):
            raise LocalProtocolError("expect must be Preamble or PreambleReply")
        self._expect = expect
        self._max_size = max_size
        self._rb = ReceiveBuffer()
        self._event: Preamble | PreambleReply | None = None

    def receive_data(self, data: bytes) -> None:
        """Buffer bytes from the peer; ``b""`` means the peer closed."""
        if self._event is not None:
            raise LocalProtocolError("the preamble was already read; relay the rest yourself")
        self._rb.feed(data)
        if data and len(self._rb) >= _HEAD.size:
            self._check_head()

    def _check_head(self) -> tuple[int, int]:
        magic, version, kind, length = _HEAD.unpack_from(self._rb.data)
        if magic != MAGIC:
            raise RemoteProtocolError("not a cryptoros stream (bad magic)")
        if version != VERSION:
            raise RemoteProtocolError(f"unsupported preamble version {version}")
        if _KINDS.get(kind) is not self._expect:
            raise RemoteProtocolError(f"unexpected preamble kind {kind}")
        if length > self._max_size:
            raise RemoteProtocolError(f"preamble of {length} bytes exceeds the limit of {self._max_size}")
        return kind, length

    def next_event(self) -> Preamble | PreambleReply | _NeedData:
        if self._event is not None:
            return self._event
        if len(self._rb) < _HEAD.size:
            if self._rb.closed:
                raise RemoteProtocolError("stream closed before the preamble was complete")
            return NEED_DATA
        _, length = self._check_head()
        end = _HEAD.size + length
        if len(self._rb) < end:
            if self._rb.closed:
                raise RemoteProtocolError("stream closed in the middle of the preamble")
            return NEED_DATA
        self._rb.discard(_HEAD.size)
        body = self._rb.maybe_extract(length)
        assert body is not None
        self._event = self._decode(body)
        return self._event

    def _decode(self, body: bytes) -> Preamble | PreambleReply:
        try:
            fields = json.loads(body.decode("utf-8"))
        except (UnicodeDecodeError, ValueError) as exc:
            raise RemoteProtocolError(f"preamble body is not UTF-8 JSON: {exc}") from exc
        if not isinstance(fields, dict):
            raise RemoteProtocolError("preamble body is not a JSON object")
        try:
            if self._expect is Preamble:
                if set(fields) != {"token", "purpose", "target"}:
                    raise RemoteProtocolError(f"preamble fields {sorted(fields)} are not token, purpose, target")
                return Preamble(token=fields["token"], purpose=fields["purpose"], target=fields["target"])
            if (
                set(fields) != {"ok", "error", "token"}
                or not isinstance(fields["ok"], bool)
                or not isinstance(fields["error"], str)
                or not isinstance(fields["token"], str)
            ):
                raise RemoteProtocolError("malformed preamble reply")
            return PreambleReply(ok=fields["ok"], error=fields["error"], token=fields["token"])
        except LocalProtocolError as exc:  # the peer's values failed validation
            raise RemoteProtocolError(str(exc)) from exc

    @property
    def trailing_data(self) -> TrailingData:
        """``(data, closed)``: bytes received after the preamble (the start of the
        relayed stream) and whether the peer closed. ``reader.trailing_data()``
        gives ``data`` alone."""
        if self._event is None:
            raise LocalProtocolError("no preamble read yet")
        return self._rb.trailing()


__all__ = [
    "DEFAULT_MAX_SIZE",
    "NEED_DATA",
    "PURPOSES",
    "Preamble",
    "PreambleReader",
    "PreambleReply",
    "encode",
]
