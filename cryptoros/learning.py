"""Learning mode on the interceptor's side: grants widened while a manager learns, and
what its own nodes were seen to need.

The registry puts a manager in learning mode for a bounded window (``cryptoros-authz
learn start``); the revocation feed carries ``learning: {manager: until}`` to every
interceptor. While the window lasts:

- a request of this interceptor's own nodes that its grants would refuse is let
  through and recorded (:class:`ObservationTable`, reported to the authorization
  server, which proposes the grants from it);
- a peer's request is let through only while the peer's manager learns too and this
  interceptor's own manager learns, or this interceptor is the master's (it serves
  every manager: registrations and parameters are not a peer-to-peer flow).

Only what grants answer is widened, after everything else was checked: the TLS
certificate and its CRL, the token (signature, time, binding, feed), the calls that
are always dropped (``shutdown``), name ownership (a learning manager cannot take a
name another manager registered: :meth:`LearningGrants.names_node_exactly` is never
widened), rates and quotas. A window ends by itself at ``until`` (the clock is read on
every decision), and when the feed drops it.

Grants that did allow a request of the own manager are recorded too (``allowed``):
that is what ``cryptoros-authz unused`` compares the grants against.

Pure: the clock is passed in; nothing here does I/O.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

from cryptoros.grants import Grants

Clock = Callable[[], float]

#: keys an interceptor keeps between two reports (each ~200 bytes)
MAX_KEYS = 4096
#: a key already reported as allowed is reported again only this long after (seconds):
#: ``unused`` works in days, and a robot checks the same grants over and over
USED_REPORT_EVERY = 300.0


class _AnyTypes(frozenset):
    """Every type (what :meth:`LearningGrants.types_for` answers for a name nothing
    grants while learning: the type is decided, and recorded, when it is seen)."""

    def __contains__(self, item: object) -> bool:
        return True

    def __repr__(self) -> str:
        return "ANY_TYPES"


ANY_TYPES: frozenset[str] = _AnyTypes({"*"})


@dataclass(frozen=True, slots=True)
class Seen:
    """One request, as recorded: ``node`` wanted to ``action`` ``name`` (a topic, a
    service, a parameter key) with ``type`` (None: not told by this request)."""

    allowed: bool  # True: a grant allowed it; False: only learning mode did
    action: str
    node: str
    name: str
    type: str | None


@dataclass(slots=True)
class _Row:
    count: int = 0
    first: float = 0.0
    last: float = 0.0
    unreported: int = 0  # seen since the last report
    reported_at: float = 0.0  # 0: never reported


class ObservationTable:
    """Requests seen, by :class:`Seen`: count, first and last seen (wall clock), and
    what is still to be reported. Bounded: a new key past ``max_keys`` is dropped and
    counted (:attr:`dropped`)."""

    def __init__(self, max_keys: int = MAX_KEYS, used_every: float = USED_REPORT_EVERY) -> None:
        self.max_keys = max_keys
        self.used_every = used_every
        self._rows: dict[Seen, _Row] = {}
        self.dropped = 0
        #: nodes seen in a learned request (their own private parameters are theirs
        #: once the proposal names them, so they are theirs while learning too)
        self.learned_nodes: set[str] = set()

    def record(self, seen: Seen, now: float) -> None:
        row = self._rows.get(seen)
        if row is None:
            if len(self._rows) >= self.max_keys:
                self.dropped += 1
                return
            self._rows[seen] = row = _Row(first=now)
            if not seen.allowed:
                self.learned_nodes.add(seen.node)
        row.count += 1
        row.last = now
        row.unreported += 1

    def due(self, now: float) -> list[dict]:
        """What to report now (learned keys with news; allowed keys with news not
        reported for :attr:`used_every`); marks them reported."""
        out = []
        for seen, row in self._rows.items():
            if not row.unreported or (seen.allowed and row.reported_at and now - row.reported_at < self.used_every):
                continue
            out.append({"allowed": seen.allowed, "action": seen.action, "node": seen.node, "name": seen.name,
                        "type": seen.type, "count": row.unreported, "first": row.first, "last": row.last})
            row.unreported, row.reported_at = 0, now
        return out

    def unreport(self, rows: Iterable[Mapping]) -> None:
        """A report that failed: its counts are due again."""
        for r in rows:
            row = self._rows.get(Seen(r["allowed"], r["action"], r["node"], r["name"], r["type"]))
            if row is not None:
                row.unreported += r["count"]
                row.reported_at = 0.0

    def learned(self) -> list[dict]:
        """The learned keys, most seen first (``status``)."""
        rows = [{"action": s.action, "node": s.node, "name": s.name, "type": s.type, "count": r.count,
                 "first": r.first, "last": r.last} for s, r in self._rows.items() if not s.allowed]
        return sorted(rows, key=lambda r: -r["count"])

    def forget_learned(self) -> None:
        """A window ended: what it learned was reported (or is lost with it)."""
        for seen in [s for s, r in self._rows.items() if not s.allowed and not r.unreported]:
            del self._rows[seen]
        self.learned_nodes.clear()


class LearningState:
    """Which managers learn now (from the feed) and what this interceptor records."""

    def __init__(self, own: str, *, serves_everyone: bool, clock: Clock = time.time,
                 table: ObservationTable | None = None) -> None:
        self.own = own
        #: the master's interceptor: a learning peer's registrations and parameters are let
        #: through whatever its own manager does
        self.serves_everyone = serves_everyone
        self.clock = clock
        self.windows: Mapping[str, float] = {}
        self.table = table or ObservationTable()
        #: the master's interceptor: who set what a parameter key holds (its value, those
        #: below it, a value above it); a learning peer's parameter access is widened
        #: only over what itself or other learning managers set
        self.param_owners: Callable[[str], frozenset[str]] | None = None

    def until(self, manager: str) -> float | None:
        """When ``manager``'s window ends, while it lasts."""
        until = self.windows.get(manager)
        return until if until is not None and self.clock() < until else None

    def learning(self, manager: str) -> bool:
        return self.until(manager) is not None

    def widens(self, manager: str) -> bool:
        """Whether ``manager``'s grants are widened here now."""
        if not self.learning(manager):
            return False
        return manager == self.own or self.serves_everyone or self.learning(self.own)

    def widens_param(self, manager: str, key: str) -> bool:
        """Whether ``manager``'s parameter access to ``key`` is widened here now: as
        :meth:`widens`, and never over a value another manager that does not learn set."""
        if not self.widens(manager):
            return False
        if manager == self.own or self.param_owners is None:
            return True
        return all(owner == manager or self.learning(owner) for owner in self.param_owners(key))

    def note(self, allowed: bool, action: str, node: str, name: str, type_: str | None) -> None:
        self.table.record(Seen(allowed, action, node, name, type_), self.clock())

    def grants(self, subject: str, grants: Grants) -> Grants:
        """``grants`` of ``subject`` as decisions here see them."""
        return LearningGrants(grants, subject, self)


