"""ROS 1 message types and serialization, through ``rosbags``.

A :class:`Typestore` is explicit (never a global registry): :func:`typestore` returns
the Noetic store, optionally extended with custom ``.msg`` definitions registered at
run time, cached per distinct set of extra definitions.

Type names are accepted in either spelling, ``std_msgs/String`` (ROS 1, what goes on
the wire) or ``std_msgs/msg/String`` (rosbags). md5sums and message definitions are
the ones ROS 1 computes, so a real ``rospy``/``roscpp`` peer accepts our headers.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from typing import Any

from rosbags.typesys import Stores, TypesysError, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from cryptoros.errors import LocalProtocolError, RemoteProtocolError

__all__ = [
    "Typestore",
    "typestore",
    "serialize",
    "deserialize",
    "md5sum",
    "message_definition",
    "ros1_name",
    "store_name",
    "msg_class",
    "warm",
    "UnknownTypeError",
    "ServiceType",
    "service_type",
    "BUILTIN_SRVS",
]


class UnknownTypeError(LocalProtocolError):
    """A message type is not in the typestore (our configuration, not the peer)."""


_lock = threading.Lock()
_stores: dict[tuple[tuple[str, str], ...], Typestore] = {}


def store_name(typename: str) -> str:
    """``std_msgs/String`` or ``std_msgs/msg/String`` -> ``std_msgs/msg/String``
    (``pkg/srv/Name`` stays a service name)."""
    parts = typename.strip("/").split("/")
    if len(parts) == 2 and all(parts):
        return f"{parts[0]}/msg/{parts[1]}"
    if len(parts) == 3 and parts[1] in ("msg", "srv", "action") and parts[0] and parts[2]:
        return "/".join(parts)
    raise UnknownTypeError(f"not a ROS message type name: {typename!r}")


def ros1_name(typename: str) -> str:
    """``std_msgs/msg/String`` -> ``std_msgs/String`` (unchanged if already ROS 1 style)."""
    parts = store_name(typename).split("/")
    return f"{parts[0]}/{parts[2]}"


# Services ROS nodes serve out of the box (rospy: ~get_loggers, ~set_logger_level),
# registered in every store so a client can call them without custom definitions.
BUILTIN_SRVS: dict[str, str] = {
    "roscpp/msg/Logger": "string name\nstring level\n",
    "roscpp/srv/Empty": "---\n",
    "roscpp/srv/GetLoggers": "---\nLogger[] loggers\n",
    "roscpp/srv/SetLoggerLevel": "string logger\nstring level\n---\n",
    "std_srvs/srv/Empty": "---\n",
    "std_srvs/srv/Trigger": "---\nbool success\nstring message\n",
    "std_srvs/srv/SetBool": "bool data\n---\nbool success\nstring message\n",
}


def _split_srv(text: str) -> tuple[str, str]:
    lines = text.splitlines()
    marks = [i for i, line in enumerate(lines) if line.strip() == "---"]
    if len(marks) != 1:
        raise LocalProtocolError("a .srv definition has exactly one '---' line")
    i = marks[0]
    return "\n".join(lines[:i]) + "\n", "\n".join(lines[i + 1 :]) + "\n"


def typestore(extra: Mapping[str, str] | None = None) -> Typestore:
    """The ROS 1 Noetic typestore, plus custom ``.msg`` texts keyed by type name.

    Cached per distinct ``extra``: calling twice with equal mappings returns the same
    object. A custom type whose name already exists with another definition raises
    :class:`LocalProtocolError`.
    """
    key = tuple(sorted({**BUILTIN_SRVS, **{store_name(k): v for k, v in (extra or {}).items()}}.items()))
    with _lock:
        store = _stores.get(key)
        if store is not None:
            return store
        store = get_typestore(Stores.ROS1_NOETIC)
        if key:
            types: dict[str, Any] = {}
            try:
                for name, text in key:
                    if name.split("/")[1] == "srv":
                        req, resp = _split_srv(text)
                        pkg, _, base = name.split("/")
                        types.update(get_types_from_msg(req, f"{pkg}/msg/{base}_Request"))
                        types.update(get_types_from_msg(resp, f"{pkg}/msg/{base}_Response"))
                    else:
                        types.update(get_types_from_msg(text, name))
                store.register(types)
            except TypesysError as err:
                raise LocalProtocolError(f"cannot register custom message types: {err}") from err
            except Exception as err:  # the msg parser raises plain errors on bad syntax
                raise LocalProtocolError(f"invalid .msg definition: {err}") from err
        _stores[key] = store
        return store


def _store(store: Typestore | None) -> Typestore:
    return typestore() if store is None else store


def _check(typename: str, store: Typestore) -> str:
    name = store_name(typename)
    if name not in store.fielddefs:
        raise UnknownTypeError(f"unknown message type {ros1_name(name)!r}")
    return name


def warm(typename: str, store: Typestore | None = None) -> None:
    """Generate the (de)serializer code of a type now, not on its first message."""
    st = _store(store)
    st.get_msgdef(_check(typename, st))


def msg_class(typename: str, store: Typestore | None = None) -> type:
    """The Python class of a message type (build messages with keyword arguments)."""
    st = _store(store)
    return st.types[_check(typename, st)]


def serialize(msg: object, typename: str, store: Typestore | None = None) -> bytes:
    """ROS 1 wire bytes of ``msg`` (no length prefix)."""
    st = _store(store)
    name = _check(typename, st)
    try:
        return bytes(st.serialize_ros1(msg, name))
    except Exception as err:
        raise LocalProtocolError(f"cannot serialize {ros1_name(name)}: {err!r}") from err


def deserialize(data: bytes | bytearray | memoryview, typename: str, store: Typestore | None = None) -> Any:
    """Parse ROS 1 wire bytes into a message object; every byte must be consumed.

    Malformed bytes (the peer's) raise :class:`RemoteProtocolError`.
    """
    st = _store(store)
    name = _check(typename, st)
    try:
        return st.deserialize_ros1(data, name)
    except Exception as err:
        raise RemoteProtocolError(f"malformed {ros1_name(name)} message: {err!r}") from err


_defs: dict[int, tuple[Typestore, dict[str, tuple[str, str]]]] = {}


def _generated(typename: str, store: Typestore | None) -> tuple[str, str]:
    st = _store(store)
    name = _check(typename, st)
    entry = _defs.get(id(st))
    if entry is None or entry[0] is not st:
        entry = _defs[id(st)] = (st, {})
    cache = entry[1]
    found = cache.get(name)
    if found is None:
        found = cache[name] = st.generate_msgdef(name, ros_version=1)
    return found


def md5sum(typename: str, store: Typestore | None = None) -> str:
    """The md5sum ROS 1 puts in the connection header for this type."""
    return _generated(typename, store)[1]


def message_definition(typename: str, store: Typestore | None = None) -> str:
    """The full message definition text (with ``MSG:`` sub-definitions) for the header."""
    return _generated(typename, store)[0]


def _md5_text(name: str, st: Typestore) -> str:
    """The text genmsg hashes for a message (sub-messages replaced by their md5)."""
    typemap = {"builtin_interfaces/msg/Time": "time", "builtin_interfaces/msg/Duration": "duration"}
    consts, fields = st.fielddefs[name]
    lines = [f"{typ} {cname}={value}" for cname, typ, value in consts]
    for fname, desc in fields:
        if fname == "structure_needs_at_least_one_member":
            continue
        kind, arg = desc
        if kind == 1:  # BASE
            base, limit = arg
            lines.append(f"{f'string<={limit}' if base == 'string' and limit else base} {fname}")
        elif kind == 2:  # NAME
            lines.append(f"{typemap[arg]} {fname}" if arg in typemap else f"{md5sum(arg, st)} {fname}")
        else:  # ARRAY (3) / SEQUENCE (4)
            (subkind, sub), num = arg
            count = "" if num == 0 else str(num) if kind == 3 else f"<={num}"
            if subkind == 1:
                base = f"string<={sub[1]}" if sub[0] == "string" and sub[1] else sub[0]
                lines.append(f"{base}[{count}] {fname}")
            elif sub in typemap:
                lines.append(f"{typemap[sub]}[{count}] {fname}")
            else:
                lines.append(f"{md5sum(sub, st)} {fname}")
    return "\n".join(lines)


class ServiceType:
    """A ROS 1 service type: request and response message types and the md5sum."""

    __slots__ = ("name", "request", "response", "md5sum", "store")

    def __init__(self, name: str, request: str, response: str, md5: str, store: Typestore) -> None:
        self.name, self.request, self.response, self.md5sum, self.store = name, request, response, md5, store

    def request_class(self) -> type:
        return msg_class(self.request, self.store)

    def response_class(self) -> type:
        return msg_class(self.response, self.store)

    def __repr__(self) -> str:
        return f"ServiceType({self.name!r}, md5sum={self.md5sum!r})"


def service_type(srvname: str, store: Typestore | None = None) -> ServiceType:
    """``roscpp/GetLoggers`` or ``roscpp/srv/GetLoggers`` -> its :class:`ServiceType`
    (md5sum as genmsg computes it: md5 of request text + response text)."""
    import hashlib

    st = _store(store)
    parts = srvname.strip("/").split("/")
    if len(parts) == 3 and parts[1] == "srv":
        parts = [parts[0], parts[2]]
    if len(parts) != 2 or not all(parts):
        raise UnknownTypeError(f"not a ROS service type name: {srvname!r}")
    pkg, base = parts
    req, resp = f"{pkg}/msg/{base}_Request", f"{pkg}/msg/{base}_Response"
    if req not in st.fielddefs or resp not in st.fielddefs:
        raise UnknownTypeError(f"unknown service type {pkg}/{base!r}")
    text = _md5_text(req, st) + _md5_text(resp, st)
    return ServiceType(f"{pkg}/{base}", req, resp, hashlib.md5(text.encode()).hexdigest(), st)  # noqa: S324
