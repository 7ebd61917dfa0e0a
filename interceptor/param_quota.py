"""What each manager has stored in rosmaster's parameter tree through setParam (master
role), sans-IO.

Any node of a manager may write its own private namespace (``/<node>/...``) without a
parameter grant, and each call may carry up to ``max_xmlrpc_body``: without a bound,
one insider grows rosmaster's parameter tree until it runs out of memory. This table
mirrors the tree as rosmaster keeps it (``rosmaster/paramserver.py`` upstream), for
what was written through this interceptor: setting a key replaces everything at and
below it, creates the namespaces on the way (a value there becomes a namespace), and a
dict value is a namespace of its members; deleting a key removes its subtree, whoever
wrote it, and leaves the namespaces above it (rosmaster keeps them, empty). Each key
of the tree (a value or a namespace) is charged to the manager whose write made it:
one key, and the bytes of its name and value.

A write that would take its manager past ``max_keys`` or ``max_bytes`` is refused
(``param_quota``) and changes nothing; a write that does not grow what the manager
holds is always allowed. The table is bounded by the quotas: every key in it was
written within one.

Exact for what passes here. Writes that reach rosmaster another way (a process on
the master's host talking to rosmaster directly) are not seen: a key such a write
replaced stays charged until it is deleted through here, and a namespace it made is
charged to the first manager that writes below it. A write is charged when it is
sent: one whose request got no answer stays charged (rosmaster may have applied it).
The table keeps the values too (they are what it charges): a restarted rosmaster,
which has lost every parameter, gets back what was set through here and not deleted
(:meth:`items`, replayed by the master role). A restarted interceptor starts from
nothing (what was written before is neither charged nor replayed).
"""

from __future__ import annotations

from typing import Any
from xmlrpc.client import DateTime

from cryptoros.errors import PolicyDenied

#: bytes charged for a number, a boolean, a date or nil, and for each list or dict
SCALAR_BYTES = 8


class _Node:
    __slots__ = ("children", "data", "owner", "size", "value")

    def __init__(self, owner: str, size: int, value: bool, data: Any = None) -> None:
        self.children: dict[str, _Node] = {}
        self.owner, self.size, self.value = owner, size, value
        self.data = data  # the value itself (a value node)


def _parts(key: str) -> tuple[str, ...]:
    return tuple(p for p in key.split("/") if p)


def value_bytes(value: Any) -> int:
    """The bytes a parameter value is charged (strings as UTF-8)."""
    if isinstance(value, str):
        return len(value.encode("utf-8", "surrogatepass"))
    if isinstance(value, (bytes, bytearray)):
        return len(value)
    if isinstance(value, DateTime):  # fixed-size as parsed; charged for its text all the same
        return len(value.value)
    if isinstance(value, (list, tuple)):
        return SCALAR_BYTES + sum(value_bytes(v) for v in value)
    if isinstance(value, dict):
        return SCALAR_BYTES + sum(len(str(k)) + value_bytes(v) for k, v in value.items())
    return SCALAR_BYTES


def _measure(name: str, value: Any) -> tuple[int, int]:
    """(keys, bytes) of ``value`` set under ``name``: a dict is a namespace (one key,
    its name) holding its members; anything else is one key, its name and value."""
    if isinstance(value, dict):
        keys, size = 1, len(name)
        for member, inner in value.items():
            k, b = _measure(str(member), inner)
            keys, size = keys + k, size + b
        return keys, size
    return 1, len(name) + value_bytes(value)


def _build(name: str, value: Any, owner: str) -> _Node:
    if not isinstance(value, dict):
        return _Node(owner, len(name) + value_bytes(value), True, value)
    node = _Node(owner, len(name), False)
    for member, inner in value.items():
        node.children[str(member)] = _build(str(member), inner, owner)
    return node


def _subtree(node: _Node):
    stack = [node]
    while stack:
        node = stack.pop()
        yield node
        stack.extend(node.children.values())


