"""Topic streams a peer's side refused to this host's subscribers, and when their
subscribers may be told the publishers again (pure bookkeeping, clock passed in).

rospy, refused a topic stream, asks the publisher ``getPublications`` a second later and,
if the topic is not listed then, drops that publisher for good while the master lists
its URI (it never takes a URI it holds out of its list, and ignores one it holds). So a
grant given back soon after its removal would leave a listener deaf: the node role
remembers each refusal by the manager whose side refused, and that manager's next
fresher token (its grants may have changed) tells the topic's subscribers the publishers
again (``publisherUpdate``), at least :data:`REFUSED_RECHECK` after the refusal.

A peer whose side refuses every stream while it shows token after token would have each
of its topics' subscribers told again every 1.5 s (a security audit: 398
``publisherUpdate`` calls and 406 streams in 20 s over 30 topics, from an insider's node
answering every subscriber with an error header). So the wait doubles with each time a
topic was told again while its streams from that manager kept being refused (1.5, 3, 6
... s, up to :data:`REFUSED_MEMORY`), and a stream of that manager's on the topic
accepted starts it over.

Every telling after a stream of a manager's side ended or was refused also waits its
turn in that manager's bucket (:meth:`RefusedStreams.paced`): an insider whose node
accepted each subscriber's stream and closed it at once had the victim's subscribers
told again, and reconnecting, 330 times in 15 s over 30 topics (a re-audit), nothing
refused and so no back-off above.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from cryptoros.lru import remember
from interceptor.pump import MessageBudget

#: the least wait from a refusal to the subscribers told again (rospy's own check is
#: one second after the refusal): a grant given back within a second of its removal
#: left a listener deaf (a day-2 test, every run)
REFUSED_RECHECK = 1.5
#: a refusal older than this is not acted on; the longest wait between two tellings
REFUSED_MEMORY = 60.0
#: managers, and topics per manager, whose refused streams are remembered
MAX_REFUSED = 256
#: (manager, topic) pairs whose back-off is remembered
MAX_BACKOFFS = 4096
#: tellings after a manager's streams ended or were refused: this many a second per
#: manager after a burst that covers a robot's topics all cut at once (its host restarted)
TELLINGS_PER_SECOND = 2.0
TELLING_BURST = 64


class RefusedStreams:
    """Refusals by manager and topic, and the back-off of telling their subscribers."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._refused: dict[str, dict[str, float]] = {}  # manager -> topic -> when refused
        self._told: dict[tuple[str, str], int] = {}  # (manager, topic) -> times told since an accepted stream
        self._budgets: dict[str, MessageBudget] = {}  # manager -> its tellings' bucket

    def refused(self, manager: str, topic: str) -> None:
        """A topic stream from ``manager``'s side to a local subscriber was refused (or
        closed before its answer)."""
        topics = self._refused.get(manager)
        if topics is None:
            topics = {}
            remember(self._refused, manager, topics, MAX_REFUSED)
        remember(topics, topic, self._clock(), MAX_REFUSED)

    def accepted(self, manager: str, topic: str) -> None:
        """A stream of ``manager``'s on ``topic`` went through: its back-off starts over."""
        self._told.pop((manager, topic), None)

    def paced(self, manager: str) -> float:
        """Seconds one more telling of ``manager``'s topics waits for its turn (0: now);
        each call takes a turn, so the ones after it wait behind it."""
        budget = self._budgets.get(manager)
        if budget is None:
            budget = MessageBudget(TELLINGS_PER_SECOND, burst=TELLING_BURST, clock=self._clock)
        remember(self._budgets, manager, budget, MAX_REFUSED)
        wait = budget.delay(1)
        if wait > 0:
            budget.spend(1)  # queued: the next one waits behind this one
        return wait

    def due(self, manager: str) -> list[tuple[str, float]]:
        """``manager`` showed a fresher token: each topic its side refused lately, with the
        seconds to wait before its subscribers are told the publishers again; each is
        forgotten until refused again."""
        topics = self._refused.pop(manager, None)
        if not topics:
            return []
        now = self._clock()
        out = []
        for topic, at in topics.items():
            if now - at >= REFUSED_MEMORY:
                continue
            times = self._told.pop((manager, topic), 0)
            wait = min(REFUSED_RECHECK * 2 ** times, REFUSED_MEMORY)
            remember(self._told, (manager, topic), times + 1, MAX_BACKOFFS)
            out.append((topic, max(0.0, at + wait - now)))
        return out


__all__ = ["MAX_REFUSED", "REFUSED_MEMORY", "REFUSED_RECHECK", "RefusedStreams", "TELLINGS_PER_SECOND",
           "TELLING_BURST"]
