"""What one ROS 2 stream between two interceptors carries: the preamble's ``target``.

A stream with purpose ``ros2`` carries one topic (serialized messages, one way) or
one service (requests one way, responses back). Its preamble target is a small JSON
object, validated strictly on both sides::

    {"kind": "topic", "name": "/chatter", "type": "std_msgs/msg/String",
     "node": "/talker", "qos": {"reliability": "reliable", "durability": "volatile", "depth": 10}}

``node`` is the publishing (or serving) node on the sender's domain: the receiver
checks the sender's grants for exactly that node. Pure code, no I/O.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, Final

from cryptoros.errors import RegistryError, RemoteProtocolError
from cryptoros.names import validate_graph_name, validate_type

KINDS: Final = ("topic", "service")
RELIABILITY: Final = ("reliable", "best_effort")
DURABILITY: Final = ("volatile", "transient_local")
MAX_DEPTH: Final = 1000


@dataclass(frozen=True, kw_only=True, slots=True)
class QoS:
    reliability: str = "reliable"
    durability: str = "volatile"
    depth: int = 10

    def __post_init__(self) -> None:
        if self.reliability not in RELIABILITY or self.durability not in DURABILITY:
            raise RemoteProtocolError(f"bad QoS {self.reliability!r}/{self.durability!r}")
        if not isinstance(self.depth, int) or isinstance(self.depth, bool) or not 1 <= self.depth <= MAX_DEPTH:
            raise RemoteProtocolError(f"QoS depth must be 1..{MAX_DEPTH}, got {self.depth!r}")

    def to_dict(self) -> dict[str, Any]:
        return {"reliability": self.reliability, "durability": self.durability, "depth": self.depth}


def receiver_qos(asked: QoS, *, depth: int, keep_for_late_joiners: bool) -> QoS:
    """What a receiving robot republishes with: the sender's QoS is a request, its depth
    capped at the receiver's ``depth``, ``transient_local`` only where the receiver
    keeps samples for late joiners on that topic."""
    durability = asked.durability if keep_for_late_joiners else "volatile"
    return QoS(reliability=asked.reliability, durability=durability, depth=min(asked.depth, depth))


@dataclass(frozen=True, kw_only=True, slots=True)
class StreamTarget:
    kind: str
    name: str
    type: str
    node: str
    qos: QoS = QoS()

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise RemoteProtocolError(f"unknown ros2 stream kind {self.kind!r}")
        try:
            validate_graph_name(self.name)
            validate_graph_name(self.node, "node name")
            validate_type(self.type)
        except RegistryError as exc:
            raise RemoteProtocolError(str(exc)) from None
        wanted = "/msg/" if self.kind == "topic" else "/srv/"
        if wanted not in self.type:
            raise RemoteProtocolError(f"a {self.kind} needs a {wanted.strip('/')} type, got {self.type}")

    @property
    def action(self) -> str:
        """What the sender must be granted for ``node``."""
        return "publish" if self.kind == "topic" else "serve"

    @property
    def peer_action(self) -> str:
        """What the receiving manager must be granted (for some node of its own)."""
        return "subscribe" if self.kind == "topic" else "call"

    def encode(self) -> str:
        body: dict[str, Any] = {"kind": self.kind, "name": self.name, "type": self.type, "node": self.node}
        if self.kind == "topic":
            body["qos"] = self.qos.to_dict()
        return json.dumps(body, separators=(",", ":"))

    @classmethod
    def decode(cls, text: str) -> StreamTarget:
        try:
            obj = json.loads(text)
        except ValueError as exc:
            raise RemoteProtocolError(f"ros2 target is not JSON: {exc}") from None
        if not isinstance(obj, dict):
            raise RemoteProtocolError("ros2 target is not a JSON object")
        allowed = {"kind", "name", "type", "node"} | ({"qos"} if obj.get("kind") == "topic" else set())
        if set(obj) - allowed or not {"kind", "name", "type", "node"} <= set(obj):
            raise RemoteProtocolError(f"ros2 target fields {sorted(obj)} are not {sorted(allowed)}")
        if not all(isinstance(obj[k], str) for k in ("kind", "name", "type", "node")):
            raise RemoteProtocolError("ros2 target fields must be strings")
        qos = QoS()
        if "qos" in obj:
            q = obj["qos"]
            if not isinstance(q, dict) or set(q) != {"reliability", "durability", "depth"}:
                raise RemoteProtocolError("ros2 target qos must hold reliability, durability and depth")
            qos = QoS(reliability=q["reliability"], durability=q["durability"], depth=q["depth"])
        return cls(kind=obj["kind"], name=obj["name"], type=obj["type"], node=obj["node"], qos=qos)


__all__ = ["DURABILITY", "KINDS", "QoS", "RELIABILITY", "StreamTarget", "receiver_qos"]
