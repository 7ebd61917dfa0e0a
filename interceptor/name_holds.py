"""Node names kept for the manager that last held them (master role), sans-IO.

A node that restarts unregisters its name and registers it again moments later. In
between, the name is free at the master: a manager whose grant names nodes by a
pattern (``/rostopic_*``, or ``*``) could register it first, and the robot's own node
would then be refused as the hijacker (``name_taken``). So a name its last owner
released stays that owner's for ``hold_seconds``: another manager registering it
meanwhile is refused like a name still registered, and the owner takes it back.

Bounded: each manager has at most ``per_manager`` names held (its oldest hold goes
first), so no manager can grow the table or push out another's holds by churning names.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable


class NameHolds:
    def __init__(self, per_manager: int, *, clock: Callable[[], float] = time.monotonic) -> None:
        self.per_manager = per_manager
        self.clock = clock
        #: manager -> node -> until (in the order held: the oldest first)
        self._by_manager: dict[str, OrderedDict[str, float]] = {}
        #: node -> the manager holding it
        self._holder: dict[str, str] = {}

    def __len__(self) -> int:
        return len(self._holder)

    def release(self, node: str, manager: str, hold_seconds: float) -> None:
        """``manager``'s last registration of ``node`` is gone: hold the name for it."""
        self.claim(node)
        if hold_seconds <= 0:
            return
        held = self._by_manager.setdefault(manager, OrderedDict())
        held[node] = self.clock() + hold_seconds
        self._holder[node] = manager
        self._expire(manager)
        while len(held) > self.per_manager:
            gone, _until = held.popitem(last=False)
            del self._holder[gone]

    def claim(self, node: str) -> None:
        """``node`` is registered again (by its holder: the registry of owners has it now)."""
        manager = self._holder.pop(node, None)
        if manager is not None:
            held = self._by_manager[manager]
            del held[node]
            if not held:
                del self._by_manager[manager]

    def holder(self, node: str) -> str | None:
        """The manager ``node`` is held for, or None (never held, or the hold is over)."""
        manager = self._holder.get(node)
        if manager is None:
            return None
        if self._by_manager[manager][node] <= self.clock():
            self.claim(node)
            return None
        return manager

    def _expire(self, manager: str) -> None:
        held = self._by_manager.get(manager)
        now = self.clock()
        while held and next(iter(held.values())) <= now:
            gone, _until = held.popitem(last=False)
            del self._holder[gone]
        if held is not None and not held:
            del self._by_manager[manager]


__all__ = ["NameHolds"]
