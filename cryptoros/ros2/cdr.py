"""Structural checks of serialized ROS 2 messages (CDR, XCDR1), sans-IO.

Before a receiving interceptor republishes a sample on its robot's domain, the
sample must be a well-formed serialization of the granted type: an encapsulation
header for plain CDR (big or little endian), every field where CDR puts it (aligned
relative to the data after the header), every string and sequence length inside the
payload, strings NUL-terminated UTF-8 within their bounds, sequences within theirs,
and nothing after the last field but alignment padding (at most 3 bytes). An empty or
truncated sample, one of another encapsulation, lengths past the end, or trailing
garbage is refused (:class:`CdrError`): a reader that meets such a sample from a
reliable writer can stop receiving from it for good.

This is a walk over lengths and offsets compiled once per type from the message
definitions rosbags ships (:func:`checker_for`); no message object is built.
"""

from __future__ import annotations

import functools
import re
import struct
from collections.abc import Callable

from cryptoros.errors import RemoteProtocolError

#: Encapsulation identifiers of plain CDR (XCDR1): big and little endian.
_ENCAPSULATIONS = {b"\x00\x00": ">", b"\x00\x01": "<"}
_PRIMITIVE_SIZES = {
    "bool": 1, "byte": 1, "char": 1, "int8": 1, "uint8": 1, "octet": 1,
    "int16": 2, "uint16": 2, "int32": 4, "uint32": 4, "float32": 4,
    "int64": 8, "uint64": 8, "float64": 8,
}


class CdrError(RemoteProtocolError):
    """A sample that is not a well-formed serialization of its type."""


# A step walks one field: (data, offset, u32 unpacker) -> new offset; raises CdrError.
Step = Callable[[bytes, int, Callable], int]


def _align(offset: int, size: int) -> int:
    return (offset + size - 1) & ~(size - 1) if size > 1 else offset


def _primitive(size: int, count: int = 1) -> Step:
    def step(data: memoryview, off: int, u32: Callable) -> int:
        off = _align(off, size) + size * count
        if off > len(data):
            raise CdrError("sample ends inside a field")
        return off

    return step


def _string(bound: int) -> Step:
    def step(data: memoryview, off: int, u32: Callable) -> int:
        off = _align(off, 4)
        if off + 4 > len(data):
            raise CdrError("sample ends inside a string length")
        (length,) = u32(data, off)
        off += 4
        end = off + length
        if length == 0 or end > len(data):
            raise CdrError(f"string length {length} outside the sample")
        if data[end - 1] != 0:
            raise CdrError("string without its terminating NUL")
        if bound and length - 1 > bound:
            raise CdrError(f"string of {length - 1} bytes over its bound {bound}")
        try:
            bytes(data[off : end - 1]).decode("utf-8")
        except UnicodeDecodeError as exc:
            raise CdrError("string is not UTF-8") from exc
        return end

    return step


def _repeat(steps: list[Step], count: int) -> Step:
    def step(data: memoryview, off: int, u32: Callable) -> int:
        for _ in range(count):
            for s in steps:
                off = s(data, off, u32)
        return off

    return step


def _sequence(element: tuple, bound: int, typestore, budget: list[int] | None) -> Step:
    kind, detail = element
    if kind == 1 and detail[0] in _PRIMITIVE_SIZES:
        size = _PRIMITIVE_SIZES[detail[0]]

        def step(data: memoryview, off: int, u32: Callable) -> int:
            off = _align(off, 4)
            if off + 4 > len(data):
                raise CdrError("sample ends inside a sequence length")
            (count,) = u32(data, off)
            if bound and count > bound:
                raise CdrError(f"sequence of {count} over its bound {bound}")
            off = _align(off + 4, size) + size * count if count else off + 4
            if off > len(data):
                raise CdrError(f"sequence of {count} elements outside the sample")
            return off

        return step
    inner = _steps_of_field(element, typestore, budget)

    def step(data: memoryview, off: int, u32: Callable) -> int:
        off = _align(off, 4)
        if off + 4 > len(data):
            raise CdrError("sample ends inside a sequence length")
        (count,) = u32(data, off)
        off += 4
        if (bound and count > bound) or count > len(data) - off:  # every element takes a byte at least
            raise CdrError(f"sequence of {count} elements outside the sample or its bound")
        if budget is not None:  # strings and messages: an object each where the message is built
            budget[0] -= count
            if budget[0] < 0:
                raise CdrError(f"more than {MAX_SERVICE_ELEMENTS} strings and messages in sequences")
        for _ in range(count):
            for s in inner:
                off = s(data, off, u32)
        return off

    return step


