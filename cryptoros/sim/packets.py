"""Simulator packets: ROS 1 ``.msg`` types serialized with the project's serializer.

The definitions live as files in ``cryptoros/sim/msg/`` (package ``cryptoros_sim``) and
are modelled on the paper's Tables 1 and 2. Every packet the simulator puts on the
radio is the real ROS 1 wire encoding (:mod:`cryptoros.ros1.msgs`), so packet sizes
and byte counts are those a ROS node would send.

A :class:`Frame` is what travels on the radio: the type name and the bytes. The
channel hands the *same* frame object to every receiver; :meth:`Frame.decode` caches
the parsed message (parsing equal bytes always gives an equal message, so the cache
changes wall time, never results). Decoded messages are shared: never mutate them,
build a new one with :func:`dataclasses.replace`.
"""

from __future__ import annotations

import dataclasses
from functools import cache
from importlib import resources
from typing import Any

from cryptoros.ros1 import msgs

PKG = "cryptoros_sim"
HELLO = f"{PKG}/Hello"
LSU = f"{PKG}/LinkStateUpdate"
PROTOCOL = f"{PKG}/ProtocolPacket"
RECRUIT = f"{PKG}/RecruitPacket"
MAP = f"{PKG}/MapUpdate"
SECURE = f"{PKG}/SecureFrame"
KEYX = f"{PKG}/KeyExchange"
ALL_TYPES = (HELLO, LSU, PROTOCOL, RECRUIT, MAP, SECURE, KEYX)


@cache
def definitions() -> dict[str, str]:
    """``{type name: .msg text}`` read from the package's ``msg/`` directory."""
    folder = resources.files("cryptoros.sim") / "msg"
    out = {}
    for name in ALL_TYPES:
        out[name] = (folder / (name.split("/")[1] + ".msg")).read_text()
    return out


@cache
def store() -> msgs.Typestore:
    return msgs.typestore(definitions())


@cache
def cls(typename: str) -> type:
    return msgs.msg_class(typename, store())


def Point(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> Any:
    return cls("geometry_msgs/Point")(x=float(x), y=float(y), z=float(z))


def make(typename: str, **fields: Any) -> Any:
    return cls(typename)(**fields)


def encode(msg: Any, typename: str) -> bytes:
    return msgs.serialize(msg, typename, store())


def decode(data: bytes, typename: str) -> Any:
    return msgs.deserialize(data, typename, store())


def md5sum(typename: str) -> str:
    return msgs.md5sum(typename, store())


def replace(msg: Any, **changes: Any) -> Any:
    return dataclasses.replace(msg, **changes)


@dataclasses.dataclass(eq=False, slots=True)
class Frame:
    """One radio transmission: who sent it (radio id), the type and the wire bytes."""

    sender: str
    typename: str
    data: bytes
    _decoded: Any = None
    _failed: bool = False
    cache: dict = dataclasses.field(default_factory=dict)  # per-frame results shared by receivers

    @property
    def size(self) -> int:
        return len(self.data)

    def decode(self) -> Any:
        """The parsed message, or None when the bytes do not parse (counted as garbage)."""
        if self._decoded is None and not self._failed:
            try:
                self._decoded = decode(self.data, self.typename)
            except Exception:
                self._failed = True
        return self._decoded


def frame(sender: str, msg: Any, typename: str) -> Frame:
    f = Frame(sender, typename, encode(msg, typename))
    f._decoded = msg
    return f
