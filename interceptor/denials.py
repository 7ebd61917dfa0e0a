"""Refusals, aggregated: what the log says about them and the table ``/status`` shows.

A denial is keyed by (kind, peer, reason, target). The first of a key is logged at once;
repeats within ``interval`` seconds are only counted, and the next one after the
interval logs one line with the count (so a node that retries, or logs at 5 Hz while a
parameter it reads is refused, adds a line per interval, not per call). The table is
bounded (the least recently seen key is dropped) and carries, per key, the
``cryptoros-authz grant ...`` command that would allow it when one is known.

Sans-IO: the clock is passed in; :meth:`DenialTable.record` returns the lines to log.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from cryptoros.lru import remember

#: seconds between two log lines of one key
INTERVAL = 10.0
#: keys kept (each a few hundred bytes)
MAX_KEYS = 512
#: lines logged per interval for refusals of connections that showed no certificate
#: (``tls``), all sources together; the rest are counted in one line at the next interval.
#: A stranger chooses how many sources and kinds of junk it sends: 20 addresses gave
#: 160-240 lines a minute, a /24 about 0.5 GB of log a day.
MAX_UNAUTHENTICATED_LINES = 20


@dataclass
class _Entry:
    kind: str
    peer: str
    reason: str
    target: str
    hint: str | None
    first: float
    last: float
    total: int = 1
    #: repeats since the last line logged, and when that line was logged
    unlogged: int = 0
    logged_at: float = 0.0


@dataclass
class DenialTable:
    interval: float = INTERVAL
    max_keys: int = MAX_KEYS
    max_unauthenticated_lines: int = MAX_UNAUTHENTICATED_LINES
    _entries: dict[tuple[str, str, str, str], _Entry] = field(default_factory=dict)
    #: the unauthenticated lines' window: its start, lines logged in it, lines held back
    _window: list[float] = field(default_factory=lambda: [float("-inf"), 0, 0])

    def record(self, kind: str, peer: str, reason: str, target: str, now: float,
               hint: str | None = None) -> list[str]:
        """Count one refusal (``target``: what was refused and why, as logged); returns
        the log lines it calls for (none, one, or a count of lines held back too)."""
        lines = self._record(kind, peer, reason, target, now, hint)
        return self._within_budget(lines, now) if kind == "tls" else lines

    def _within_budget(self, lines: list[str], now: float) -> list[str]:
        start, logged, held = self._window
        out = []
        if now - start >= self.interval:
            if held:
                out.append(f"DENY tls: {held} more line(s) of refused connections not logged in the last "
                           f"{now - start:.0f} s (over {self.max_unauthenticated_lines} every {self.interval:g} s; "
                           "cryptoros denials lists them all)")
            start, logged, held = now, 0, 0
        for line in lines:
            if logged < self.max_unauthenticated_lines:
                out.append(line)
                logged += 1
            else:
                held += 1
        self._window[:] = [start, logged, held]
        return out

    def _record(self, kind: str, peer: str, reason: str, target: str, now: float, hint: str | None) -> list[str]:
        key = (kind, peer, reason, target)
        entry = self._entries.pop(key, None)
        if entry is None:
            entry = _Entry(kind, peer, reason, target, hint, first=now, last=now, logged_at=now)
            remember(self._entries, key, entry, self.max_keys)
            return [f"DENY {kind} from {peer}: {target}{_hint(hint)}"]
        self._entries[key] = entry  # most recently seen last
        entry.total += 1
        entry.last = now
        entry.hint = hint or entry.hint
        if now - entry.logged_at < self.interval:
            entry.unlogged += 1
            return []
        count, entry.unlogged, since = entry.unlogged + 1, 0, entry.logged_at
        entry.logged_at = now
        return [f"DENY {kind} from {peer}: {target} ({count} times in the last {now - since:.0f} s, "
                f"{entry.total} in all){_hint(hint)}"]

    def table(self, now: float) -> list[dict]:
        """The keys, most recent first: what ``cryptoros denials`` shows."""
        return [{"kind": e.kind, "peer": e.peer, "reason": e.reason, "target": e.target, "count": e.total,
                 "first_ago": round(now - e.first, 1), "last_ago": round(now - e.last, 1), "grant": e.hint}
                for e in reversed(self._entries.values())]


def _hint(hint: str | None) -> str:
    return f" (to allow: {hint})" if hint else ""


__all__ = ["INTERVAL", "MAX_KEYS", "MAX_UNAUTHENTICATED_LINES", "DenialTable"]
