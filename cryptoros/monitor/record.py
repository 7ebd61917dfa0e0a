"""``cryptoros monitor record``: a recording the monitor can learn from.

Subscribes to the named topics with their real types (a registry may grant exact types
only; a type this node does not know is taken as any type, ``*``, as ``rosbag record``
does) and writes a ROS 1 bag
with one connection per (topic, publisher): the publisher's ``callerid`` is what
labels an attacker, and the arrival time stored with each message is what the rate
features read. Runs as a normal node behind the host's interceptor and needs its
subscribe grants.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cryptoros.errors import CryptorosError, RemoteProtocolError
from cryptoros.ros1 import msgs
from cryptoros.ros1.node import Node, call


async def record(master_uri: str, topics: list[str], out: Path, *, seconds: float, name: str = "/monitor_recorder",
                 host: str = "127.0.0.1", timeout: float = 10.0,
                 on_ready: Callable[[], None] = lambda: None, stop: asyncio.Event | None = None) -> dict[str, Any]:
    """Record ``topics`` for ``seconds`` (counted once every subscription is registered:
    then ``on_ready`` is called) or until ``stop`` is set; returns messages per (topic,
    publisher). The bag is closed either way."""
    from rosbags.rosbag1 import Writer

    types = dict(await call(master_uri, "getTopicTypes", name, timeout=timeout))
    missing = [t for t in topics if t not in types]
    if missing:
        raise RemoteProtocolError(f"the master knows no type for {', '.join(missing)} (nothing published yet?)")
    out.unlink(missing_ok=True)
    writer = Writer(out)
    writer.open()
    counts: dict[str, int] = {}
    connections: dict[tuple[str, str], Any] = {}
    closed = False  # the bag is closed first when recording stops: what comes after is not written
    node = Node(name, master_uri, host=host, api_timeout=timeout)
    try:
        await node.start()
        for topic in topics:
            typename = types[topic]
            known = _known(typename, node.store)

            def on_message(data: bytes, header: dict[str, str] | None, topic: str = topic,
                           typename: str = typename, known: bool = known) -> None:
                if closed:
                    return
                header = header or {}
                publisher = header.get("callerid", "?")
                conn = connections.get((topic, publisher))
                if conn is None:
                    if known:
                        conn = writer.add_connection(topic, msgs.store_name(typename), typestore=node.store,
                                                     callerid=publisher)
                    else:  # a type of its own (the demo's team packets): its definition as the publisher sent it
                        conn = writer.add_connection(topic, msgs.store_name(typename),
                                                     msgdef=header.get("message_definition", ""),
                                                     md5sum=header.get("md5sum", "*"), callerid=publisher)
                    connections[(topic, publisher)] = conn
                writer.write(conn, time.time_ns(), bytes(data))
                key = f"{publisher} on {topic}"
                counts[key] = counts.get(key, 0) + 1

            # a type this node does not know is taken as any type ('*'), as rosbag record does
            await node.subscribe(topic, typename if known else "*", on_message, raw=True, with_publisher=True)
        on_ready()
        with contextlib.suppress(asyncio.TimeoutError, TimeoutError):
            await asyncio.wait_for((stop or asyncio.Event()).wait(), seconds)
    finally:
        # the bag first: a node slow to unregister (a master going away, a loaded machine)
        # must not keep it from being complete when whoever stopped us loses patience
        closed = True
        writer.close()
        with contextlib.suppress(CryptorosError, OSError, asyncio.TimeoutError):
            await asyncio.wait_for(node.close(), timeout)
    return counts


def _known(typename: str, store: Any) -> bool:
    try:
        msgs.md5sum(typename, store)
    except CryptorosError:
        return False
    return True


__all__ = ["record"]
