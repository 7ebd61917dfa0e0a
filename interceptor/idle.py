"""Connections kept between calls: at most ``max_idle``, the most recently used taken
first (the others may age out), each closed once unused for ``idle_seconds``, all on
one timer. The XML-RPC tunnels to a peer and the calls to local servers keep theirs
here; what a connection is and how it closes is the caller's."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")


class IdleKeeper(Generic[T]):
    """Idle connections of one kind to one place. ``close`` ends one; ``on_expired`` is
    told each time one is closed for age."""

    def __init__(self, close: Callable[[T], None], *, max_idle: int, idle_seconds: float,
                 on_expired: Callable[[], None] = lambda: None) -> None:
        self._close = close
        self._max_idle = max_idle
        self._idle_seconds = idle_seconds
        self._on_expired = on_expired
        #: idle connections and when each was put back (the loop's clock), oldest first
        self._idle: list[tuple[T, float]] = []
        self._sweep: asyncio.TimerHandle | None = None

    def __len__(self) -> int:
        return len(self._idle)

    def take(self, usable: Callable[[T], bool] = lambda _: True) -> T | None:
        """The most recently parked connection still ``usable`` and young enough, or None;
        the others met on the way are closed."""
        now = asyncio.get_running_loop().time()
        while self._idle:
            item, since = self._idle.pop()
            if now - since < self._idle_seconds and usable(item):
                return item
            self._close(item)
        return None

    def park(self, item: T) -> None:
        """Keep ``item`` for the next call (closed at once if ``max_idle`` are kept)."""
        if len(self._idle) >= self._max_idle:
            self._close(item)
            return
        loop = asyncio.get_running_loop()
        self._idle.append((item, loop.time()))
        if self._sweep is None:
            self._sweep = loop.call_later(self._idle_seconds, self._close_aged)

    def _close_aged(self) -> None:
        self._sweep = None
        loop = asyncio.get_running_loop()
        due = loop.time() - self._idle_seconds + 0.01  # the loop may wake a little early
        while self._idle and self._idle[0][1] <= due:
            self._close(self._idle.pop(0)[0])
            self._on_expired()
        if self._idle:
            self._sweep = loop.call_at(self._idle[0][1] + self._idle_seconds, self._close_aged)

    def close(self) -> None:
        """Close every kept connection now."""
        if self._sweep is not None:
            self._sweep.cancel()
            self._sweep = None
        while self._idle:
            self._close(self._idle.pop()[0])


__all__ = ["IdleKeeper"]
