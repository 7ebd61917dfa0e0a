"""rosmaster's notifications to remote nodes (``publisherUpdate``, ``paramUpdate``),
answered at once and delivered behind the answer, one at a time per node API.

rosmaster sends every notification from three worker threads and waits for each answer
(``NUM_WORKERS = 3`` in ros_comm's rosmaster/master_api.py). Relayed straight, a remote
node API that takes a call and never answers holds a worker for the relay's whole
CALL_TIMEOUT; three such APIs of one robot, re-armed every second with allowed writes
to their own subscribed parameters, held all three: no robot learnt of a new publisher
or a parameter change while it went on (an insider audit: a subscriber on another robot
waited 100 s for its publisher). Here the master's interceptor queues a notification
per node API and answers rosmaster at once. A node API has at most one call in flight;
a later notification of the same topic or key replaces the queued one (each carries the
whole state: the topic's publishers, the key's value), and the queue keeps the order of
the latest ones, so the node ends in the state rosmaster's last notifications describe.
What waits per API is bounded by what it subscribed, and by :data:`MAX_QUEUED`.
"""

from __future__ import annotations

import asyncio
import logging
from collections import OrderedDict
from collections.abc import Awaitable, Callable, Hashable

from cryptoros.ros1.xmlrpc import Request, Response

log = logging.getLogger("cryptoros.interceptor.ros1")

#: the notifications rosmaster sends (its only calls to node APIs besides shutdown)
NOTICES = frozenset({"publisherUpdate", "paramUpdate"})
#: notifications queued per node API at most (distinct topics and keys); the oldest go
MAX_QUEUED = 1024
#: what rosmaster is answered (it reads only the code: -1 to a paramUpdate unsubscribes)
QUEUED = Response(value=[1, "queued by cryptoros", 0])


class Notices:
    """Per-target queues of notifications, each drained by one task at a time.

    ``deliver(target, request)``: the call to the node API (its answer is not used);
    ``spawn(coro)``: runs a drain (the gateway's, so a stop cuts it)."""

    def __init__(self, deliver: Callable[[Hashable, Request], Awaitable[object]],
                 spawn: Callable[[Awaitable[None]], object], *, max_queued: int = MAX_QUEUED) -> None:
        self._deliver = deliver
        self._spawn = spawn
        self.max_queued = max_queued
        self._queues: dict[Hashable, OrderedDict[tuple[str, object], Request]] = {}
        self.delivered = 0
        self.replaced = 0  # superseded by a later notification of the same topic or key
        self.dropped = 0  # over max_queued

    def post(self, target: Hashable, request: Request) -> Response:
        """Queue ``request`` for ``target``; what rosmaster is answered now."""
        queue = self._queues.get(target)
        if queue is None:
            queue = self._queues[target] = OrderedDict()
            self._spawn(self._drain(target, queue))
        key = (request.method, request.params[1] if len(request.params) > 1 else None)
        if queue.pop(key, None) is not None:
            self.replaced += 1
        queue[key] = request
        if len(queue) > self.max_queued:
            queue.popitem(last=False)
            self.dropped += 1
            if self.dropped in (1, 10, 100) or self.dropped % 1000 == 0:
                log.warning("notifications to %s: more than %d queued; the oldest dropped (%d so far)",
                            target, self.max_queued, self.dropped)
        return QUEUED

    def pending(self) -> int:
        return sum(len(q) for q in self._queues.values())

    async def _drain(self, target: Hashable, queue: OrderedDict[tuple[str, object], Request]) -> None:
        try:
            while queue:
                _, request = queue.popitem(last=False)
                try:
                    await self._deliver(target, request)
                    self.delivered += 1
                except asyncio.CancelledError:
                    raise
                except Exception as exc:  # a node gone or refusing: rosmaster would only have logged it
                    log.info("%s to %s not delivered: %s", request.method, target, exc)
        finally:
            if self._queues.get(target) is queue:
                del self._queues[target]


__all__ = ["MAX_QUEUED", "NOTICES", "QUEUED", "Notices"]