def _steps_of_field(field: tuple, typestore, budget: list[int] | None = None) -> list[Step]:
    kind, detail = field
    if kind == 1:  # BASE: a primitive or a (bounded) string
        name, bound = detail
        if name in _PRIMITIVE_SIZES:
            return [_primitive(_PRIMITIVE_SIZES[name])]
        if name == "string":
            return [_string(bound)]
        raise CdrError(f"cannot check fields of type {name}")
    if kind == 2:  # NAME: a nested message
        return _steps_of_type(detail, typestore, budget)
    if kind == 3:  # ARRAY: fixed count
        element, count = detail
        ekind, edetail = element
        if ekind == 1 and edetail[0] in _PRIMITIVE_SIZES:
            return [_primitive(_PRIMITIVE_SIZES[edetail[0]], count)]
        return [_repeat(_steps_of_field(element, typestore, budget), count)]
    if kind == 4:  # SEQUENCE: u32 count
        element, bound = detail
        return [_sequence(element, bound, typestore, budget)]
    raise CdrError(f"unknown field kind {kind}")


def _steps_of_type(type_name: str, typestore, budget: list[int] | None = None) -> list[Step]:
    try:
        _consts, fields = typestore.fielddefs[type_name]
    except KeyError:
        raise CdrError(f"no definition of {type_name}") from None
    steps: list[Step] = []
    for _name, field in fields:
        steps += _steps_of_field(field, typestore, budget)
    return steps


#: strings and messages in the sequences of one service request or response, all
#: together. A service's body is built into a message (rclpy's ``deserialize_message``, in
#: the bridge and in the server or client): each such element an object of a hundred bytes
#: or more, from a few bytes of CDR. An insider's answer of 12 MiB claiming that many
#: empty elements took the bridge to 2.5 GB before it failed (a ROS 2 audit). Sequences
#: of numbers are one array each and do not count.
MAX_SERVICE_ELEMENTS = 65_536


@functools.lru_cache(maxsize=256)
def service_checkers(type_name: str, definition: str) -> tuple[Callable, Callable]:
    """Checks of ``pkg/srv/Name`` requests and responses, from its ``.srv`` text (the
    request's fields, ``---``, the response's), each bounded by
    :data:`MAX_SERVICE_ELEMENTS`; CdrError for a definition it cannot read or a field
    type it cannot check (refuse the service: fail closed)."""
    from rosbags.typesys import get_types_from_msg

    parts = re.split(r"^---[ \t]*$", definition, maxsplit=1, flags=re.MULTILINE)
    if len(parts) != 2 or type_name.count("/") != 2 or type_name.split("/")[1] != "srv":
        raise CdrError(f"{type_name}: not a service definition (request, ---, response)")
    typestore = _typestore()
    # as rosbags names message types (pkg/msg/Name): the definition's relative field types
    # (TransitionDescription) are then the package's messages, as in ROS
    pkg, _srv, base = type_name.split("/")
    names = (f"{pkg}/msg/{base}_Request", f"{pkg}/msg/{base}_Response")
    try:
        for name, text in zip(names, parts):
            if name not in typestore.fielddefs:
                typestore.register(get_types_from_msg(text, name))
    except Exception as exc:  # rosbags raises several kinds on a definition it cannot read
        raise CdrError(f"{type_name}: its definition cannot be read ({exc})") from None
    return tuple(checker_for(name, max_elements=MAX_SERVICE_ELEMENTS) for name in names)  # type: ignore[return-value]


@functools.lru_cache(maxsize=1)
def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


@functools.lru_cache(maxsize=512)
def checker_for(type_name: str, *,
                max_elements: int | None = None) -> Callable[[bytes | bytearray | memoryview], None]:
    """A check of serialized ``type_name`` samples (``pkg/msg/Name``); raises
    CdrError for a type it cannot check (refuse such streams: fail closed).
    ``max_elements``: at most this many strings and messages in its sequences, all
    together (what a receiver that builds the message makes an object of each)."""
    budget = None if max_elements is None else [max_elements]
    steps = _steps_of_type(type_name, _typestore(), budget)
    unpackers = {">": struct.Struct(">I").unpack_from, "<": struct.Struct("<I").unpack_from}

    def check(sample: bytes | bytearray | memoryview) -> None:
        if budget is not None:
            budget[0] = max_elements
        view = memoryview(sample)
        if len(view) < 4:
            raise CdrError(f"sample of {len(view)} bytes has no encapsulation header")
        order = _ENCAPSULATIONS.get(bytes(view[:2]))
        if order is None:
            raise CdrError(f"encapsulation {bytes(view[:2]).hex()} is not plain CDR")
        data = view[4:]
        u32 = unpackers[order]
        off = 0
        for step in steps:
            off = step(data, off, u32)
        if len(data) - off > 3:
            raise CdrError(f"{len(data) - off} bytes after the last field")

    return check


@functools.lru_cache(maxsize=512)
def deserializer(type_name: str) -> Callable[[bytes | bytearray | memoryview], object]:
    """A decoder of ``type_name`` samples (``pkg/msg/Name``) into rosbags message
    objects; malformed bytes raise :class:`CdrError`."""
    typestore = _typestore()
    if type_name not in typestore.fielddefs:
        raise CdrError(f"no definition of {type_name}")
    decode = typestore.deserialize_cdr

    def run(sample: bytes | bytearray | memoryview) -> object:
        try:
            return decode(bytes(sample), type_name)
        except Exception as err:  # rosbags raises several kinds on short or bad bytes
            raise CdrError(f"malformed {type_name} sample: {err!r}") from err

    return run


__all__ = ["CdrError", "checker_for", "deserializer"]