class ParamQuota:
    def __init__(self, max_keys: int, max_bytes: int) -> None:
        self.max_keys, self.max_bytes = max_keys, max_bytes
        self._root = _Node("", 0, False)  # rosmaster's "/", charged to nobody
        #: manager -> [keys, bytes] it holds now
        self._usage: dict[str, list[int]] = {}

    def usage(self, manager: str) -> tuple[int, int]:
        keys, size = self._usage.get(manager, (0, 0))
        return keys, size

    def all_usage(self) -> dict[str, tuple[int, int]]:
        return {manager: (keys, size) for manager, (keys, size) in self._usage.items()}

    def set(self, manager: str, key: str, value: Any) -> None:
        """Charge ``manager`` for rosmaster's ``setParam(key, value)`` (``key`` resolved);
        PolicyDenied (and nothing changed) past its quota."""
        parts = _parts(key)
        if not parts and not isinstance(value, dict):
            return  # rosmaster refuses a root that is not a dict: nothing changes
        keys, size = self.usage(manager)
        after_keys, after_bytes = keys, size
        # the namespaces on the way: made where missing, or where a value was
        node: _Node | None = self._root
        for part in parts[:-1]:
            node = node.children.get(part) if node is not None else None
            if node is None or node.value:
                after_keys, after_bytes = after_keys + 1, after_bytes + len(part)
            if node is not None and node.value and node.owner == manager:
                after_keys, after_bytes = after_keys - 1, after_bytes - node.size
            if node is not None and node.value:
                node = None  # nothing below a value
        # what sits at the key now goes; the value comes
        old = (node.children.get(parts[-1]) if parts else node) if node is not None else None
        for gone in _subtree(old) if old is not None else ():
            if gone.owner == manager and gone is not self._root:
                after_keys, after_bytes = after_keys - 1, after_bytes - gone.size
        k, b = _measure(parts[-1] if parts else "", value)
        if not parts:
            k, b = k - 1, b  # the root itself is nobody's
        after_keys, after_bytes = after_keys + k, after_bytes + b
        if (after_keys > self.max_keys and after_keys > keys) or (after_bytes > self.max_bytes and after_bytes > size):
            raise PolicyDenied(
                "param_quota",
                f"{manager} would hold {after_keys} parameter keys, {after_bytes} bytes through setParam of {key[:80]} "
                f"(max_param_keys_per_peer {self.max_keys}, max_param_bytes_per_peer {self.max_bytes})",
            )
        if not parts:
            self._uncharge(self._root)
            self._root = _build("", value, manager)
            self._root.owner, self._root.size = "", 0
            self._charge(self._root)
            return
        node = self._root
        for part in parts[:-1]:
            child = node.children.get(part)
            if child is None:
                child = node.children[part] = _Node(manager, len(part), False)
                self._charge(child, subtree=False)
            elif child.value:
                self._uncharge(child)
                child.owner, child.size, child.value, child.data = manager, len(part), False, None
                self._charge(child)
            node = child
        old = node.children.pop(parts[-1], None)
        if old is not None:
            self._uncharge(old)
        new = node.children[parts[-1]] = _build(parts[-1], value, manager)
        self._charge(new)

    def delete(self, key: str) -> None:
        """rosmaster's ``deleteParam(key)`` (``key`` resolved): its subtree is freed."""
        parts = _parts(key)
        node: _Node | None = self._root
        for part in parts[:-1]:
            node = node.children.get(part) if node is not None else None
        if not parts or node is None:
            return  # rosmaster does not delete its root
        gone = node.children.pop(parts[-1], None)
        if gone is not None:
            self._uncharge(gone)

    def owners(self, key: str) -> frozenset[str]:
        """The managers that set ``key``, a namespace above it, or anything below it
        through here (what a read of ``key`` could return, or a write replace)."""
        found: set[str] = set()
        node: _Node | None = self._root
        for part in _parts(key):
            node = node.children.get(part) if node is not None else None
            if node is None:
                break
            if node.value:
                found.add(node.owner)  # a value above the key holds the key's value too
        if node is not None:
            found.update(n.owner for n in _subtree(node))
        found.discard("")
        return frozenset(found)

    def items(self) -> list[tuple[str, Any]]:
        """What rosmaster holds through here, as ``setParam`` calls would make it again:
        (key, value) of every value, and ``{}`` for every namespace with nothing in it,
        namespaces before what is below them."""
        out: list[tuple[str, Any]] = []
        stack = [("", self._root)]
        while stack:
            key, node = stack.pop()
            if node.value:
                out.append((key or "/", node.data))
            elif not node.children and node is not self._root:
                out.append((key, {}))
            stack.extend((f"{key}/{name}", child) for name, child in reversed(node.children.items()))
        return out

    def clear(self) -> None:
        """rosmaster restarted: it holds no parameter any more."""
        self._root = _Node("", 0, False)
        self._usage.clear()

    def _charge(self, node: _Node, *, subtree: bool = True, sign: int = 1) -> None:
        for one in _subtree(node) if subtree else (node,):
            if not one.owner:
                continue
            usage = self._usage.setdefault(one.owner, [0, 0])
            usage[0] += sign
            usage[1] += sign * one.size
            if usage[0] <= 0:
                del self._usage[one.owner]

    def _uncharge(self, node: _Node) -> None:
        self._charge(node, sign=-1)


__all__ = ["ParamQuota", "value_bytes"]
