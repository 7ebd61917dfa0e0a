"""A lean receive loop for raw (serialized) rclpy subscriptions, without an executor.

rclpy's executors rebuild a wait set and run a task per message: on this 2-core
machine a SingleThreadedExecutor delivers about 1,100 to 1,900 small messages a
second. :class:`RawTaker` keeps one wait set over its subscriptions, wakes once, then
takes *every* message ready on every subscription (``take_message`` until empty) and
hands them over as one batch, so a burst costs one wake-up and its receiver can write
the whole batch with one syscall.

The subscriptions must belong to a node that no executor spins (the executor would
take from them too). Standard library and rclpy only: imported by the DDS bridge and
the benchmark nodes, which run under the ROS 2 venv's python.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

#: how long one wait lasts before shutdown is checked again
WAIT_NS = 200_000_000
#: at most this many messages are taken from one subscription per wake-up (fairness)
MAX_BATCH = 256


class RawTaker:
    """``add(key, subscription)``; ``run(on_batch)`` calls ``on_batch([(key, cdr), ...])``."""

    def __init__(self, context) -> None:
        self._context = context
        self._lock = threading.Lock()
        self._subs: dict[object, object] = {}
        self._changed = True
        self._stop = False
        self._gc = _rclpy.GuardCondition(context.handle)

    def add(self, key: object, subscription) -> None:
        with self._lock:
            self._subs[key] = subscription
            self._changed = True
        self._wake()

    def remove(self, key: object):
        """Stop taking from ``key``'s subscription; returns it (destroy it afterwards:
        rclpy defers the destruction while this loop holds the handle)."""
        with self._lock:
            sub = self._subs.pop(key, None)
            self._changed = True
        self._wake()
        return sub

    def stop(self) -> None:
        self._stop = True
        self._wake()

    def _wake(self) -> None:
        with contextlib.suppress(Exception):
            with self._gc:
                self._gc.trigger_guard_condition()

    def run(self, on_batch: Callable[[list[tuple[object, bytes]]], None]) -> None:
        while not self._stop and self._context.ok():
            with self._lock:
                entries = list(self._subs.items())
                self._changed = False
            with contextlib.ExitStack() as stack:
                live = []
                for key, sub in entries:
                    try:
                        stack.enter_context(sub.handle)
                        live.append((key, sub.handle, sub.msg_type))
                    except Exception:  # destroyed meanwhile
                        continue
                stack.enter_context(self._gc)
                stack.enter_context(self._context.handle)
                wait_set = _rclpy.WaitSet(len(live), 1, 0, 0, 0, 0, self._context.handle)
                while not self._stop and not self._changed and self._context.ok():
                    wait_set.clear_entities()
                    for _, handle, _ in live:
                        wait_set.add_subscription(handle)
                    wait_set.add_guard_condition(self._gc)
                    wait_set.wait(WAIT_NS)
                    batch: list[tuple[object, bytes]] = []
                    for key, handle, msg_type in live:
                        for _ in range(MAX_BATCH):
                            taken = handle.take_message(msg_type, True)
                            if taken is None:
                                break
                            batch.append((key, taken[0]))
                    if batch:
                        on_batch(batch)


__all__ = ["RawTaker"]
