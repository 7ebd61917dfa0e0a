"""Publishers' requestTopic answers, shared by the subscribers of this host.

When a robot brings up its nodes, each subscriber asks every publisher of its topic for
a TCPROS endpoint (``requestTopic``). In ROS 1 that answer depends on the publisher only
(rospy and roscpp name the node's one TCPROS server for every topic and caller), so 50
subscribers starting at once need one tunnelled call per publisher and topic, not 50:
calls already in flight wait for the first one's answer, and a successful answer serves
calls for :data:`ANSWER_SECONDS` more. A restarted publisher has a new node API (a new
export, so a new key); what the answer names is checked again, against fresh grants at
both ends, when the subscriber connects. Who may take a shared answer is the caller's
business (:meth:`~interceptor.ros1.relays.Relays._on_xmlrpc_relay`: subscribers this
host registered, while its manager's current token grants them the topic).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable, Hashable

from cryptoros.lru import remember
from cryptoros.ros1.xmlrpc import Fault, Response

#: how long a publisher's successful answer serves later subscribers (a bring-up's span;
#: a publisher's TCPROS endpoint is fixed for its life)
ANSWER_SECONDS = 2.0
#: answers kept at most (publisher and topic pairs), the least recently stored dropped
MAX_ANSWERS = 1024


def _succeeded(response: Response | Fault) -> bool:
    return isinstance(response, Response) and isinstance(response.value, list) and response.value[:1] == [1]


class TopicAnswers:
    """Single-flight, briefly kept answers per key (a publisher's node API and a topic)."""

    def __init__(self, *, seconds: float = ANSWER_SECONDS, cap: int = MAX_ANSWERS,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.seconds = seconds
        self.cap = cap
        self.clock = clock
        self._kept: dict[Hashable, tuple[float, Response]] = {}
        self._asking: dict[Hashable, asyncio.Future[Response | None]] = {}
        self.shared = 0  # calls answered without a call of their own (/status)

    async def ask(self, key: Hashable, call: Callable[[], Awaitable[Response | Fault]]) -> Response | Fault:
        """The answer for ``key``: kept, the one in flight, or ``call()``'s. A failed or
        refused call is never shared: each waiter then makes its own."""
        kept = self._kept.get(key)
        if kept is not None:
            if kept[0] > self.clock():
                self.shared += 1
                return kept[1]
            del self._kept[key]
        pending = self._asking.get(key)
        if pending is not None:
            answer = await asyncio.shield(pending)
            if answer is not None:
                self.shared += 1
                return answer
            return await call()
        future: asyncio.Future[Response | None] = asyncio.get_running_loop().create_future()
        self._asking[key] = future
        answer: Response | None = None
        try:
            response = await call()
            if isinstance(response, Response) and _succeeded(response):
                answer = response
                remember(self._kept, key, (self.clock() + self.seconds, response), self.cap)
            return response
        finally:
            del self._asking[key]
            future.set_result(answer)


__all__ = ["ANSWER_SECONDS", "TopicAnswers"]
