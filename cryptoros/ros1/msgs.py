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


# ================================================================= fast paths
#
# rosbags' generic entry points cost several function calls, a size pass, a
# bytearray, a memoryview and a copy per message (about 2 us hot and 10 us cold for a
# std_msgs/String at 1 kHz). For a "flat" type, made only of fixed-size base fields,
# strings and sub-messages of the same kind (std_msgs/String, Header, Pose, Twist...),
# one generated function per direction does the whole job with a few precompiled
# ``struct.Struct`` calls. The wire bytes are those rosbags produces: the format
# characters are taken from rosbags' own packers, the field order from its field
# definitions, and the message objects are built with rosbags' classes (the tests
# compare both directions with rosbags and with genpy's bytes). Every other type
# (arrays, sequences, empty messages) goes through rosbags.

import struct as _struct  # noqa: E402
from collections.abc import Callable  # noqa: E402

from rosbags.serde import primitives as _primitives  # noqa: E402
from rosbags.typesys.store import normalize_fieldname as _normalize  # noqa: E402

_FORMATS: dict[str, str] = {
    name[len("unpack_") : -len("_le")]: getattr(_primitives, name).__self__.format.lstrip("<>=!@")
    for name in dir(_primitives)
    if name.startswith("unpack_") and name.endswith("_le")
}


class _NotFlat(LocalProtocolError):
    """A type is not flat: the generated struct serializer does not apply (caught here)."""


def _leaves(name: str, st: Typestore, expr: str, out: list, depth: int = 0) -> str:
    """Append ``('fixed', fmt, expr)`` / ``('string', expr)`` leaves of a flat type;
    return the constructor expression template (``{}`` per leaf, in order)."""
    if depth > 16:
        raise _NotFlat
    fields = st.fielddefs[name][1]
    if not fields or any(f == "structure_needs_at_least_one_member" for f, _ in fields):
        raise _NotFlat
    parts = []
    for fname, (kind, arg) in fields:
        attr = f"{expr}.{_normalize(fname)}"
        if kind == 1:  # BASE
            base, _limit = arg
            if base == "string":
                out.append(("string", attr))
            elif base in _FORMATS:
                out.append(("fixed", _FORMATS[base], attr))
            else:
                raise _NotFlat
            parts.append("{}")
        elif kind == 2:  # NAME
            parts.append(_leaves(arg, st, attr, out, depth + 1))
        else:
            raise _NotFlat
    return f"C[{name!r}](" + ", ".join(parts) + ")"


