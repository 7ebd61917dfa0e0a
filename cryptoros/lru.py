"""Bounded tables that forget their least recently stored entries.

Every cache and per-peer table of cryptoros is capped, so a peer cannot grow it without
bound. A ``dict`` keeps insertion order, so storing a key anew (popped, then set) makes
it the most recent, and the first key is always the oldest: :func:`remember` is that
idiom in one place.
"""

from __future__ import annotations

from collections.abc import MutableMapping
from typing import TypeVar

K = TypeVar("K")
V = TypeVar("V")


def remember(table: MutableMapping[K, V], key: K, value: V, cap: int) -> list[tuple[K, V]]:
    """``table[key] = value`` as the most recent entry; past ``cap`` entries the oldest
    are dropped and returned, oldest first (to close what they hold, say)."""
    table.pop(key, None)
    table[key] = value
    dropped: list[tuple[K, V]] = []
    while len(table) > cap:
        oldest = next(iter(table))
        dropped.append((oldest, table.pop(oldest)))
    return dropped


__all__ = ["remember"]