class LearningGrants(Grants):
    """A manager's grants as an interceptor decides with them: the same answers, except
    that while :meth:`LearningState.widens` the manager, what they would refuse is
    allowed (and, for the interceptor's own manager, recorded); the own manager's
    allowed requests are recorded as used."""

    __slots__ = ("_subject", "_state", "_own")

    def __init__(self, grants: Grants, subject: str, state: LearningState) -> None:
        self._grants, self._index = grants._grants, grants._index  # shared, immutable
        self._subject = subject
        self._state = state
        self._own = subject == state.own

    def _miss(self, action: str, node: str, name: str, type_: str | None) -> bool:
        if not self._state.widens(self._subject):
            return False
        if self._own:
            self._state.note(False, action, node, name, type_)
        return True

    def allows(self, action: str, node: str, name: str, type: str) -> bool:
        if super().allows(action, node, name, type):
            if self._own:
                self._state.note(True, action, node, name, type)
            return True
        return self._miss(action, node, name, type)

    def types_for(self, action: str, node: str, name: str) -> frozenset[str]:
        types = super().types_for(action, node, name)
        if types:
            if self._own:
                for type_name in types:
                    self._state.note(True, action, node, name, type_name)
            return types
        return ANY_TYPES if self._miss(action, node, name, None) else types

    def param_allows(self, access: str, node: str, key: str) -> bool:
        action = f"{access}_param"
        if super().param_allows(access, node, key):
            if self._own:
                self._state.note(True, action, node, key, None)
            return True
        if not self._state.widens_param(self._subject, key):
            return False
        return self._miss(action, node, key, None)

    def param_namespaces(self, node: str) -> frozenset[str]:
        """What a namespace read may reach; every key in its answer is judged again by
        :meth:`param_allows` (another manager's values are pruned from it)."""
        namespaces = super().param_namespaces(node)
        return namespaces | {"/"} if self._state.widens(self._subject) else namespaces

    def names_node(self, node: str) -> bool:
        if super().names_node(node):
            return True
        if not self._state.widens(self._subject):
            return False
        # a peer's node at the master's interceptor (its name is bound by registration);
        # an own node once a learned request named it
        return not self._own or node in self._state.table.learned_nodes

    def any_node_allows(self, action: str, name: str, type_name: str) -> bool:
        return super().any_node_allows(action, name, type_name) or self._state.widens(self._subject)


__all__ = ["ANY_TYPES", "LearningGrants", "LearningState", "ObservationTable", "Seen", "USED_REPORT_EVERY"]