def _compile_flat(name: str, st: Typestore) -> tuple[Callable, Callable, Callable] | None:
    leaves: list = []
    try:
        ctor = _leaves(name, st, "m", leaves)
    except _NotFlat:
        return None
    classes: dict[str, type] = {}

    def collect(n: str) -> None:
        classes[n] = st.types[n]
        for _f, (kind, arg) in st.fielddefs[n][1]:
            if kind == 2:
                collect(arg)

    collect(name)
    ns: dict[str, Any] = {"C": classes, "RemoteProtocolError": RemoteProtocolError}
    # --- serializer: strings encoded first (their lengths make the frame length)
    strs = [i for i, leaf in enumerate(leaves) if leaf[0] == "string"]
    ser = ["def frame(m):"]
    for i in strs:
        ser.append(f"    s{i} = {leaves[i][1]}.encode()")
    fixed_size = 0
    chunks: list[str] = []  # expressions joined in order
    fmt, args = "<I", ["__TOTAL__"]
    nstruct = 0
    for i, leaf in enumerate(leaves):
        if leaf[0] == "fixed":
            fmt += leaf[1]
            args.append(leaf[2])
        else:
            fmt += "I"
            args.append(f"len(s{i})")
            ns[f"S{nstruct}"] = _struct.Struct(fmt)
            chunks.append(f"S{nstruct}.pack({', '.join(args)})")
            chunks.append(f"s{i}")
            fixed_size += _struct.calcsize(fmt)
            nstruct += 1
            fmt, args = "<", []
    if args:
        ns[f"S{nstruct}"] = _struct.Struct(fmt)
        chunks.append(f"S{nstruct}.pack({', '.join(args)})")
        fixed_size += _struct.calcsize(fmt)
    body_fixed = fixed_size - 4
    total = " + ".join([str(body_fixed), *(f"len(s{i})" for i in strs)])
    chunks[0] = chunks[0].replace("__TOTAL__", total)
    if len(chunks) == 1:
        ser.append(f"    return {chunks[0]}")
    elif len(chunks) == 2:
        ser.append(f"    return {chunks[0]} + {chunks[1]}")
    else:
        ser.append(f"    return b''.join(({', '.join(chunks)},))")
    # --- deserializer: one unpack per run of fixed fields (+ the next string length)
    des = ["def des(raw):", "    try:", "        n = len(raw)", "        p = 0"]
    fmt, names = "<", []
    nstruct = 0
    values: list[str] = []

    def emit_unpack() -> None:
        nonlocal fmt, names, nstruct
        key = f"D{nstruct}"
        ns[key] = _struct.Struct(fmt)
        lhs = ", ".join(names) + ("," if len(names) == 1 else "")
        des.append(f"        {lhs} = {key}.unpack_from(raw, p)")
        des.append(f"        p += {_struct.calcsize(fmt)}")
        nstruct += 1
        fmt, names = "<", []

    for i, leaf in enumerate(leaves):
        if leaf[0] == "fixed":
            fmt += leaf[1]
            names.append(f"v{i}")
        else:
            fmt += "I"
            names.append(f"l{i}")
            emit_unpack()
            des.append(f"        e = p + l{i}")
            des.append("        if e > n:")
            des.append(f"            raise ValueError(f'string length {{l{i}}} exceeds the message')")
            des.append(f"        v{i} = str(raw[p:e], 'utf-8')")
            des.append("        p = e")
        values.append(f"v{i}")
    if names:
        emit_unpack()
    des.append("        if p != n:")
    des.append("            raise ValueError(f'{n - p} bytes left over')")
    des.append(f"        return {ctor.format(*values)}")
    des.append("    except (_struct.error, UnicodeDecodeError, ValueError) as err:")
    des.append(f"        raise RemoteProtocolError(f'malformed {ros1_name(name)} message: {{err!r}}') from err")
    ns["_struct"] = _struct
    exec(compile("\n".join(ser) + "\n\n" + "\n".join(des) + "\n", f"<cryptoros flat {name}>", "exec"), ns)  # noqa: S102
    frame_fn = ns["frame"]

    def body(m: Any) -> bytes:
        return frame_fn(m)[4:]

    return frame_fn, body, ns["des"]


_flat: dict[int, tuple[Typestore, dict[str, tuple[Callable, Callable, Callable] | None]]] = {}


def _flat_of(name: str, st: Typestore) -> tuple[Callable, Callable, Callable] | None:
    entry = _flat.get(id(st))
    if entry is None or entry[0] is not st:
        with _lock:
            entry = _flat[id(st)] = (st, {})
    cache = entry[1]
    if name not in cache:
        cache[name] = _compile_flat(name, st)
    return cache[name]


def is_flat(typename: str, store: Typestore | None = None) -> bool:
    """Whether ``typename`` gets the generated struct fast path."""
    st = _store(store)
    return _flat_of(_check(typename, st), st) is not None


def frame_serializer(typename: str, store: Typestore | None = None) -> Callable[[Any], bytes]:
    """A function ``msg -> u32 length + ROS 1 bytes`` (a TCPROS frame). Errors on a
    bad message are whatever the packer raises (wrap them). Fast for flat types."""
    st = _store(store)
    name = _check(typename, st)
    flat = _flat_of(name, st)
    if flat is not None:
        return flat[0]
    st.get_msgdef(name)
    pack = _struct.Struct("<I").pack

    def frame(m: Any) -> bytes:
        data = st.serialize_ros1(m, name)
        return pack(len(data)) + bytes(data)

    return frame


def deserializer(typename: str, store: Typestore | None = None) -> Callable[[Any], Any]:
    """A function ``bytes -> message`` that raises :class:`RemoteProtocolError` on
    malformed bytes (every byte must be consumed), like :func:`deserialize`."""
    st = _store(store)
    name = _check(typename, st)
    flat = _flat_of(name, st)
    if flat is not None:
        return flat[2]
    st.get_msgdef(name)
    des = st.deserialize_ros1

    def slow(data: Any) -> Any:
        try:
            return des(data, name)
        except Exception as err:
            raise RemoteProtocolError(f"malformed {ros1_name(name)} message: {err!r}") from err

    return slow
