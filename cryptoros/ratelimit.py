"""Bounded per-key rate limits, shared by the interceptor and the authorization server.

:class:`TokenBuckets` admits ``rate`` events per second per key after a burst;
:class:`OncePer` lets a log line through once per interval per key; :class:`Shunned`
turns a key away for a while once its failures outran a budget. All keep at most
``max_keys`` keys (the least recently used go first), so a flood of new keys costs
bounded memory. Pure: the clock is passed in.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Hashable

from cryptoros.lru import remember


class TokenBuckets:
    """A token bucket per key: ``rate`` per second, up to ``burst`` at once."""

    def __init__(self, rate: float, burst: float, *, max_keys: int = 10_000,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.rate, self.burst, self.max_keys = rate, max(1.0, float(burst)), max_keys
        self._clock = clock
        self._state: dict[Hashable, tuple[float, float]] = {}

    def allow(self, key: Hashable) -> bool:
        now = self._clock()
        tokens, last = self._state.pop(key, (self.burst, now))
        tokens = min(self.burst, tokens + (now - last) * self.rate)
        allowed = tokens >= 1.0
        remember(self._state, key, (tokens - 1.0 if allowed else tokens, now), self.max_keys)
        return allowed


class OncePer:
    """True for a key at most once per ``seconds`` (log lines of a repeated event)."""

    def __init__(self, seconds: float, *, max_keys: int = 10_000, clock: Callable[[], float] = time.monotonic) -> None:
        self.seconds, self.max_keys = seconds, max_keys
        self._clock = clock
        self._last: dict[Hashable, float] = {}

    def __call__(self, key: Hashable) -> bool:
        now = self._clock()
        last = self._last.pop(key, None)
        due = last is None or now - last >= self.seconds
        remember(self._last, key, now if due else last, self.max_keys)  # type: ignore[arg-type]
        return due


class Shunned:
    """Keys whose failures outran ``rate`` per second after a ``burst``: each is turned
    away for ``seconds`` from its failure past the budget."""

    def __init__(self, rate: float, burst: float, seconds: float, *, max_keys: int = 10_000,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.seconds, self.max_keys = seconds, max_keys
        self._clock = clock
        self._failures = TokenBuckets(rate, burst, max_keys=max_keys, clock=clock)
        self._until: dict[Hashable, float] = {}

    def failed(self, key: Hashable) -> bool:
        """Count a failure of ``key``: True when it is past the budget (shunned from now)."""
        if self._failures.allow(key):
            return False
        self._until.pop(key, None)
        remember(self._until, key, self._clock() + self.seconds, self.max_keys)
        return True

    def left(self, key: Hashable) -> float:
        """Seconds ``key`` is still turned away (0: not shunned)."""
        until = self._until.get(key)
        if until is None:
            return 0.0
        left = until - self._clock()
        if left <= 0:
            del self._until[key]
            return 0.0
        return left


__all__ = ["OncePer", "Shunned", "TokenBuckets"]
