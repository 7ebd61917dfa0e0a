"""At most N holders at once per key (a peer endpoint, a peer manager), waiters in line.

:class:`KeyedSlots` is an :class:`asyncio.Semaphore` per key, made on first use and
dropped when its last holder or waiter leaves: a key costs nothing at rest, and the
table holds only keys someone is using. A wait is bounded; past it the caller's
``on_timeout`` error is raised.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable, Hashable


class KeyedSlots:
    """Per-key semaphores, each of the size given at its first use."""

    def __init__(self) -> None:
        #: key -> [semaphore, holders and waiters]
        self._slots: dict[Hashable, list] = {}

    def __len__(self) -> int:
        return len(self._slots)

    @contextlib.asynccontextmanager
    async def hold(self, key: Hashable, limit: int, timeout: float,
                   on_timeout: Callable[[], Exception]) -> AsyncIterator[None]:
        """One of ``key``'s ``limit`` slots for the block; ``on_timeout()`` is raised if
        none frees within ``timeout`` seconds. ``limit`` counts when the key has no entry
        (a changed limit applies once the key's current users are gone)."""
        slot = self._slots.get(key)
        if slot is None:
            slot = self._slots[key] = [asyncio.Semaphore(limit), 0]
        slot[1] += 1
        try:
            if slot[0].locked():
                try:
                    async with asyncio.timeout(timeout):
                        await slot[0].acquire()
                except TimeoutError:
                    raise on_timeout() from None
            else:  # free: taken at once, without the timeout's timer (every master call comes here)
                await slot[0].acquire()
            try:
                yield
            finally:
                slot[0].release()
        finally:
            slot[1] -= 1
            if slot[1] == 0 and self._slots.get(key) is slot:
                del self._slots[key]


__all__ = ["KeyedSlots"]
