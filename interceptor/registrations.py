"""What this host's nodes asked the master to register (node role), kept so that a
grant that arrives while they run takes effect with no node restart.

A rospy or roscpp node registers a publication, subscription or service once, when it
declares it; refused (no grant yet), it logs the refusal and never asks again. The
ledger keeps each registration a local node made or had refused, as the node sent it,
by (kind, node, name). When this interceptor's own token changes, the ones the new
grants cover and the old did not (a grant added, or removed and added back), and every
refused one the new grants cover, are made again on the node's behalf
(:meth:`LocalRegistrations.to_resend`); the role then tells a subscriber its publishers.

Pure state: no I/O, no clock. Bounded: at most ``max_entries`` kept in all, of them at
most ``max_refused`` refused (the oldest refused one goes first).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from cryptoros.errors import PolicyDenied
from cryptoros.policy.ros1 import check_master_call
from cryptoros.grants import Grants

#: the master calls a node registers with, and the kind each makes
REGISTER = {"registerPublisher": "pub", "registerSubscriber": "sub", "registerService": "srv"}
#: the calls that release one
RELEASE = {"unregisterPublisher": "pub", "unregisterSubscriber": "sub", "unregisterService": "srv"}

Key = tuple[str, str, str]


@dataclass(frozen=True, slots=True)
class Registration:
    """One registration as the node sent it (its own local URIs)."""

    method: str
    params: tuple
    refused: bool

    @property
    def node_api(self) -> str | None:
        """The node's XML-RPC API (caller_api, the last parameter of every register call)."""
        api = self.params[3] if len(self.params) > 3 else None
        return api if isinstance(api, str) else None


def _key(method: str, params: tuple) -> Key | None:
    kind = REGISTER.get(method) or RELEASE.get(method)
    if kind is None or len(params) < 2 or not isinstance(params[0], str) or not isinstance(params[1], str):
        return None
    return kind, params[0], params[1]


def covers(grants: Grants, manager: str, method: str, params: tuple) -> bool:
    """Whether ``grants`` let ``manager``'s node make this registration (the same check
    the local master makes; who else holds the name is the master's interceptor's to say)."""
    try:
        check_master_call(method, params, manager=manager, grants=grants, owners={})
    except PolicyDenied:
        return False
    return True


class LocalRegistrations:
    """Registrations of this host's nodes: made (rosmaster holds them) or refused."""

    def __init__(self, max_entries: int = 8192, max_refused: int = 1024) -> None:
        self.max_entries = max_entries
        self.max_refused = max_refused
        self._entries: dict[Key, Registration] = {}
        self._refused: dict[Key, None] = {}  # the refused keys, oldest first
        #: registrations not kept because the ledger was full (for /status and a log line)
        self.dropped = 0

    def __len__(self) -> int:
        return len(self._entries)

    @property
    def refused_count(self) -> int:
        return len(self._refused)

    def get(self, method: str, params: tuple) -> Registration | None:
        key = _key(method, params)
        return None if key is None else self._entries.get(key)

    def made(self, method: str, params: tuple) -> None:
        """rosmaster accepted it."""
        self._put(method, params, refused=False)

    def refused(self, method: str, params: tuple) -> bool:
        """Refused (for want of a grant, here or at the master): made later if a grant
        comes. Whether the ledger changed (a refusal repeated changes nothing)."""
        key = _key(method, params)
        known = None if key is None else self._entries.get(key)
        if known is not None and known.refused and known.params == tuple(params):
            return False
        self._put(method, params, refused=True)
        return key is not None and key in self._refused

    def of_node(self, node: str) -> list[Registration]:
        """Every registration of ``node``, made or refused."""
        return [reg for (_, owner, _), reg in self._entries.items() if owner == node]

    def refused_items(self) -> list[tuple[str, tuple]]:
        """The refused registrations, oldest first (kept across a restart in the state file)."""
        return [(self._entries[key].method, self._entries[key].params) for key in self._refused]

    def made_items(self) -> list[tuple[str, tuple]]:
        """The registrations rosmaster holds (kept across a restart in the state file: a
        grant removed and given back makes them again, a node dead meanwhile has them
        withdrawn, whether or not this interceptor restarted in between)."""
        return [(reg.method, reg.params) for reg in self._entries.values() if not reg.refused]

    def released(self, method: str, params: tuple) -> None:
        """The node unregistered it (an ``unregister*`` call), or it is gone."""
        key = _key(method, params)
        if key is not None:
            self._entries.pop(key, None)
            self._refused.pop(key, None)

    def _put(self, method: str, params: tuple, *, refused: bool) -> None:
        key = _key(method, params)
        if key is None or method not in REGISTER:
            return
        self._refused.pop(key, None)
        if key not in self._entries and len(self._entries) >= self.max_entries:
            if not refused or not self._refused:
                self.dropped += 1
                return
            self._entries.pop(self._oldest_refused())  # a refused one makes room
        if refused:
            if len(self._refused) >= self.max_refused:
                self._entries.pop(self._oldest_refused(), None)
            self._refused[key] = None
        self._entries[key] = Registration(method=method, params=tuple(params), refused=refused)

    def _oldest_refused(self) -> Key:
        key = next(iter(self._refused))
        del self._refused[key]
        self.dropped += 1
        return key

    def to_resend(self, covered_now: Callable[[Registration], bool],
                  covered_before: Callable[[Registration], bool] | None) -> list[Registration]:
        """What to make again after a change of our grants: every refused registration
        the new grants cover, and every one made that they cover and the old ones did not
        (``covered_before`` None: the old grants are not known; only the refused).
        Services first, then publications, then subscriptions (a subscriber told its
        publishers finds them registered)."""
        order = {"registerService": 0, "registerPublisher": 1, "registerSubscriber": 2}
        out = [
            reg for reg in self._entries.values()
            if covered_now(reg) and (reg.refused or (covered_before is not None and not covered_before(reg)))
        ]
        return sorted(out, key=lambda reg: order[reg.method])


__all__ = ["LocalRegistrations", "REGISTER", "RELEASE", "Registration", "covers"]
