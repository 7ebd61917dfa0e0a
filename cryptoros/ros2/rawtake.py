"""A lean receive loop for raw (serialized) rclpy subscriptions, without an executor.

rclpy's executors rebuild a wait set and run a task per message: on this 2-core
machine a SingleThreadedExecutor delivers about 1,100 to 1,900 small messages a
second. :class:`RawTaker` keeps one wait set over its subscriptions, wakes once, then
takes *every* message ready on every subscription (``take_message`` until empty) and
hands them over as one batch, so a burst costs one wake-up and its receiver can write
the whole batch with one syscall.

Each message comes with its writer's GID (``rmw_message_info_t.publisher_gid``), which
rclpy's own ``take_message`` drops: the loop calls ``rcl_take_serialized_message`` of
the wheels' ``librcl`` through :mod:`ctypes` (one call and one copy per message, like
rclpy's raw take). The GID is what the graph reports as a publisher's
``endpoint_gid``: the DDS bridge forwards a sample only when its writer belongs to a
granted node (docs/ros2.md).

The subscriptions must belong to a node that no executor spins (the executor would
take from them too). Standard library and rclpy only: imported by the DDS bridge and
the benchmark nodes, which run under the ROS 2 venv's python.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import threading
from collections.abc import Callable

import rclpy
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

#: how long one wait lasts before shutdown is checked again
WAIT_NS = 200_000_000
#: at most this many messages are taken from one subscription per wake-up (fairness)
MAX_BATCH = 256


#: rcl_take_serialized_message's answer when nothing is left to take
RCL_RET_SUBSCRIPTION_TAKE_FAILED = 401
GID_SIZE = 16  # RMW_GID_STORAGE_SIZE in Jazzy


class _Allocator(ctypes.Structure):  # rcutils_allocator_t
    _fields_ = [("allocate", ctypes.c_void_p), ("deallocate", ctypes.c_void_p), ("reallocate", ctypes.c_void_p),
                ("zero_allocate", ctypes.c_void_p), ("state", ctypes.c_void_p)]


class _Bytes(ctypes.Structure):  # rcutils_uint8_array_t (rcl_serialized_message_t)
    _fields_ = [("buffer", ctypes.POINTER(ctypes.c_uint8)), ("buffer_length", ctypes.c_size_t),
                ("buffer_capacity", ctypes.c_size_t), ("allocator", _Allocator)]


class _Gid(ctypes.Structure):  # rmw_gid_t
    _fields_ = [("implementation_identifier", ctypes.c_char_p), ("data", ctypes.c_uint8 * GID_SIZE)]


class _MessageInfo(ctypes.Structure):  # rmw_message_info_t
    _fields_ = [("source_timestamp", ctypes.c_int64), ("received_timestamp", ctypes.c_int64),
                ("publication_sequence_number", ctypes.c_uint64), ("reception_sequence_number", ctypes.c_uint64),
                ("publisher_gid", _Gid), ("from_intra_process", ctypes.c_bool)]


@functools.cache
def _libs() -> tuple[ctypes.CDLL, ctypes.CDLL]:
    """The wheels' librcl and librcutils (next to rclpy: ``<venv>/lib``); OSError if absent."""
    libdir = os.path.realpath(os.path.join(os.path.dirname(rclpy.__file__), "..", "..", ".."))
    rcl = ctypes.CDLL(os.path.join(libdir, "librcl.so"))
    rcutils = ctypes.CDLL(os.path.join(libdir, "librcutils.so"))
    rcl.rcl_take_serialized_message.restype = ctypes.c_int32
    rcl.rcl_take_serialized_message.argtypes = [ctypes.c_void_p, ctypes.POINTER(_Bytes),
                                                ctypes.POINTER(_MessageInfo), ctypes.c_void_p]
    rcutils.rcutils_get_default_allocator.restype = _Allocator
    rcutils.rcutils_uint8_array_init.restype = ctypes.c_int32
    rcutils.rcutils_uint8_array_fini.restype = ctypes.c_int32
    return rcl, rcutils


class SerializedTake:
    """``take(rcl_subscription_pointer) -> (cdr, writer_gid) | None`` (the pointer: an
    rclpy subscription handle's ``pointer``, valid while the handle is held): one reusable buffer
    (grown by the rmw as messages need), for the one thread that takes."""

    def __init__(self, capacity: int = 64 * 1024) -> None:
        self._rcl, rcutils = _libs()
        self._buffer = _Bytes()
        allocator = rcutils.rcutils_get_default_allocator()
        if rcutils.rcutils_uint8_array_init(ctypes.byref(self._buffer), capacity, ctypes.byref(allocator)) != 0:
            raise MemoryError("cannot allocate the take buffer")
        self._info = _MessageInfo()
        self._fini = rcutils.rcutils_uint8_array_fini

    def take(self, pointer: int) -> tuple[bytes, bytes] | None:
        ret = self._rcl.rcl_take_serialized_message(pointer, ctypes.byref(self._buffer),
                                                    ctypes.byref(self._info), None)
        if ret == RCL_RET_SUBSCRIPTION_TAKE_FAILED:
            return None
        if ret != 0:
            raise RuntimeError(f"rcl_take_serialized_message failed ({ret})")
        return (ctypes.string_at(self._buffer.buffer, self._buffer.buffer_length),
                bytes(self._info.publisher_gid.data))

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self._fini(ctypes.byref(self._buffer))


class RawTaker:
    """``add(key, subscription)``; ``run(on_batch)`` calls
    ``on_batch([(key, cdr, writer_gid), ...])``."""

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

    def run(self, on_batch: Callable[[list[tuple[object, bytes, bytes]]], None]) -> None:
        """Take until :meth:`stop` or the context's shutdown; what the shutdown makes a
        wait or take raise ends the loop quietly, anything else is raised."""
        try:
            self._run(on_batch)
        except Exception:
            if self._stop or not self._context.ok():
                return
            raise

    def _run(self, on_batch: Callable[[list[tuple[object, bytes, bytes]]], None]) -> None:
        take = SerializedTake().take
        while not self._stop and self._context.ok():
            with self._lock:
                entries = list(self._subs.items())
                self._changed = False
            with contextlib.ExitStack() as stack:
                live = []
                for key, sub in entries:
                    try:
                        stack.enter_context(sub.handle)
                        live.append((key, sub.handle, sub.handle.pointer))
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
                    batch: list[tuple[object, bytes, bytes]] = []
                    for key, _, pointer in live:
                        for _ in range(MAX_BATCH):
                            taken = take(pointer)
                            if taken is None:
                                break
                            batch.append((key, *taken))
                    if batch:
                        on_batch(batch)


__all__ = ["RawTaker", "SerializedTake"]
